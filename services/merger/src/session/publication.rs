//! What the merger publishes after a window, as messages of the client contract: every
//! frame's pose with its revision (a pose that moves is published again with the next
//! revision), the keyframe trajectory, the points new or moved since last published and
//! the whole map for late joiners' snapshot. The service hands them to `egoslam_egress`
//! and writes the same [`MapState`] to its result files.

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

    /// A point as the client contract carries it, with its confidence when scored.
    fn point_message(&self, track: u64, x: &Vector3<f64>) -> pb::MapPoint {
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
    }

    /// The messages of this state: poses new or moved since `revisions` last saw them
    /// (recorded there), and the rest at their current revisions; likewise the points new or
    /// moved since `published_points` last saw them. The snapshot of every frame and point
    /// is kept as this state, made into messages only when a client asks for it.
    pub fn publication(
        self,
        revisions: &mut Revisions,
        published_points: &mut PublishedPoints,
    ) -> Publication {
        let poses = revisions.changed(&self.frames);
        let numbers = |v: &[PosedFrame]| -> Vec<u32> {
            v.iter().map(|f| revisions.revision(f.frame_id)).collect()
        };
        let (keyframe_revisions, frame_revisions) =
            (numbers(&self.keyframes), numbers(&self.frames));
        let keyframes = trajectory(&self.keyframes, &keyframe_revisions);
        let changed_points = published_points
            .changed(&self.points)
            .into_iter()
            .map(|(t, x)| self.point_message(t, &x))
            .collect();
        Publication {
            poses,
            keyframes: keyframes.clone(),
            changed_points,
            snapshot: SnapshotParts {
                state: self,
                keyframes,
                frame_revisions,
            },
        }
    }
}

fn trajectory(frames: &[PosedFrame], revisions: &[u32]) -> pb::Trajectory {
    pb::Trajectory {
        poses: frames
            .iter()
            .zip(revisions)
            .map(|(f, r)| message(f, *r))
            .collect(),
    }
}

/// What a snapshot holds, kept as the merger's own data: making every frame's and point's
/// message after each window costs time in proportion to the stream's length (a day of
/// video is millions of frames), so it is done when a client asks ([`Self::to_message`]).
pub struct SnapshotParts {
    state: MapState,
    keyframes: pb::Trajectory,
    /// The revision of each of `state.frames`, as published with this state.
    frame_revisions: Vec<u32>,
}

impl SnapshotParts {
    /// The snapshot message: the keyframes, every frame at its revision, every point, and
    /// `status`.
    pub fn to_message(&self, status: &pb::Status) -> pb::Snapshot {
        pb::Snapshot {
            keyframes: Some(self.keyframes.clone()),
            frames: Some(trajectory(&self.state.frames, &self.frame_revisions)),
            map: Some(pb::MapPoints {
                points: self
                    .state
                    .points
                    .iter()
                    .map(|(t, x)| self.state.point_message(*t, x))
                    .collect(),
            }),
            status: Some(status.clone()),
        }
    }
}

/// One window's messages ([`MapState::publication`]).
pub struct Publication {
    /// Frames whose pose is new (revision 0) or moved (the next revision).
    pub poses: Vec<pb::Pose>,
    /// Every keyframe at its current revision.
    pub keyframes: pb::Trajectory,
    /// The points new or moved since the last publication.
    pub changed_points: Vec<pb::MapPoint>,
    /// Every frame and point, for the snapshot queryable.
    pub snapshot: SnapshotParts,
}

/// Which map points were published where: a point is published again when the map moves it
/// (a window's bundle adjustment, a merge, global BA) and when it first enters the map,
/// whichever window brought it, so a client that applies every `map` message holds the
/// map's points where the map has them.
#[derive(Default)]
pub struct PublishedPoints {
    published: HashMap<u64, Vector3<f64>>,
}

impl PublishedPoints {
    /// The points of `points` new or moved (by more than 1e-9) since the last call; points
    /// no longer in the map are forgotten (a client keeps them, as culled).
    pub fn changed(&mut self, points: &[(u64, Vector3<f64>)]) -> Vec<(u64, Vector3<f64>)> {
        let mut changed = Vec::new();
        let mut now = HashMap::with_capacity(points.len());
        for &(track, x) in points {
            if self
                .published
                .get(&track)
                .is_none_or(|old| (old - x).norm() > 1e-9)
            {
                changed.push((track, x));
            }
            now.insert(track, x);
        }
        self.published = now;
        changed
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

    #[test]
    fn a_point_goes_out_when_it_enters_the_map_and_whenever_it_moves() {
        let mut published = PublishedPoints::default();
        let at = |x: f64| Vector3::new(x, 1.0, 2.0);
        let tracks =
            |v: Vec<(u64, Vector3<f64>)>| v.into_iter().map(|(t, _)| t).collect::<Vec<_>>();
        assert_eq!(
            tracks(published.changed(&[(1, at(0.0)), (2, at(0.0))])),
            vec![1, 2]
        );
        // A later window adds point 3 (brought by an earlier window, say) and its BA moves 1.
        let changed = published.changed(&[(1, at(0.25)), (2, at(0.0)), (3, at(5.0))]);
        assert_eq!(changed, vec![(1, at(0.25)), (3, at(5.0))]);
        assert!(
            published.changed(&[(1, at(0.25)), (3, at(5.0))]).is_empty(),
            "2 culled"
        );
        // A culled point that comes back is new again.
        assert_eq!(
            tracks(published.changed(&[(2, at(0.0)), (3, at(5.0))])),
            vec![2]
        );
    }

    #[test]
    fn the_snapshot_made_on_request_holds_every_frame_at_its_revision() {
        let state = |x: f64| MapState {
            keyframes: vec![frame(1, x)],
            frames: vec![frame(1, x), frame(2, 0.0)],
            points: vec![(7, Vector3::new(x, 1.0, 2.0))],
            confidence: None,
        };
        let (mut revisions, mut points) = (Revisions::default(), PublishedPoints::default());
        let first = state(0.0).publication(&mut revisions, &mut points);
        assert_eq!((first.poses.len(), first.changed_points.len()), (2, 1));
        // Frame 1 (a keyframe) moves: revision 1 in the message, the keyframe trajectory
        // and the snapshot; frame 2 stays at 0.
        let moved = state(0.5).publication(&mut revisions, &mut points);
        let status = pb::Status {
            service: "merger".into(),
            ..pb::Status::default()
        };
        let snapshot = moved.snapshot.to_message(&status);
        let frames = snapshot.frames.expect("frames").poses;
        let revision_of = |id: u64| frames.iter().find(|p| p.frame_id == id).map(|p| p.revision);
        assert_eq!((revision_of(1), revision_of(2)), (Some(1), Some(0)));
        assert_eq!(snapshot.keyframes.expect("keyframes").poses[0].revision, 1);
        assert_eq!(moved.keyframes.poses[0].revision, 1);
        let map = snapshot.map.expect("map").points;
        assert_eq!(map.len(), 1);
        assert_eq!(map[0].position.expect("position").x, 0.5);
        assert_eq!(snapshot.status.expect("status").service, "merger");
    }
}
