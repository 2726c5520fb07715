//! The merger service: window solutions from the bus -> one map -> result files.
//!
//! Files are rewritten (atomically) after every window, so a crash or kill loses at most the
//! window in flight.

use crate::cli::ServiceArgs;
use crate::convert::{pose_from_pb, vec3_from_pb};
use crate::output::{ply_text, tum_text, write_atomically};
use crate::stats::ServiceStats;
use anyhow::bail;
use egoslam_bus::{Bus, BusOptions, MessageSubscriber, WINDOWS};
use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_merger::{
    interpolate_frames, MapBuilder, RefinementOptions, WindowInput, WindowOutcome,
};
use egoslam_messages::v1 as pb;
use nalgebra::Point2;
use std::collections::BTreeMap;
use std::path::Path;

/// Every frame known to the merger: frame id -> timestamp.
#[derive(Default)]
struct FrameIndex {
    frames: BTreeMap<u64, f64>,
}

impl FrameIndex {
    fn add_stamp(&mut self, k: &pb::KeyframeStamp) {
        self.frames.insert(k.frame_id, k.timestamp_s);
        for (id, t) in k
            .frames_since_previous_ids
            .iter()
            .zip(&k.frames_since_previous_timestamps_s)
        {
            self.frames.insert(*id, *t);
        }
    }
}

fn write_outputs(
    out: &Path,
    map: &MapBuilder,
    frames: &FrameIndex,
    stats: &mut ServiceStats,
) -> anyhow::Result<()> {
    let keyframes: Vec<(u32, StampedPose)> = map.keyframes().map(|(_, s, p)| (s, *p)).collect();
    let mut sorted = keyframes.clone();
    sorted.sort_by(|a, b| a.1.timestamp.total_cmp(&b.1.timestamp));
    let stamps: Vec<f64> = frames.frames.values().copied().collect();
    let posed: Vec<StampedPose> = interpolate_frames(&sorted, &stamps)
        .into_iter()
        .map(|(_, p, _)| p)
        .collect();
    let kf_poses: Vec<StampedPose> = sorted.iter().map(|(_, p)| *p).collect();
    let points: Vec<_> = map.points().map(|(_, _, x)| *x).collect();
    write_atomically(&out.join("trajectory.tum"), tum_text(&posed).as_bytes())?;
    write_atomically(&out.join("keyframes.tum"), tum_text(&kf_poses).as_bytes())?;
    write_atomically(&out.join("map.ply"), ply_text(&points).as_bytes())?;
    stats.frames = frames.frames.len() as u64;
    stats.keyframes = kf_poses.len() as u64;
    stats
        .counters
        .insert("posed_frames".into(), posed.len() as u64);
    stats
        .counters
        .insert("segments".into(), u64::from(map.segments()));
    stats
        .counters
        .insert("map_points".into(), points.len() as u64);
    stats.write(out)
}

pub fn run(args: ServiceArgs) -> anyhow::Result<()> {
    let mut stats = ServiceStats::new("merger");
    std::fs::create_dir_all(&args.out)?;
    let bus = Bus::open(
        "merger",
        BusOptions {
            namespace: args.namespace.clone(),
            ..BusOptions::default()
        },
    )?;
    let mut windows = MessageSubscriber::<pb::WindowSolution>::create(&bus, WINDOWS)?;
    let mut map = MapBuilder::new();
    let mut frames = FrameIndex::default();
    loop {
        let Some(w) = windows.receive()? else {
            bail!("terminated by signal")
        };
        for k in &w.keyframes {
            frames.add_stamp(k);
        }
        for f in &w.trailing_frames {
            frames.frames.insert(f.frame_id, f.timestamp_s);
        }
        if w.end_of_stream {
            break;
        }
        stats.windows += 1;
        let status = w
            .quality
            .as_ref()
            .map_or(pb::SolveStatus::Unspecified, |q| q.status());
        if status == pb::SolveStatus::Solved && !w.poses.is_empty() {
            let input = WindowInput {
                poses: w
                    .poses
                    .iter()
                    .filter_map(|kp| kp.pose.as_ref().map(|p| (kp.keyframe_id, pose_from_pb(p))))
                    .collect(),
                points: w
                    .points
                    .iter()
                    .map(|p| (p.track_id, vec3_from_pb(&p.position)))
                    .collect(),
                observations: w
                    .observations
                    .iter()
                    .map(|o| {
                        (
                            o.keyframe_id,
                            o.track_id,
                            Point2::new(f64::from(o.x), f64::from(o.y)),
                        )
                    })
                    .collect(),
            };
            let outcome = stats.time("align", || map.add_window(&input));
            match outcome {
                WindowOutcome::NewSegment { segment } => {
                    tracing::info!(window = w.window_id, segment, "new map segment")
                }
                WindowOutcome::Aligned {
                    residual,
                    transform,
                    ..
                } => {
                    tracing::debug!(
                        window = w.window_id,
                        residual,
                        scale = transform.scale,
                        "window aligned"
                    );
                    let camera = w.intrinsics.as_ref().and_then(|i| {
                        PinholeRadtan::new(i.width, i.height, [i.fx, i.fy, i.cx, i.cy], [0.0; 5])
                            .ok()
                    });
                    let refine = RefinementOptions {
                        keyframes: args.pipeline.refine_keyframes,
                        ..RefinementOptions::default()
                    };
                    if let (Some(camera), true) = (camera, refine.keyframes > 0) {
                        let refined = stats.time("refine", || map.refine_recent(&camera, &refine));
                        if let Some(r) = refined {
                            tracing::info!(
                                window = w.window_id,
                                keyframes = r.keyframes,
                                points = r.points,
                                rmse_px = r.rmse_px,
                                outliers = r.outliers,
                                "recent keyframes refined"
                            );
                        }
                    }
                }
            }
        } else {
            let reason = w
                .quality
                .as_ref()
                .map(|q| q.reason.clone())
                .unwrap_or_default();
            tracing::warn!(window = w.window_id, ?status, %reason, "window not solved: map breaks here");
            stats.count("unsolved_windows", 1);
            map.break_segment();
        }
        let write_start = std::time::Instant::now();
        write_outputs(&args.out, &map, &frames, &mut stats)?;
        stats.add_time("write", write_start.elapsed().as_secs_f64() * 1e3);
    }
    write_outputs(&args.out, &map, &frames, &mut stats)?;
    tracing::info!(
        windows = stats.windows,
        segments = map.segments(),
        "merger finished"
    );
    Ok(())
}
