//! The merger's current results in one place: keyframe and frame poses (with revisions),
//! points; written to files and published over zenoh from the same values.

use crate::convert::{pose_to_pb, vec3_to_pb};
use crate::output::{tum_text, write_atomically};
use egoslam_egress::Egress;
use egoslam_export::map_ply::{self, MapPlyPoint};
use egoslam_geometry::StampedPose;
use egoslam_merger::{interpolate_frames, MapBuilder, PointConfidence, PointConfidenceOptions};
use egoslam_messages::v1 as pb;
use nalgebra::{Point2, Vector3};
use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::Arc;

/// A frame between keyframes waiting for its next keyframe to reach the map.
#[derive(Debug, Clone, PartialEq)]
pub struct PendingFrame {
    pub next_keyframe: u64,
    /// `(track id, undistorted pixel)`.
    pub tracks: Vec<(u64, Point2<f64>)>,
}

/// A frame posed by PnP, kept relative to the keyframe before it so that it follows that
/// keyframe when a refinement moves it, and rescaled with the distance to the keyframe
/// after it when the map's scale there changes (a loop's scale step can shrink a stretch
/// posed while inflated a thousandfold: its frames were left hundreds of metres off).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalizedFrame {
    pub anchor_keyframe: u64,
    /// anchor_from_frame (position: the frame's centre in the anchor camera's frame).
    pub relative: StampedPose,
    /// The keyframe after the frame.
    pub next_keyframe: u64,
    /// Distance from the anchor to `next_keyframe` when the frame was posed, map units
    /// (0: not known; `relative` is then used as it is).
    pub bracket_length: f64,
}

impl LocalizedFrame {
    /// world_from_frame, given its anchor's pose now and the next keyframe's (when in the
    /// same segment): `relative` with its position scaled by how the anchor-to-next
    /// distance changed since the frame was posed.
    pub fn pose(&self, anchor: &StampedPose, next: Option<&StampedPose>) -> StampedPose {
        let scale = match next {
            Some(next) if self.bracket_length > 1e-12 => {
                (next.position - anchor.position).norm() / self.bracket_length
            }
            _ => 1.0,
        };
        let relative = StampedPose {
            position: self.relative.position * scale,
            ..self.relative
        };
        compose(anchor, &relative)
    }
}

/// Every frame known to the merger, which keyframe is which frame, and how the frames
/// between keyframes are posed.
#[derive(Default)]
pub struct FrameIndex {
    /// frame id -> timestamp
    pub frames: BTreeMap<u64, f64>,
    /// keyframe id -> frame id
    pub keyframe_frames: BTreeMap<u64, u64>,
    /// frame id -> tracks, until its bracketing keyframes are in the map.
    pub pending: BTreeMap<u64, PendingFrame>,
    /// frame id -> PnP pose relative to its anchor keyframe.
    pub localized: BTreeMap<u64, LocalizedFrame>,
}

impl FrameIndex {
    pub fn add_stamp(&mut self, k: &pb::KeyframeStamp) {
        self.frames.insert(k.frame_id, k.timestamp_s);
        // Overlapping windows repeat keyframes: their frames are taken (and tried) once.
        let new = self
            .keyframe_frames
            .insert(k.keyframe_id, k.frame_id)
            .is_none();
        for (id, t) in k
            .frames_since_previous_ids
            .iter()
            .zip(&k.frames_since_previous_timestamps_s)
        {
            self.frames.insert(*id, *t);
        }
        for f in &k.frames_since_previous {
            if !new || f.tracks.is_empty() {
                continue;
            }
            let tracks = f
                .tracks
                .iter()
                .map(|t| (t.track_id, Point2::new(f64::from(t.x), f64::from(t.y))))
                .collect();
            self.pending.insert(
                f.frame_id,
                PendingFrame {
                    next_keyframe: k.keyframe_id,
                    tracks,
                },
            );
        }
    }
}

/// A posed frame.
#[derive(Debug, Clone, Copy)]
pub struct PosedFrame {
    pub frame_id: u64,
    pub segment: u32,
    pub pose: StampedPose,
    pub interpolated: bool,
}

/// `a_from_b` of two world_from_camera poses (timestamp of `b`).
pub fn relative(a: &StampedPose, b: &StampedPose) -> StampedPose {
    StampedPose {
        timestamp: b.timestamp,
        position: a.rotation.inverse() * (b.position - a.position),
        rotation: a.rotation.inverse() * b.rotation,
    }
}

/// `a` composed with `a_from_b`: world_from_b (timestamp of `a_from_b`).
pub fn compose(a: &StampedPose, a_from_b: &StampedPose) -> StampedPose {
    StampedPose {
        timestamp: a_from_b.timestamp,
        position: a.position + a.rotation * a_from_b.position,
        rotation: a.rotation * a_from_b.rotation,
    }
}

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

/// The map's keyframes as posed frames, in time order.
fn posed_keyframes(map: &MapBuilder, index: &FrameIndex) -> Vec<PosedFrame> {
    // Keyframes of a saved map this run extends have no frame of this run: the run's
    // frames are posed between the run's own keyframes only, whatever their timestamps.
    let mut keyframes: Vec<PosedFrame> = map
        .keyframes()
        .filter_map(|(kf, segment, pose)| {
            Some(PosedFrame {
                frame_id: *index.keyframe_frames.get(&kf)?,
                segment,
                pose: *pose,
                interpolated: false,
            })
        })
        .collect();
    keyframes.sort_by(|a, b| a.pose.timestamp.total_cmp(&b.pose.timestamp));
    keyframes
}

/// The frames with ids in `ids` that can be posed: localized ones relative to their anchor
/// keyframe, the others interpolated between the keyframes around them.
fn posed_frames(
    map: &MapBuilder,
    index: &FrameIndex,
    keyframes: &[PosedFrame],
    ids: impl std::ops::RangeBounds<u64>,
) -> Vec<PosedFrame> {
    let anchors: Vec<(u32, StampedPose)> = keyframes.iter().map(|k| (k.segment, k.pose)).collect();
    let (ids, stamps): (Vec<u64>, Vec<f64>) =
        index.frames.range(ids).map(|(i, t)| (*i, *t)).unzip();
    let keyframe_ids: std::collections::BTreeSet<u64> =
        keyframes.iter().map(|k| k.frame_id).collect();
    interpolate_frames(&anchors, &stamps)
        .into_iter()
        .map(|(i, pose, segment)| {
            let frame_id = ids[i];
            let localized = index.localized.get(&frame_id).and_then(|l| {
                let (s, anchor) = map.keyframe(l.anchor_keyframe)?;
                let next = map
                    .keyframe(l.next_keyframe)
                    .and_then(|(sn, next)| (sn == s).then_some(next));
                (s == segment).then(|| l.pose(anchor, next))
            });
            PosedFrame {
                frame_id,
                segment,
                interpolated: localized.is_none() && !keyframe_ids.contains(&frame_id),
                pose: localized.unwrap_or(pose),
            }
        })
        .collect()
}

/// frame id -> (segment, pose) of the frames with ids in `ids`, as [`MapState::of`] poses
/// them.
pub fn frame_poses(
    map: &MapBuilder,
    index: &FrameIndex,
    ids: impl std::ops::RangeBounds<u64>,
) -> BTreeMap<u64, (u32, StampedPose)> {
    let keyframes = posed_keyframes(map, index);
    posed_frames(map, index, &keyframes, ids)
        .into_iter()
        .map(|f| (f.frame_id, (f.segment, f.pose)))
        .collect()
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

    #[test]
    fn a_localized_frame_follows_the_scale_of_its_bracket() {
        // Posed while the map there was inflated: keyframes 10 units apart, the frame a
        // quarter of the way and 1 unit aside, the anchor turned 90 deg about y.
        let turned = UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0);
        let at = |x: f64| StampedPose {
            timestamp: 0.0,
            position: Vector3::new(x, 0.0, 0.0),
            rotation: turned,
        };
        let (anchor, next) = (at(0.0), at(10.0));
        let posed = StampedPose {
            position: Vector3::new(2.5, 1.0, 0.0),
            ..at(0.0)
        };
        let frame = LocalizedFrame {
            anchor_keyframe: 0,
            relative: relative(&anchor, &posed),
            next_keyframe: 1,
            bracket_length: 10.0,
        };
        // Unchanged map: the pose as found.
        let same = frame.pose(&anchor, Some(&next));
        assert!((same.position - posed.position).norm() < 1e-12);
        // A loop shrank the stretch 1000x and moved it: the frame keeps its place between.
        let moved = |x: f64| StampedPose {
            position: Vector3::new(5.0 + x / 1000.0, 2.0, 0.0),
            ..at(0.0)
        };
        let shrunk = frame.pose(&moved(0.0), Some(&moved(10.0)));
        assert!((shrunk.position - Vector3::new(5.0025, 2.001, 0.0)).norm() < 1e-12);
        // No next keyframe in the segment, or none recorded (older checkpoints): as found.
        let alone = frame.pose(&moved(0.0), None);
        assert!((alone.position - Vector3::new(7.5, 3.0, 0.0)).norm() < 1e-12);
        let unrecorded = LocalizedFrame {
            bracket_length: 0.0,
            ..frame
        };
        let old = unrecorded.pose(&moved(0.0), Some(&moved(10.0)));
        assert!((old.position - alone.position).norm() < 1e-12);
    }
}
