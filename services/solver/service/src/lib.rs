//! The window solver service: keyframes from the bus -> windows -> solutions on the bus.
//! The geometry is `egoslam_solver::window_solver`; this crate only converts, journals and
//! publishes.

pub mod intrinsics_estimation;
mod resume;

use anyhow::bail;
use egoslam_bus::{Bus, BusOptions, MessagePublisher, MessageSubscriber, KEYFRAMES, WINDOWS};
use egoslam_durability::log_compaction;
use egoslam_durability::window_journal::{self, JournalWriter};
use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_messages::internal::v1 as internal;
use egoslam_messages::v1 as pb;
use egoslam_relocalization::patch_alignment::PATCH_SIDE;
use egoslam_relocalization::wire::{pose_to_pb, vec3_to_pb};
use egoslam_runtime::ServiceStats;
use egoslam_solver::view_graph::{EdgeCache, KeyframeObservations};
use egoslam_solver::window_solver::{solve_window, WindowSolverOptions, WindowStatus};
use egoslam_solver::windowing::Window;
use egoslam_solver::{WindowBuilder, WindowOptions};
use nalgebra::{Point2, UnitQuaternion};
use std::path::PathBuf;

/// What a solver service is told (the launcher's `egoslam solver` flags, docs/config.md).
#[derive(Debug, Clone)]
pub struct SolverServiceOptions {
    /// Bus namespace (iceoryx2 service names egoslam/<namespace>/...).
    pub namespace: String,
    /// Output folder: statistics, and the state folder (journal, compaction marks).
    pub out: PathBuf,
    /// Keyframes per window and the overlap between successive windows.
    pub windows: WindowOptions,
    /// Keyframes apart that local loop-closure edges may span.
    pub loop_closure_span: usize,
    /// Self-calibrations to estimate from the stream's first frames
    /// (intrinsics_estimation.rs); `None`: none.
    pub estimate_intrinsics: Option<intrinsics_estimation::IntrinsicsRequest>,
}

/// Timing facts of a keyframe, for the merger's per-frame trajectory.
fn stamp(k: &internal::Keyframe) -> internal::KeyframeStamp {
    internal::KeyframeStamp {
        keyframe_id: k.keyframe_id,
        frame_id: k.frame_id,
        timestamp_s: k.timestamp_s,
        frames_since_previous_ids: k.frames_since_previous.iter().map(|f| f.frame_id).collect(),
        frames_since_previous_timestamps_s: k
            .frames_since_previous
            .iter()
            .map(|f| f.timestamp_s)
            .collect(),
        frames_since_previous: k.frames_since_previous.clone(),
    }
}

/// The ideal pinhole camera of the undistorted track positions.
fn pinhole(k: &internal::Keyframe) -> anyhow::Result<PinholeRadtan> {
    let Some(i) = &k.intrinsics else {
        bail!("keyframe {} has no intrinsics", k.keyframe_id)
    };
    Ok(PinholeRadtan::new(
        i.width,
        i.height,
        [i.fx, i.fy, i.cx, i.cy],
        [0.0; 5],
    )?)
}

/// Windows whose end moves out of a fast turn (`WindowBuilder::with_adaptive_end`) and that
/// end at a track break (`WindowBuilder::with_track_breaks`): a keyframe sharing fewer
/// tracks with the one before than a relative pose needs (`min_matches`).
fn windows(
    builder: WindowBuilder<internal::Keyframe>,
    min_matches: usize,
) -> WindowBuilder<internal::Keyframe> {
    builder
        .with_adaptive_end(overlap_strength)
        .with_track_breaks(shared_tracks, min_matches)
}

/// Tracks two keyframes both see.
fn shared_tracks(a: &internal::Keyframe, b: &internal::Keyframe) -> usize {
    tracks_seen_by_all(a, std::iter::once(b))
}

/// Tracks seen by every keyframe of `overlap`: how firmly the keyframes two windows share
/// are tied to both windows' points.
fn overlap_strength(overlap: &[internal::Keyframe]) -> usize {
    overlap
        .split_first()
        .map_or(0, |(first, rest)| tracks_seen_by_all(first, rest))
}

/// Tracks of `first` that every keyframe of `rest` sees too.
fn tracks_seen_by_all<'a>(
    first: &internal::Keyframe,
    rest: impl IntoIterator<Item = &'a internal::Keyframe>,
) -> usize {
    let sets: Vec<std::collections::HashSet<u64>> = rest
        .into_iter()
        .map(|k| k.tracks.iter().map(|t| t.track_id).collect())
        .collect();
    first
        .tracks
        .iter()
        .filter(|t| sets.iter().all(|s| s.contains(&t.track_id)))
        .count()
}

/// A keyframe message as the window solver takes it: its tracks' undistorted positions,
/// without those that are not finite or lie far outside the image (counted in `stats` as
/// `invalid_tracks`): they come from another process, and one NaN would spoil a window.
pub fn observations(k: &internal::Keyframe, stats: &mut ServiceStats) -> KeyframeObservations {
    let (observations, rejected) = valid_observations(k);
    if rejected > 0 {
        tracing::warn!(
            keyframe = k.keyframe_id,
            rejected,
            "tracks with invalid positions dropped"
        );
        stats.count("invalid_tracks", rejected as u64);
    }
    observations
}

/// [`observations`] and how many tracks it dropped.
fn valid_observations(k: &internal::Keyframe) -> (KeyframeObservations, usize) {
    let limit = k
        .intrinsics
        .as_ref()
        .map_or(1e6, |i| 4.0 * f64::from(i.width.max(i.height)));
    let tracks: std::collections::BTreeMap<u64, Point2<f64>> = k
        .tracks
        .iter()
        .map(|t| (t.track_id, Point2::new(f64::from(t.x), f64::from(t.y))))
        .filter(|(_, p)| {
            p.x.is_finite() && p.y.is_finite() && p.x.abs() < limit && p.y.abs() < limit
        })
        .collect();
    let rejected = k.tracks.len() - tracks.len();
    let observations = KeyframeObservations {
        id: k.keyframe_id,
        timestamp: k.timestamp_s,
        tracks,
    };
    (observations, rejected)
}

/// Largest displacement of a keyframe from the first, over the median depth of the points
/// seen from the first keyframe (scale-free); 0 when nothing moved or nothing was
/// triangulated.
fn relative_translation(solution: &egoslam_solver::window_solver::WindowSolution) -> f64 {
    let Some(first) = solution.poses.first() else {
        return 0.0;
    };
    let reach = solution
        .poses
        .iter()
        .map(|p| (p.centre - first.centre).norm())
        .fold(0.0, f64::max);
    let mut depths: Vec<f64> = solution
        .points
        .iter()
        .map(|p| first.to_camera(&p.position).z)
        .filter(|z| *z > 0.0)
        .collect();
    if reach == 0.0 || depths.is_empty() {
        return 0.0;
    }
    let mid = depths.len() / 2;
    reach / *depths.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// `(keyframe index in the window, track, pixel)` triples as wire observations.
fn observation_messages(
    kfs: &[internal::Keyframe],
    observations: &[(usize, u64, Point2<f64>)],
) -> Vec<internal::Observation> {
    observations
        .iter()
        .map(|(k, track, px)| internal::Observation {
            keyframe_id: kfs[*k].keyframe_id,
            track_id: *track,
            x: px.x as f32,
            y: px.y as f32,
        })
        .collect()
}

/// The described tracks of a keyframe, with the patches of those first described in it,
/// forwarded once (in the first window holding the keyframe) for the merger's
/// relocalization map.
fn keyframe_features(k: &internal::Keyframe) -> internal::KeyframeFeatures {
    let described: Vec<&internal::TrackObservation> = k
        .tracks
        .iter()
        .filter(|t| t.descriptor.len() == 32)
        .collect();
    let patched: Vec<&&internal::TrackObservation> = described
        .iter()
        .filter(|t| t.patch.len() == PATCH_SIDE * PATCH_SIDE)
        .collect();
    internal::KeyframeFeatures {
        keyframe_id: k.keyframe_id,
        track_ids: described.iter().map(|t| t.track_id).collect(),
        descriptors: described
            .iter()
            .flat_map(|t| t.descriptor.iter().copied())
            .collect(),
        x: described.iter().map(|t| t.x).collect(),
        y: described.iter().map(|t| t.y).collect(),
        patch_track_ids: patched.iter().map(|t| t.track_id).collect(),
        patches: patched
            .iter()
            .flat_map(|t| t.patch.iter().copied())
            .collect(),
    }
}

/// Solves one window and builds its message.
fn solve(
    window_id: u64,
    window: &Window<internal::Keyframe>,
    cache: &mut EdgeCache,
    options: &WindowSolverOptions,
    stats: &mut ServiceStats,
) -> anyhow::Result<internal::WindowSolution> {
    let kfs = &window.keyframes;
    let camera = pinhole(&kfs[0])?;
    let obs: Vec<KeyframeObservations> = kfs.iter().map(|k| observations(k, stats)).collect();
    let first_id = kfs[0].keyframe_id;
    cache.retain(|(a, _), _| *a >= first_id);
    let solution = stats.time("window", || solve_window(&camera, &obs, options, cache));
    for (stage, ms) in &solution.timings_ms {
        stats.add_time(stage, *ms);
    }
    let (status, reason) = match &solution.status {
        WindowStatus::Solved if solution.keyframes.len() < kfs.len() => (
            internal::SolveStatus::Solved,
            format!(
                "partial: {} of {} keyframes (view graph in pieces)",
                solution.keyframes.len(),
                kfs.len()
            ),
        ),
        WindowStatus::Solved => (internal::SolveStatus::Solved, String::new()),
        WindowStatus::RotationOnly(reason) => (
            internal::SolveStatus::Solved,
            format!("rotation only: {reason}"),
        ),
        WindowStatus::Failed(r) => (internal::SolveStatus::Failed, r.clone()),
    };
    tracing::info!(
        window = window_id,
        keyframes = kfs.len(),
        edges = solution.edges,
        translation_edges = solution.translation_edges,
        points = solution.points.len(),
        rmse_px = solution.rmse_px,
        ?status,
        %reason,
        "window solved"
    );
    if status == internal::SolveStatus::Failed {
        stats.count("failed_windows", 1);
    }
    stats
        .window_translations
        .push(relative_translation(&solution));
    if solution.keyframes.len() < kfs.len() && !solution.keyframes.is_empty() {
        stats.count("partial_windows", 1);
    }
    // Poses of the solved keyframes (all, or the largest connected piece of the window).
    let poses = solution
        .keyframes
        .iter()
        .map(|k| &kfs[*k])
        .zip(&solution.poses)
        .map(|(k, p)| internal::KeyframePose {
            keyframe_id: k.keyframe_id,
            pose: Some(pose_to_pb(
                k.frame_id,
                0,
                &StampedPose {
                    timestamp: k.timestamp_s,
                    position: p.centre,
                    rotation: UnitQuaternion::from_rotation_matrix(&p.rotation.inverse()),
                },
            )),
        })
        .collect();
    Ok(internal::WindowSolution {
        window_id,
        keyframe_ids: kfs.iter().map(|k| k.keyframe_id).collect(),
        overlap: window.overlap as u32,
        poses,
        points: solution
            .points
            .iter()
            .map(|p| pb::MapPoint {
                track_id: p.track_id,
                position: Some(vec3_to_pb(&p.position)),
                observations: p.observations,
                relative_std: None,
                largest_reprojection_sigmas: None,
            })
            .collect(),
        observations: observation_messages(kfs, &solution.observations),
        quality: Some(internal::SolutionQuality {
            status: status as i32,
            reason,
            reprojection_rmse_px: solution.rmse_px,
            inlier_observations: solution.observations.len() as u32,
            outlier_observations: solution.outlier_observations as u32,
        }),
        timings: solution
            .timings_ms
            .iter()
            .map(|(stage, ms)| internal::StageTiming {
                stage: stage.to_string(),
                milliseconds: *ms,
            })
            .collect(),
        keyframes: kfs.iter().map(stamp).collect(),
        end_of_stream: false,
        trailing_frames: Vec::new(),
        stream_id: 0, // set when published
        weak_observations: observation_messages(kfs, &solution.weak_observations),
        keyframe_features: kfs[window.overlap.min(kfs.len())..]
            .iter()
            .map(keyframe_features)
            .collect(),
        // The camera as the frontend had it, its lens model included: the window's
        // observations are undistorted pixels of its ideal pinhole, and a saved map
        // records the lens for queries from the same camera (focal.rs).
        intrinsics: kfs[0].intrinsics.clone(),
    })
}

/// Debugging aid: writes a window's keyframes (length-delimited protobuf) so that
/// `cargo run --example solve_window` can replay the solve offline.
fn dump_window(
    dir: &std::path::Path,
    window_id: u64,
    window: &Window<internal::Keyframe>,
) -> anyhow::Result<()> {
    use prost::Message;
    std::fs::create_dir_all(dir)?;
    let mut bytes = Vec::new();
    for k in &window.keyframes {
        k.encode_length_delimited(&mut bytes)?;
    }
    std::fs::write(dir.join(format!("window_{window_id:04}.pb")), bytes)?;
    Ok(())
}

/// A stream id unlikely to repeat across solver starts (clock and process id; never 0,
/// which on the wire means "unset").
fn new_stream_id() -> u64 {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    (nanos ^ (u64::from(std::process::id()) << 40)) | 1
}

/// Runs the solver service until the stream's end (or a signal: an error).
pub fn run(args: SolverServiceOptions) -> anyhow::Result<()> {
    let mut stats = ServiceStats::new("solver");
    let window_options = args.windows;
    let mut options = WindowSolverOptions::default();
    options.view_graph.loop_closure_span = args.loop_closure_span;
    let mut cache = EdgeCache::new();
    let bus = Bus::open(
        "solver",
        BusOptions {
            namespace: args.namespace.clone(),
            ..BusOptions::default()
        },
    )?;
    std::fs::create_dir_all(&args.out)?;
    let state_dir = egoslam_durability::create_state_dir(&args.out)?;
    let journal_path = state_dir.join(window_journal::FILE_NAME);
    // A restarted solver continues its predecessor's stream (docs/durability.md).
    let resume = resume::find(&args.out, &args.namespace, args.windows.overlap)?;
    let (stream_id, mut journal, mut builder, next_sequence, replay, skip_up_to) = match resume {
        Some(r) => {
            tracing::warn!(
                windows = r.windows(),
                replayed_keyframes = r.replay.len(),
                "resuming the stream of a previous solver"
            );
            stats.count("restarts", 1);
            stats.count("replayed_keyframes", r.replay.len() as u64);
            stats.windows = r.windows();
            let last = r.last_keyframe_id();
            (
                r.journal.stream_id,
                JournalWriter::resume(&journal_path, &r.journal)?,
                windows(
                    WindowBuilder::resume(window_options, r.tail)?,
                    options.view_graph.relative_pose.min_matches,
                ),
                r.journal.next_sequence(),
                r.replay,
                last,
            )
        }
        None => {
            let stream_id = new_stream_id();
            (
                stream_id,
                JournalWriter::create(&journal_path, stream_id)?,
                windows(
                    WindowBuilder::new(window_options)?,
                    options.view_graph.relative_pose.min_matches,
                ),
                0,
                Vec::new(),
                None,
            )
        }
    };
    let mut keyframes = MessageSubscriber::<internal::Keyframe>::create(&bus, KEYFRAMES)?;
    let mut windows = MessagePublisher::<internal::WindowSolution>::create(&bus, WINDOWS)?
        .continue_at(next_sequence);
    egoslam_runtime::systemd::ready("solver");
    // Journal first, then send: a message the merger may have received is always in the
    // journal, so a restarted merger can recover it.
    let (merger_mark, solver_mark) = (
        state_dir.join(log_compaction::MERGER_MARK),
        state_dir.join(log_compaction::SOLVER_MARK),
    );
    let overlap = args.windows.overlap;
    let mut schedule = log_compaction::CompactionSchedule::from_env();
    let mut publish = |message: internal::WindowSolution| -> anyhow::Result<()> {
        let message = internal::WindowSolution {
            stream_id,
            ..message
        };
        journal.append(&message)?;
        windows.send(&message)?;
        // A restarted solver now resumes after this window: it reads back its overlap
        // keyframes and those after it, so the frontend may drop older ones.
        let ids = &message.keyframe_ids;
        if let Some(first) = ids[ids.len().saturating_sub(overlap)..].iter().min() {
            log_compaction::write_mark(&solver_mark, stream_id, *first)?;
        }
        if schedule.outgrown(journal.len_bytes()?) {
            let mark = log_compaction::read_mark(&merger_mark).filter(|(s, _)| *s == stream_id);
            if let Some(mark @ (_, next)) = schedule.fresh(mark) {
                let dropped = journal.compact_before(next)?;
                tracing::info!(dropped, "window journal compacted");
                schedule.compacted(mark, journal.len_bytes()?);
            }
        }
        Ok(())
    };
    // A restarted solver does not see the stream's start: it leaves the estimates to the
    // run (which restarts the pipeline when one applies, and then asks again).
    let mut estimation = args
        .estimate_intrinsics
        .clone()
        .filter(|_| replay.is_empty() && skip_up_to.is_none())
        .map(|request| {
            intrinsics_estimation::IntrinsicsEstimation::new(request, state_dir.clone())
        });
    let mut trailing = Vec::new();
    let mut replay = replay.into_iter();
    loop {
        let k = match replay.next() {
            Some(k) => k,
            None => {
                let Some(k) = keyframes.receive()? else {
                    bail!(egoslam_bus::StoppedBySignal { during: "" })
                };
                // Keyframes the replay already took (sent before this solver started).
                if !k.end_of_stream && skip_up_to.is_some_and(|last| k.keyframe_id <= last) {
                    continue;
                }
                k
            }
        };
        let end_of_stream = k.end_of_stream;
        let window = if end_of_stream {
            trailing = k.trailing_frames;
            if let Some(estimation) = &mut estimation {
                estimation.stream_ended();
            }
            builder.finish()
        } else {
            stats.keyframes += 1;
            if let Some(estimation) = &mut estimation {
                estimation.observe(&k);
            }
            builder.push(k)
        };
        if let Some(window) = window {
            // SIGTERM means stop now (a Ctrl-C ends the stream at the replay instead): a
            // backlog of windows is not solved first.
            if egoslam_bus::stop_requested() {
                bail!(egoslam_bus::StoppedBySignal { during: "" })
            }
            if let Some(dir) = std::env::var_os("EGOSLAM_DUMP_WINDOWS") {
                dump_window(std::path::Path::new(&dir), stats.windows, &window)?;
            }
            let solution = solve(stats.windows, &window, &mut cache, &options, &mut stats)?;
            if let Some(estimation) = &mut estimation {
                estimation.share_edges(
                    &cache,
                    &pinhole(&window.keyframes[0])?,
                    &options.view_graph,
                );
            }
            publish(solution)?;
            stats.windows += 1;
        }
        if end_of_stream {
            break;
        }
    }
    if let Some(estimation) = estimation.take() {
        estimation.finish();
    }
    publish(internal::WindowSolution {
        end_of_stream: true,
        trailing_frames: trailing,
        ..Default::default()
    })?;
    tracing::info!(
        keyframes = stats.keyframes,
        windows = stats.windows,
        "solver finished"
    );
    stats.count("dropped_messages", keyframes.dropped());
    stats.write(&args.out)?;
    // Stay until the merger has read everything (see MessagePublisher::finish).
    if !windows.finish() {
        bail!(egoslam_bus::StoppedBySignal {
            during: " while the merger was reading the last windows"
        })
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tracks_with_invalid_positions_are_dropped_and_counted() {
        let track = |id: u64, x: f32, y: f32| internal::TrackObservation {
            track_id: id,
            x,
            y,
            ..Default::default()
        };
        let k = internal::Keyframe {
            keyframe_id: 3,
            intrinsics: Some(pb::Intrinsics {
                width: 640,
                height: 480,
                ..Default::default()
            }),
            tracks: vec![
                track(1, 10.0, 20.0),
                track(2, f32::NAN, 5.0),
                track(3, 5.0, f32::INFINITY),
                track(4, 1e9, 5.0),
                track(5, -3.0, 479.5),
            ],
            ..Default::default()
        };
        let mut stats = ServiceStats::new("solver");
        let o = observations(&k, &mut stats);
        assert_eq!(o.tracks.keys().copied().collect::<Vec<_>>(), vec![1, 5]);
        assert_eq!(stats.counters.get("invalid_tracks"), Some(&3));
    }
}
