//! What the merger publishes after a window, as messages of the client contract: every
//! frame's pose with its revision (a pose that moves is published again with the next
//! revision), the keyframe trajectory, the points the window changed and the whole map for
//! late joiners' snapshot. The service hands them to `egoslam_egress` and writes the same
//! [`MapState`] to its result files.

use super::frames::{posed_frames, posed_keyframes, FrameIndex, PosedFrame};
use crate::{MapBuilder, PointConfidence};
use egoslam_geometry::StampedPose;
use egoslam_messages::v1 as pb;
use egoslam_relocalization::wire::{pose_to_pb, vec3_to_pb};
use nalgebra::Vector3;
use std::collections::{BTreeMap, HashMap};
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

    /// The messages of this state: poses new or moved since `revisions` last saw them
    /// (recorded there), and the rest at their current revisions; `changed_points` are the
    /// tracks the window brought.
    pub fn publication(&self, revisions: &mut Revisions, changed_points: &[u64]) -> Publication {
        let poses = revisions.changed(&self.frames);
        let trajectory = |v: &[PosedFrame]| pb::Trajectory {
            poses: v
                .iter()
                .map(|f| message(f, revisions.revision(f.frame_id)))
                .collect(),
        };
        let all: BTreeMap<u64, Vector3<f64>> = self.points.iter().copied().collect();
        let point = |track: u64, x: &Vector3<f64>| {
            let confidence = self.confidence.as_ref().and_then(|c| c.get(&track));
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
        Publication {
            poses,
            keyframes: trajectory(&self.keyframes),
            frames: trajectory(&self.frames),
            changed_points: changed_points
                .iter()
                .filter_map(|t| all.get(t).map(|x| point(*t, x)))
                .collect(),
            map: pb::MapPoints {
                points: self.points.iter().map(|(t, x)| point(*t, x)).collect(),
            },
        }
    }
}

/// One window's messages ([`MapState::publication`]).
pub struct Publication {
    /// Frames whose pose is new (revision 0) or moved (the next revision).
    pub poses: Vec<pb::Pose>,
    /// Every keyframe at its current revision.
    pub keyframes: pb::Trajectory,
    /// Every frame at its current revision (the snapshot's).
    pub frames: pb::Trajectory,
    /// The points the window brought, as the map now has them.
    pub changed_points: Vec<pb::MapPoint>,
    /// Every point (the snapshot's).
    pub map: pb::MapPoints,
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

    pub fn revision(&self, frame_id: u64) -> u32 {
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
