//! What the merger publishes after a window, as messages of the client contract: the
//! poses of the frames new or moved with their revision (a pose that moves is published
//! again with the next revision), the keyframe trajectory, the points new or moved since
//! last published, and what a late joiner's snapshot holds. The service hands them to
//! `egoslam_egress` and writes the same state to its result files.

use super::frame_poses::FramePoseUpdate;
use super::frames::PosedFrame;
use crate::map_points::Changed;
use crate::{MapBuilder, PointConfidence};
use egoslam_geometry::StampedPose;
use egoslam_messages::v1 as pb;
use egoslam_relocalization::wire::{pose_to_pb, vec3_to_pb};
use nalgebra::Vector3;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::{Arc, Mutex};

/// The map at one moment: its keyframes and points (the frames' poses are kept in
/// [`Revisions`], updated with only what changed).
pub struct MapState {
    pub keyframes: Vec<PosedFrame>,
    pub points: Vec<(u64, Vector3<f64>)>,
    /// How well each point is known, once attached ([`MapState::with_confidence`]).
    pub confidence: Option<Arc<HashMap<u64, PointConfidence>>>,
}

impl MapState {
    /// The map's points with `keyframes`, the map's keyframes of this run in time order
    /// (`FramePoseUpdate::keyframes`).
    pub fn of(map: &MapBuilder, keyframes: Vec<PosedFrame>) -> Self {
        let points = map.points().map(|(track, _, x)| (track, *x)).collect();
        Self {
            keyframes,
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

    /// The messages of this state: `poses` (what [`Revisions::record`] found new or
    /// moved), the keyframes at their revisions in `revisions`, and `changed_points` (what
    /// [`PublishedPoints::changed`] found). The snapshot of every frame and point is made
    /// into messages only when a client asks for it, the frames from `revisions` as they
    /// are then.
    pub fn publication(
        self,
        poses: Vec<pb::Pose>,
        changed_points: &[(u64, Vector3<f64>)],
        revisions: &Arc<Mutex<Revisions>>,
    ) -> Publication {
        let keyframe_revisions: Vec<u32> = {
            let mut revisions = revisions.lock().unwrap_or_else(|e| e.into_inner());
            let numbers = self
                .keyframes
                .iter()
                .map(|f| revisions.keyframe_revision(f));
            numbers.collect()
        };
        let keyframes = trajectory(&self.keyframes, &keyframe_revisions);
        let changed_points = changed_points
            .iter()
            .map(|(t, x)| self.point_message(*t, x))
            .collect();
        Publication {
            poses,
            keyframes: keyframes.clone(),
            changed_points,
            snapshot: SnapshotParts {
                state: self,
                keyframes,
                revisions: Arc::clone(revisions),
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
    /// Every frame's pose and revision.
    revisions: Arc<Mutex<Revisions>>,
}

impl SnapshotParts {
    /// The snapshot message: the keyframes, every posed frame at its revision, every
    /// point, and `status`.
    pub fn to_message(&self, status: &pb::Status) -> pb::Snapshot {
        let frames = {
            let revisions = self.revisions.lock().unwrap_or_else(|e| e.into_inner());
            let posed = revisions.posed_frames().map(|(f, r)| message(&f, r));
            pb::Trajectory {
                poses: posed.collect(),
            }
        };
        pb::Snapshot {
            keyframes: Some(self.keyframes.clone()),
            frames: Some(frames),
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
    /// The points of `map` new or moved (by more than 1e-9) since the last call, among
    /// those `changed` names (every point for [`Changed::All`]); points no longer in the
    /// map are forgotten (a client keeps them, as culled).
    pub fn changed(&mut self, map: &MapBuilder, changed: &Changed) -> Vec<(u64, Vector3<f64>)> {
        let tracks = match changed {
            Changed::All => {
                self.published
                    .retain(|track, _| map.point(*track).is_some());
                Box::new(map.points().map(|(track, ..)| track)) as Box<dyn Iterator<Item = u64>>
            }
            Changed::Some(tracks) => Box::new(tracks.iter().copied()),
        };
        let mut out = Vec::new();
        for track in tracks {
            let Some((_, &x)) = map.point(track) else {
                self.published.remove(&track);
                continue;
            };
            let old = self.published.insert(track, x);
            if old.is_none_or(|old| (old - x).norm() > 1e-9) {
                out.push((track, x));
            }
        }
        out
    }
}

/// A frame's pose as last published, with its revision, and whether the map poses it now
/// (and how). Poses that moved by at most 1e-9 since are not published again, nor kept:
/// one pose per frame (a day of video is millions of frames), and the snapshot and the
/// files hold what the clients were sent.
struct FrameRecord {
    pose: StampedPose,
    revision: u32,
    segment: u32,
    interpolated: bool,
    /// Posed by the map now (`false`: not posable any more, or only tracked live).
    posed: bool,
}

impl FrameRecord {
    fn posed_frame(&self, frame_id: u64) -> PosedFrame {
        PosedFrame {
            frame_id,
            segment: self.segment,
            pose: self.pose,
            interpolated: self.interpolated,
        }
    }
}

/// Every frame's pose as published: which poses are new or moved since, and their
/// revisions.
#[derive(Default)]
pub struct Revisions {
    frames: BTreeMap<u64, FrameRecord>,
    /// Frames the map poses now.
    posed: usize,
    /// Keyframes' frames retired past the horizon (`super::frame_retirement`) while their
    /// keyframe stays in the map: no longer published as frames, but the keyframe
    /// trajectory keeps counting their revisions up as the keyframe moves.
    retired_keyframes: BTreeMap<u64, FrameRecord>,
    /// The revision of a frame's first pose (0, but for a run started again:
    /// [`Self::starting_at`]).
    first: u32,
}

impl Revisions {
    /// Revisions whose first is `first`: a run started again from the first frame (for a
    /// calibration estimate) numbers its poses above those its earlier round published,
    /// so that clients, which keep a frame's highest revision, take the new ones.
    pub fn starting_at(first: u32) -> Self {
        Self {
            first,
            ..Self::default()
        }
    }

    /// Takes an update's poses; returns those new (revision 0) or moved (revision + 1)
    /// since last published, as messages, and records them so.
    pub fn record(&mut self, update: &FramePoseUpdate) -> Vec<pb::Pose> {
        for frame in &update.unposed {
            if let Some(record) = self.frames.get_mut(frame) {
                if std::mem::replace(&mut record.posed, false) {
                    self.posed -= 1;
                }
            }
        }
        let mut out = Vec::new();
        for f in &update.posed {
            let Some(record) = self.frames.get_mut(&f.frame_id) else {
                let record = FrameRecord {
                    pose: f.pose,
                    revision: self.first,
                    segment: f.segment,
                    interpolated: f.interpolated,
                    posed: true,
                };
                self.frames.insert(f.frame_id, record);
                self.posed += 1;
                out.push(message(f, self.first));
                continue;
            };
            if !std::mem::replace(&mut record.posed, true) {
                self.posed += 1;
            }
            (record.segment, record.interpolated) = (f.segment, f.interpolated);
            if moved(&record.pose, &f.pose) {
                record.pose = f.pose;
                record.revision += 1;
                out.push(message(f, record.revision));
            }
        }
        out
    }

    /// Records the live tracker's pose of a frame as its first revision, which it returns;
    /// `None` (nothing recorded) when the frame was already published, by a window that
    /// came first.
    pub fn claim_live(&mut self, frame_id: u64, pose: &StampedPose) -> Option<u32> {
        if self.frames.contains_key(&frame_id) {
            return None;
        }
        let record = FrameRecord {
            pose: *pose,
            revision: self.first,
            segment: 0,
            interpolated: false,
            posed: false,
        };
        self.frames.insert(frame_id, record);
        Some(self.first)
    }

    /// The last published revision of every frame (what a checkpoint keeps).
    pub fn numbers(&self) -> BTreeMap<u64, u32> {
        let records = self.frames.iter().chain(&self.retired_keyframes);
        records.map(|(f, r)| (*f, r.revision)).collect()
    }

    /// Revisions of a restarted merger: the checkpointed numbers, with the resumed poses
    /// (`frames`) as published, so that a pose that moves later is published with a higher
    /// revision than any the clients already hold (they keep the highest). Which frames the
    /// map poses comes with the next [`Self::record`].
    /// Frames numbered below `retired_before` are keyframes' frames past the horizon.
    pub fn resume(
        numbers: &BTreeMap<u64, u32>,
        frames: &[PosedFrame],
        retired_before: u64,
        first: u32,
    ) -> Self {
        let records = frames.iter().filter_map(|f| {
            let record = FrameRecord {
                pose: f.pose,
                revision: *numbers.get(&f.frame_id)?,
                segment: f.segment,
                interpolated: f.interpolated,
                posed: false,
            };
            Some((f.frame_id, record))
        });
        let mut frames: BTreeMap<u64, FrameRecord> = records.collect();
        let live = frames.split_off(&retired_before);
        Self {
            frames: live,
            posed: 0,
            retired_keyframes: frames,
            first,
        }
    }

    /// The revision of keyframe `k`'s pose on the keyframe trajectory: its frame's, or,
    /// for a frame retired past the horizon, counted up here whenever the keyframe moved.
    pub fn keyframe_revision(&mut self, k: &PosedFrame) -> u32 {
        if let Some(record) = self.frames.get(&k.frame_id) {
            return record.revision;
        }
        let Some(record) = self.retired_keyframes.get_mut(&k.frame_id) else {
            return self.first;
        };
        if moved(&record.pose, &k.pose) {
            record.pose = k.pose;
            record.revision += 1;
        }
        record.revision
    }

    /// Every frame the map poses now, as published, with its revision, in frame id order.
    pub fn posed_frames(&self) -> impl Iterator<Item = (PosedFrame, u32)> + '_ {
        let posed = self.frames.iter().filter(|(_, r)| r.posed);
        posed.map(|(id, r)| (r.posed_frame(*id), r.revision))
    }

    /// How many frames the map poses now.
    pub fn posed_count(&self) -> usize {
        self.posed
    }

    /// Drops the frames numbered below `before` (retired past the horizon,
    /// `super::frame_retirement`); returns those the map posed, as last published, in frame
    /// id order: their final poses.
    /// Those in `keyframe_frames` (the map's keyframes') keep their record for
    /// [`Self::keyframe_revision`], which forgets the others'.
    pub fn retire(&mut self, before: u64, keyframe_frames: &BTreeSet<u64>) -> Vec<PosedFrame> {
        let kept = self.frames.split_off(&before);
        let retired = std::mem::replace(&mut self.frames, kept);
        let posed: Vec<PosedFrame> = retired
            .iter()
            .filter(|(_, r)| r.posed)
            .map(|(f, r)| r.posed_frame(*f))
            .collect();
        self.posed -= posed.len();
        self.retired_keyframes.extend(retired);
        self.retired_keyframes
            .retain(|f, _| keyframe_frames.contains(f));
        posed
    }
}

/// Whether a pose moved from `old` to `new` enough to be published again (1e-9).
fn moved(old: &StampedPose, new: &StampedPose) -> bool {
    (old.position - new.position).norm() > 1e-9 || old.rotation.angle_to(&new.rotation) > 1e-9
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

    fn update(posed: &[PosedFrame], unposed: &[u64]) -> FramePoseUpdate {
        FramePoseUpdate {
            keyframes: Vec::new(),
            posed: posed.to_vec(),
            unposed: unposed.to_vec(),
        }
    }

    fn revisions_of(poses: &[pb::Pose]) -> Vec<(u64, u32)> {
        poses.iter().map(|p| (p.frame_id, p.revision)).collect()
    }

    #[test]
    fn a_restarted_merger_keeps_counting_revisions_up() {
        let mut before = Revisions::default();
        assert_eq!(
            before
                .record(&update(&[frame(1, 0.0), frame(2, 0.0)], &[]))
                .len(),
            2
        );
        let moved = before.record(&update(&[frame(1, 0.5)], &[]));
        assert_eq!(revisions_of(&moved), vec![(1, 1)]);
        // Kill and restart: the checkpointed numbers and the resumed poses.
        let resumed = [frame(1, 0.5), frame(2, 0.0)];
        let mut after = Revisions::resume(&before.numbers(), &resumed, 0, 0);
        assert!(
            after.record(&update(&resumed, &[])).is_empty(),
            "nothing moved"
        );
        assert_eq!(after.posed_count(), 2);
        let moved = after.record(&update(&[frame(1, 0.7), frame(2, 0.1), frame(3, 0.0)], &[]));
        assert_eq!(revisions_of(&moved), vec![(1, 2), (2, 1), (3, 0)]);
    }

    #[test]
    fn a_frame_tracked_live_is_published_again_only_when_the_map_poses_it_elsewhere() {
        let mut revisions = Revisions::default();
        let live = frame(4, 1.0);
        assert_eq!(revisions.claim_live(4, &live.pose), Some(0));
        assert_eq!(
            revisions.posed_frames().count(),
            0,
            "not posed by the map yet"
        );
        assert!(revisions.record(&update(&[live], &[])).is_empty());
        let moved = revisions.record(&update(&[frame(4, 1.25)], &[]));
        assert_eq!(revisions_of(&moved), vec![(4, 1)]);
        assert_eq!(
            revisions.claim_live(4, &live.pose),
            None,
            "already published"
        );
        // A frame the map can no longer pose leaves the snapshot, keeping its revision.
        assert!(revisions.record(&update(&[], &[4])).is_empty());
        assert_eq!((revisions.posed_count(), revisions.numbers()[&4]), (0, 1));
        let back = revisions.record(&update(&[frame(4, 2.0)], &[]));
        assert_eq!(revisions_of(&back), vec![(4, 2)]);
    }

    #[test]
    fn retired_frames_hand_back_their_last_published_poses() {
        let mut revisions = Revisions::default();
        let posed = [frame(1, 0.0), frame(2, 0.0), frame(5, 0.0)];
        revisions.record(&update(&posed, &[]));
        revisions.record(&update(&[frame(2, 0.3)], &[5]));
        assert_eq!(revisions.claim_live(3, &frame(3, 0.0).pose), Some(0));
        // Frame 2 is a keyframe's, which stays in the map.
        let retired = revisions.retire(4, &BTreeSet::from([2]));
        let ids: Vec<(u64, f64)> = retired
            .iter()
            .map(|f| (f.frame_id, f.pose.position.x))
            .collect();
        assert_eq!(ids, vec![(1, 0.0), (2, 0.3)], "3 was only tracked live");
        assert_eq!(revisions.posed_count(), 0, "5 is not posed now");
        assert_eq!(revisions.posed_frames().count(), 0);
        assert_eq!(
            revisions.numbers().into_keys().collect::<Vec<_>>(),
            vec![2, 5]
        );
        assert!(revisions.retire(4, &BTreeSet::from([2])).is_empty());
        // The keyframe trajectory counts its revisions on as the keyframe moves, across a
        // restart too.
        assert_eq!(revisions.keyframe_revision(&frame(2, 0.3)), 1);
        assert_eq!(revisions.keyframe_revision(&frame(2, 0.4)), 2);
        let mut resumed =
            Revisions::resume(&revisions.numbers(), &[frame(2, 0.4), frame(5, 0.0)], 4, 0);
        assert_eq!(resumed.keyframe_revision(&frame(2, 0.5)), 3);
        assert_eq!(
            resumed.posed_frames().count(),
            0,
            "neither posed before a record"
        );
        // Culled since: forgotten at the next retirement.
        resumed.retire(6, &BTreeSet::new());
        assert_eq!(resumed.keyframe_revision(&frame(2, 0.6)), 0);
    }

    #[test]
    fn a_point_goes_out_when_it_enters_the_map_and_whenever_it_moves() {
        let at = |x: f64| (0, Vector3::new(x, 1.0, 2.0));
        let mut map = MapBuilder::from_parts(crate::MapParts::default());
        let mut published = PublishedPoints::default();
        let mut publish = |map: &mut MapBuilder| {
            let changed = map.take_changed_points();
            let out = published.changed(map, &changed);
            out.into_iter().map(|(t, _)| t).collect::<Vec<_>>()
        };
        assert!(publish(&mut map).is_empty());
        map.points.insert(1, at(0.0));
        map.points.insert(2, at(0.0));
        assert_eq!(publish(&mut map), vec![1, 2]);
        // A later window adds point 3 (brought by an earlier window, say), its BA moves 1
        // and leaves 2 where it was.
        map.points.insert(3, at(5.0));
        map.points.insert(2, at(0.0));
        if let Some((_, x)) = map.points.get_mut(&1) {
            x.x = 0.25;
        }
        assert_eq!(publish(&mut map), vec![1, 3]);
        map.points.remove(&2);
        assert!(publish(&mut map).is_empty(), "2 culled");
        // A culled point that comes back is new again; a change to every point (a segment
        // relabelled) publishes those that moved.
        map.points.insert(2, at(0.0));
        for (track, (_, x)) in map.points.iter_mut() {
            if *track == 3 {
                x.x = 6.0;
            }
        }
        assert_eq!(publish(&mut map), vec![2, 3]);
        // A resumed map's points are all new to a restarted merger.
        let mut resumed = MapBuilder::from_parts(map.to_parts());
        let mut restarted = PublishedPoints::default();
        let changed = resumed.take_changed_points();
        assert_eq!(restarted.changed(&resumed, &changed).len(), 3);
    }

    #[test]
    fn the_snapshot_made_on_request_holds_every_frame_at_its_revision() {
        let state = |x: f64| MapState {
            keyframes: vec![frame(1, x)],
            points: vec![(7, Vector3::new(x, 1.0, 2.0))],
            confidence: None,
        };
        let revisions = Arc::new(Mutex::new(Revisions::default()));
        let publish = |x: f64| {
            let frames = [frame(1, x), frame(2, 0.0)];
            let poses = revisions
                .lock()
                .expect("lock")
                .record(&update(&frames, &[]));
            let changed_points = [(7, Vector3::new(x, 1.0, 2.0))];
            state(x).publication(poses, &changed_points, &revisions)
        };
        let first = publish(0.0);
        assert_eq!((first.poses.len(), first.changed_points.len()), (2, 1));
        // Frame 1 (a keyframe) moves: revision 1 in the message, the keyframe trajectory
        // and the snapshot; frame 2 stays at 0.
        let moved = publish(0.5);
        let status = pb::Status {
            service: "merger".into(),
            ..pb::Status::default()
        };
        let snapshot = moved.snapshot.to_message(&status);
        let frames = snapshot.frames.expect("frames").poses;
        assert_eq!(revisions_of(&frames), vec![(1, 1), (2, 0)]);
        assert_eq!(snapshot.keyframes.expect("keyframes").poses[0].revision, 1);
        assert_eq!(moved.keyframes.poses[0].revision, 1);
        let map = snapshot.map.expect("map").points;
        assert_eq!(map.len(), 1);
        assert_eq!(map[0].position.expect("position").x, 0.5);
        assert_eq!(snapshot.status.expect("status").service, "merger");
    }

    #[test]
    fn a_round_started_again_numbers_its_poses_above_the_round_before() {
        let first = 2 << 24;
        let mut revisions = Revisions::starting_at(first);
        assert_eq!(revisions.claim_live(1, &frame(1, 0.0).pose), Some(first));
        let published = revisions.record(&update(&[frame(1, 0.5), frame(2, 0.0)], &[]));
        let numbers: Vec<(u64, u32)> = published.iter().map(|p| (p.frame_id, p.revision)).collect();
        assert_eq!(numbers, vec![(1, first + 1), (2, first)]);
        // A merger restarted within the round goes on in it.
        let resumed = Revisions::resume(&revisions.numbers(), &[frame(1, 0.5)], 0, first);
        let mut resumed = resumed;
        let again = resumed.record(&update(&[frame(1, 0.5), frame(3, 0.0)], &[]));
        assert_eq!(
            again
                .iter()
                .map(|p| (p.frame_id, p.revision))
                .collect::<Vec<_>>(),
            vec![(3, first)]
        );
        assert_eq!(resumed.claim_live(4, &frame(4, 0.0).pose), Some(first));
    }
}
