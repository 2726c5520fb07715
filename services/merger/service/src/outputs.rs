//! What the merger writes and publishes after a window: result files, stats and (when
//! enabled) zenoh, all from one snapshot of the map.

use crate::map_state::{self, MapState, PublishedPoints, Revisions, TrajectoryRows};
use egoslam_egress::Egress;
use egoslam_geometry::PinholeRadtan;
use egoslam_merger::session::frame_poses::FramePoseTracker;
use egoslam_merger::session::frame_retirement::{map_keyframe_frames, retire_frames};
use egoslam_merger::session::frames::PosedFrame;
use egoslam_merger::MergerState;
use egoslam_merger::{point_confidence, PointConfidence, PointConfidenceOptions};
use egoslam_messages::v1 as pb;
use egoslam_runtime::ServiceStats;
use std::collections::HashMap;
use std::path::Path;
use std::sync::{Arc, Mutex};

/// Files, stats and (when enabled) zenoh, from one snapshot of the map.
pub(super) struct Outputs {
    /// Shared with the live tracker (`live_tracking.rs`), which publishes revision 0.
    pub(super) egress: Option<Arc<Egress>>,
    pub(super) revisions: Arc<Mutex<Revisions>>,
    /// Which frames' poses to compute again after a window.
    pub(super) frame_poses: FramePoseTracker,
    /// Where each map point was last published (a new or moved point goes out again).
    pub(super) published_points: PublishedPoints,
    /// Which map points map.ply holds (zenoh carries all, with their confidence).
    pub(super) point_confidence: PointConfidenceOptions,
    /// The last scores of the map's points (recomputed when the files are written).
    pub(super) confidence: Option<Arc<HashMap<u64, PointConfidence>>>,
    /// Carried by every status message (`Status.run_id`).
    pub(super) run_id: String,
    /// Also write map_all.ply (`--map-all-points`).
    pub(super) all_points: bool,
    /// Frames this much stream time older than the newest are final and leave memory
    /// (`--frame-horizon-min`; infinite: never).
    pub(super) frame_horizon_s: f64,
}

/// Retires the frames past the horizon (egoslam_merger::session::frame_retirement) from
/// the state and the revisions; returns those the map posed, at their final poses.
fn retire(
    merger: &mut MergerState,
    horizon_s: f64,
    revisions: &mut Revisions,
    stats: &mut ServiceStats,
) -> Vec<PosedFrame> {
    let start = std::time::Instant::now();
    let Some(retirement) = retire_frames(merger, horizon_s) else {
        return Vec::new();
    };
    let retired = revisions.retire(retirement.before, &map_keyframe_frames(merger));
    stats.add_time("retire_frames", start.elapsed().as_secs_f64() * 1e3);
    merger.retired.posed += retired.len() as u64;
    stats.count("retired_frames", retirement.frames as u64);
    stats.count("unposed_frames", retirement.pending as u64);
    tracing::debug!(
        before = retirement.before,
        frames = retirement.frames,
        posed = retired.len(),
        "frames retired past the horizon"
    );
    retired
}

/// Each described track's grey level: the centre of its patch (relocalization's patches,
/// kept in the keyframe that first described the track).
fn grey_levels(merger: &MergerState) -> HashMap<u64, u8> {
    merger.patched_tracks.values().flatten().copied().collect()
}

impl Outputs {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn emit(
        &mut self,
        out: &Path,
        merger: &mut MergerState,
        camera: Option<&PinholeRadtan>,
        state: pb::ServiceState,
        stats: &mut ServiceStats,
        persist: bool,
    ) -> anyhow::Result<u64> {
        if !persist && self.egress.is_none() {
            return Ok(0); // nobody reads the poses of every frame now: don't compute them
        }
        let update = stats.time("pose_frames", || {
            self.frame_poses.update(&merger.map, &mut merger.frames)
        });
        let (poses, retired, frames, posed_frames) = {
            let mut revisions = self
                .revisions
                .lock()
                .map_err(|_| anyhow::anyhow!("revisions poisoned"))?;
            let poses = stats.time("record_poses", || revisions.record(&update));
            // Retired only when the files are written: trajectory.tum takes their final
            // poses before the checkpoint forgets them.
            let retired = match persist {
                true => retire(merger, self.frame_horizon_s, &mut revisions, stats),
                false => Vec::new(),
            };
            // Every frame only for the files (at most every 5 s, O(frames) as the files).
            let frames: Vec<PosedFrame> = match persist {
                true => revisions.posed_frames().map(|(f, _)| f).collect(),
                false => Vec::new(),
            };
            (poses, retired, frames, revisions.posed_count())
        };
        let posed_frames = posed_frames + merger.retired.posed as usize;
        let (map, index) = (&merger.map, &merger.frames);
        let mut snapshot = MapState::of(map, update.keyframes);
        if let Some(camera) = camera {
            // Scoring every point is a pass over every observation: done when the files
            // are written (at most every 5 s, and at the end); in between, a new point
            // goes out over zenoh without its figure and the last scores serve the rest.
            if persist || self.confidence.is_none() {
                let scored = stats.time("point_confidence", || {
                    point_confidence(map, camera, &self.point_confidence)
                });
                self.confidence = Some(Arc::new(scored));
            }
        }
        if let Some(confidence) = &self.confidence {
            snapshot = snapshot.with_confidence(Arc::clone(confidence));
        }
        let mut written_bytes = 0;
        if persist {
            let grey = grey_levels(merger);
            let trajectory = TrajectoryRows {
                head_len: merger.retired.trajectory_bytes,
                retired: &retired,
                live: &frames,
            };
            let written = map_state::write_files(
                &snapshot,
                trajectory,
                out,
                &self.point_confidence,
                self.all_points,
                &|track| grey.get(&track).copied(),
            )?;
            written_bytes = written.bytes;
            merger.retired.trajectory_bytes = written.trajectory_head_len;
            stats
                .counters
                .insert("published_points".into(), written.published_points as u64);
        }
        stats.frames = index.frames.len() as u64 + merger.retired.frames;
        stats.keyframes = snapshot.keyframes.len() as u64;
        stats
            .counters
            .insert("posed_frames".into(), posed_frames as u64);
        stats
            .counters
            .insert("segments".into(), map.live_segments() as u64);
        // Derived from the map (segments made, segments left), so that it survives a
        // merger restart like the map itself.
        stats.counters.insert(
            "breaks_healed".into(),
            u64::from(map.segments()).saturating_sub(map.live_segments() as u64),
        );
        stats
            .counters
            .insert("map_points".into(), snapshot.points.len() as u64);
        if persist {
            stats.write(out)?;
        }
        if let Some(egress) = &self.egress {
            let status = pb::Status {
                service: "merger".into(),
                state: state as i32,
                frames: posed_frames as u64,
                keyframes: snapshot.keyframes.len() as u64,
                windows: stats.windows,
                message: format!(
                    "{} segment(s), {} map points",
                    map.live_segments(),
                    snapshot.points.len()
                ),
                run_id: self.run_id.clone(),
            };
            stats.count("poses_published", poses.len() as u64);
            let changed = merger.map.take_changed_points();
            let changed_points = stats.time("find_changed_points", || {
                self.published_points.changed(&merger.map, &changed)
            });
            let publication = stats.time("publication", || {
                snapshot.publication(poses, &changed_points, &self.revisions)
            });
            stats.time("publish", || {
                map_state::publish(egress, publication, &status)
            })?;
        }
        Ok(written_bytes)
    }
}
