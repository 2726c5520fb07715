//! The merger service: window solutions from the bus -> one map -> result files and zenoh.
//!
//! Files are rewritten (atomically) after every window, so a crash or kill loses at most the
//! window in flight; the same state goes out over zenoh (docs/egress.md).

use crate::cli::ServiceArgs;
use crate::convert::{pose_from_pb, vec3_from_pb};
use crate::map_state::{self, FrameIndex, MapState, Revisions};
use crate::stats::ServiceStats;
use anyhow::bail;
use egoslam_bus::{Bus, BusOptions, MessageSubscriber, WINDOWS};
use egoslam_egress::{Egress, EgressOptions};
use egoslam_geometry::PinholeRadtan;
use egoslam_merger::{MapBuilder, RefinementOptions, WindowInput, WindowOutcome};
use egoslam_messages::v1 as pb;
use nalgebra::Point2;
use std::path::Path;

/// Files, stats and (when enabled) zenoh, from one snapshot of the map.
struct Outputs {
    egress: Option<Egress>,
    revisions: Revisions,
}

impl Outputs {
    fn emit(
        &mut self,
        out: &Path,
        map: &MapBuilder,
        index: &FrameIndex,
        changed_points: &[u64],
        state: pb::ServiceState,
        stats: &mut ServiceStats,
    ) -> anyhow::Result<()> {
        let snapshot = MapState::of(map, index);
        snapshot.write_files(out)?;
        stats.frames = index.frames.len() as u64;
        stats.keyframes = snapshot.keyframes.len() as u64;
        stats
            .counters
            .insert("posed_frames".into(), snapshot.frames.len() as u64);
        stats
            .counters
            .insert("segments".into(), u64::from(map.segments()));
        stats
            .counters
            .insert("map_points".into(), snapshot.points.len() as u64);
        stats.write(out)?;
        if let Some(egress) = &self.egress {
            let status = pb::Status {
                service: "merger".into(),
                state: state as i32,
                frames: snapshot.frames.len() as u64,
                keyframes: snapshot.keyframes.len() as u64,
                windows: stats.windows,
                message: format!(
                    "{} segment(s), {} map points",
                    map.segments(),
                    snapshot.points.len()
                ),
            };
            map_state::publish(
                egress,
                &snapshot,
                &mut self.revisions,
                changed_points,
                &status,
            )?;
        }
        Ok(())
    }
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
    let egress = if args.egress.zenoh_listen.iter().any(|e| e == "none") {
        None
    } else {
        let e = Egress::open(&EgressOptions {
            device: args.egress.device.clone(),
            listen: args.egress.zenoh_listen.clone(),
            connect: args.egress.zenoh_connect.clone(),
        })?;
        tracing::info!(prefix = e.prefix(), listen = ?args.egress.zenoh_listen, "publishing over zenoh");
        Some(e)
    };
    let mut outputs = Outputs {
        egress,
        revisions: Revisions::default(),
    };
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
        let changed: Vec<u64> = w.points.iter().map(|p| p.track_id).collect();
        let write_start = std::time::Instant::now();
        outputs.emit(
            &args.out,
            &map,
            &frames,
            &changed,
            pb::ServiceState::Running,
            &mut stats,
        )?;
        stats.add_time("write", write_start.elapsed().as_secs_f64() * 1e3);
    }
    outputs.emit(
        &args.out,
        &map,
        &frames,
        &[],
        pb::ServiceState::Finished,
        &mut stats,
    )?;
    tracing::info!(
        windows = stats.windows,
        segments = map.segments(),
        "merger finished"
    );
    Ok(())
}
