//! The merger's current results in one place: keyframe and frame poses (with revisions),
//! points; written to files and published over zenoh from the same values.

use crate::output::tum_text;
use egoslam_durability::write_atomically;
use egoslam_egress::Egress;
use egoslam_export::map_ply::{self, MapPlyPoint};
use egoslam_geometry::StampedPose;
use egoslam_merger::session::frames::{posed_frames, posed_keyframes, FrameIndex, PosedFrame};
use egoslam_merger::{MapBuilder, PointConfidence, PointConfidenceOptions};
use egoslam_messages::v1 as pb;
use egoslam_relocalization::wire::{pose_to_pb, vec3_to_pb};
use nalgebra::Vector3;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::Arc;

/// The results at one moment.
pub struct MapState {
    pub keyframes: Vec<PosedFrame>,
    pub frames: Vec<PosedFrame>,
    pub points: Vec<(u64, Vector3<f64>)>,
    /// How well each point is known, once attached ([`MapState::with_confidence`]).
    pub confidence: Option<Arc<HashMap<u64, PointConfidence>>>,
}

impl MapState {
    pub fn of(map: &MapBuilder, index: &FrameIndex) -> Self {
        let keyframes = posed_keyframes(map, index);
        let frames = posed_frames(map, index, &keyframes, ..);
        let points = map.points().map(|(track, _, x)| (track, *x)).collect();
        Self {
            keyframes,
            frames,
            points,
            confidence: None,
        }
    }

    /// Attaches how well each point is known (point_confidence.rs): map.ply keeps the
    /// known ones, zenoh carries every point with its standard deviation.
    pub fn with_confidence(mut self, confidence: Arc<HashMap<u64, PointConfidence>>) -> Self {
        self.confidence = Some(confidence);
        self
    }

    /// The points as map.ply holds them: with their views, relative standard deviation
    /// and grey level (`grey`, from the images); only those known within `options` unless
    /// `all` (every point when no confidence was attached, as before the first window
    /// brought the camera).
    fn ply_points(
        &self,
        options: &PointConfidenceOptions,
        all: bool,
        grey: &dyn Fn(u64) -> Option<u8>,
    ) -> Vec<MapPlyPoint> {
        self.points
            .iter()
            .filter_map(|(track, p)| {
                let confidence = self.confidence.as_ref().and_then(|c| c.get(track));
                let known =
                    self.confidence.is_none() || confidence.is_some_and(|c| c.is_known(options));
                (all || known).then(|| {
                    let g = grey(*track).unwrap_or(128);
                    MapPlyPoint {
                        position: [p.x as f32, p.y as f32, p.z as f32],
                        colour: [g; 3],
                        views: confidence.map_or(0, |c| c.views),
                        relative_std: confidence
                            .and_then(|c| c.relative_std)
                            .map_or(f32::NAN, |s| s as f32),
                    }
                })
            })
            .collect()
    }

    /// trajectory.tum, keyframes.tum, keyframe_segments.txt, map.ply, each written
    /// atomically. The segments file says which map segment (own gauge and scale) each
    /// keyframe is in, so that a run with breaks can be evaluated segment by segment.
    /// Returns the number of points map.ply holds.
    pub fn write_files(
        &self,
        out: &Path,
        published: &PointConfidenceOptions,
        all_points: bool,
        grey: &dyn Fn(u64) -> Option<u8>,
    ) -> anyhow::Result<usize> {
        let poses = |v: &[PosedFrame]| v.iter().map(|f| f.pose).collect::<Vec<_>>();
        let points = self.ply_points(published, false, grey);
        let published_points = points.len();
        write_atomically(
            &out.join("trajectory.tum"),
            tum_text(&poses(&self.frames)).as_bytes(),
        )?;
        write_atomically(
            &out.join("keyframes.tum"),
            tum_text(&poses(&self.keyframes)).as_bytes(),
        )?;
        let mut segments = String::from("# timestamp segment\n");
        for k in &self.keyframes {
            segments += &format!("{:.6} {}\n", k.pose.timestamp, k.segment);
        }
        write_atomically(&out.join("keyframe_segments.txt"), segments.as_bytes())?;
        write_atomically(
            &out.join("map.ply"),
            &map_ply::to_bytes(points, "egoslam map points (docs/merger.md)")?,
        )?;
        if all_points {
            let all = self.ply_points(published, true, grey);
            write_atomically(
                &out.join("map_all.ply"),
                &map_ply::to_bytes(all, "egoslam: every triangulated point")?,
            )?;
        }
        Ok(published_points)
    }
}

/// Revision bookkeeping: which frame poses are new or changed since last published.
#[derive(Default)]
pub struct Revisions {
    published: BTreeMap<u64, (StampedPose, u32)>,
}

impl Revisions {
    /// The frames whose pose is new (revision 0) or moved (revision + 1), as messages.
    pub fn changed(&mut self, frames: &[PosedFrame]) -> Vec<pb::Pose> {
        let mut out = Vec::new();
        for f in frames {
            let revision = match self.published.get(&f.frame_id) {
                None => 0,
                Some((old, rev)) => {
                    let moved = (old.position - f.pose.position).norm() > 1e-9
                        || old.rotation.angle_to(&f.pose.rotation) > 1e-9;
                    if !moved {
                        continue;
                    }
                    rev + 1
                }
            };
            self.published.insert(f.frame_id, (f.pose, revision));
            out.push(message(f, revision));
        }
        out
    }

    /// Records the live tracker's pose of a frame as its revision 0; `false` (nothing
    /// recorded) when the frame was already published, by a window that came first.
    pub fn claim_live(&mut self, frame_id: u64, pose: &StampedPose) -> bool {
        if self.published.contains_key(&frame_id) {
            return false;
        }
        self.published.insert(frame_id, (*pose, 0));
        true
    }

    /// The last published revision of every frame (what a checkpoint keeps).
    pub fn numbers(&self) -> BTreeMap<u64, u32> {
        self.published.iter().map(|(f, (_, r))| (*f, *r)).collect()
    }

    /// Revisions of a restarted merger: the checkpointed numbers, with the resumed poses, so
    /// that a pose that moves later is published with a higher revision than any the
    /// clients already hold (they keep the highest).
    pub fn resume(numbers: &BTreeMap<u64, u32>, state: &MapState) -> Self {
        let published = state
            .frames
            .iter()
            .filter_map(|f| numbers.get(&f.frame_id).map(|r| (f.frame_id, (f.pose, *r))))
            .collect();
        Self { published }
    }

    fn revision(&self, frame_id: u64) -> u32 {
        self.published.get(&frame_id).map_or(0, |p| p.1)
    }
}

fn message(f: &PosedFrame, revision: u32) -> pb::Pose {
    pb::Pose {
        revision,
        interpolated: f.interpolated,
        ..pose_to_pb(f.frame_id, f.segment, &f.pose)
    }
}

/// Publishes what changed, the keyframe trajectory and the window's points, refreshes the
/// snapshot, and publishes the status.
pub fn publish(
    egress: &Egress,
    state: &MapState,
    revisions: &mut Revisions,
    changed_points: &[u64],
    status: &pb::Status,
) -> anyhow::Result<()> {
    let poses = revisions.changed(&state.frames);
    egress.publish_poses(&poses)?;
    let trajectory = |v: &[PosedFrame]| pb::Trajectory {
        poses: v
            .iter()
            .map(|f| message(f, revisions.revision(f.frame_id)))
            .collect(),
    };
    let keyframes = trajectory(&state.keyframes);
    egress.publish_trajectory(&keyframes)?;
    let all: BTreeMap<u64, Vector3<f64>> = state.points.iter().copied().collect();
    let point = |track: u64, x: &Vector3<f64>| {
        let confidence = state.confidence.as_ref().and_then(|c| c.get(&track));
        pb::MapPoint {
            track_id: track,
            position: Some(vec3_to_pb(x)),
            observations: confidence.map_or(0, |c| c.views),
            relative_std: confidence.and_then(|c| c.relative_std),
            largest_reprojection_sigmas: confidence
                .map(|c| c.largest_reprojection_sigmas)
                .filter(|s| s.is_finite()),
        }
    };
    let changed: Vec<pb::MapPoint> = changed_points
        .iter()
        .filter_map(|t| all.get(t).map(|x| point(*t, x)))
        .collect();
    egress.publish_map(&changed)?;
    // The snapshot before the status: a client that sees "finished" and then asks for the
    // snapshot (to fill what its subscription dropped) must get the final state.
    egress.set_snapshot(&pb::Snapshot {
        keyframes: Some(keyframes),
        frames: Some(trajectory(&state.frames)),
        map: Some(pb::MapPoints {
            points: state.points.iter().map(|(t, x)| point(*t, x)).collect(),
        }),
        status: Some(status.clone()),
    });
    egress.publish_status(status)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    fn frame(id: u64, x: f64) -> PosedFrame {
        PosedFrame {
            frame_id: id,
            segment: 0,
            pose: StampedPose {
                timestamp: id as f64,
                position: Vector3::new(x, 0.0, 0.0),
                rotation: UnitQuaternion::identity(),
            },
            interpolated: false,
        }
    }

    #[test]
    fn a_restarted_merger_keeps_counting_revisions_up() {
        let mut before = Revisions::default();
        assert_eq!(before.changed(&[frame(1, 0.0), frame(2, 0.0)]).len(), 2);
        let moved = before.changed(&[frame(1, 0.5), frame(2, 0.0)]);
        assert_eq!((moved.len(), moved[0].revision), (1, 1));
        // Kill and restart: the checkpointed numbers and the resumed poses.
        let state = MapState {
            keyframes: Vec::new(),
            frames: vec![frame(1, 0.5), frame(2, 0.0)],
            points: Vec::new(),
            confidence: None,
        };
        let mut after = Revisions::resume(&before.numbers(), &state);
        assert!(after.changed(&state.frames).is_empty(), "nothing moved");
        let moved = after.changed(&[frame(1, 0.7), frame(2, 0.1), frame(3, 0.0)]);
        let revisions: Vec<(u64, u32)> = moved.iter().map(|p| (p.frame_id, p.revision)).collect();
        assert_eq!(revisions, vec![(1, 2), (2, 1), (3, 0)]);
    }
}
