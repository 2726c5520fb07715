//! Every frame of the stream and how it is posed: keyframes by the map, frames between
//! them localized by PnP on the merged map once both keyframes around them are in it
//! (`crate::frame_localization`); those that cannot be stay interpolated and are marked so
//! on the wire.

use super::frame_tables::{FrameStamps, LocalizedFrames};
use super::tally::Tally;
use crate::{
    interpolate_between, interpolate_frames, localize_frame, LocalizationOptions, MapBuilder,
};
use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_messages::internal::v1 as internal;
use nalgebra::Point2;
use std::collections::BTreeMap;

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
    /// Interpolated between keyframes, not posed by PnP, when culling fixed it relative to
    /// a kept keyframe: it stays marked so on the wire.
    pub interpolated: bool,
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

    /// The anchor's segment and world_from_frame as `map` poses the anchor (and the next
    /// keyframe, when in the anchor's segment) now; `None` once the anchor left the map.
    pub fn posed_in(&self, map: &MapBuilder) -> Option<(u32, StampedPose)> {
        let (segment, anchor) = map.keyframe(self.anchor_keyframe)?;
        let next = map
            .keyframe(self.next_keyframe)
            .and_then(|(s, next)| (s == segment).then_some(next));
        Some((segment, self.pose(anchor, next)))
    }
}

/// Every frame known to the merger, which keyframe is which frame, and how the frames
/// between keyframes are posed.
#[derive(Default)]
pub struct FrameIndex {
    /// frame id -> timestamp
    pub frames: FrameStamps,
    /// keyframe id -> frame id
    pub keyframe_frames: BTreeMap<u64, u64>,
    /// frame id -> tracks, until its bracketing keyframes are in the map.
    pub pending: BTreeMap<u64, PendingFrame>,
    /// frame id -> PnP pose relative to its anchor keyframe.
    pub localized: LocalizedFrames,
    /// Frames numbered below this are past the horizon (`super::frame_retirement`): final,
    /// no longer posed nor published; the few the map still needs keep their entries.
    pub retired_before: u64,
}

impl FrameIndex {
    pub fn add_stamp(&mut self, k: &internal::KeyframeStamp) {
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

    /// Seconds of stream time between keyframe `keyframe`'s frame and the newest frame
    /// known; `None` for a keyframe without a stamp.
    pub fn keyframe_age_s(&self, keyframe: u64) -> Option<f64> {
        let frame = self.keyframe_frames.get(&keyframe)?;
        let taken = self.frames.get(frame)?;
        let (_, newest) = self.frames.last_key_value()?;
        Some((newest - taken).max(0.0))
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

/// The map's keyframes as posed frames, in time order.
pub fn posed_keyframes(map: &MapBuilder, index: &FrameIndex) -> Vec<PosedFrame> {
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
pub fn posed_frames(
    map: &MapBuilder,
    index: &FrameIndex,
    keyframes: &[PosedFrame],
    ids: impl std::ops::RangeBounds<u64>,
) -> Vec<PosedFrame> {
    pose_frames(
        map,
        index,
        keyframes,
        index.frames.range(ids).map(|(i, t)| (*i, *t)),
    )
}

/// The frames of `frames` (`(id, timestamp)`) that can be posed, as [`posed_frames`] poses
/// them, in the order given.
pub fn pose_frames(
    map: &MapBuilder,
    index: &FrameIndex,
    keyframes: &[PosedFrame],
    frames: impl Iterator<Item = (u64, f64)>,
) -> Vec<PosedFrame> {
    let anchors: Vec<(u32, StampedPose)> = keyframes.iter().map(|k| (k.segment, k.pose)).collect();
    let (ids, stamps): (Vec<u64>, Vec<f64>) = frames.unzip();
    let keyframe_ids: std::collections::BTreeSet<u64> =
        keyframes.iter().map(|k| k.frame_id).collect();
    interpolate_frames(&anchors, &stamps)
        .into_iter()
        .map(|(i, pose, segment)| {
            let frame_id = ids[i];
            let localized = index.localized.get(&frame_id).and_then(|l| {
                let (s, pose) = l.posed_in(map)?;
                (s == segment).then_some((pose, l.interpolated))
            });
            PosedFrame {
                frame_id,
                segment,
                interpolated: localized.map_or(!keyframe_ids.contains(&frame_id), |l| l.1),
                // The frame's own stamp, whatever the pose it hangs on carries: a PnP
                // solved without a prior stamps 0, and a row stamped 0 in trajectory.tum
                // is matched to the ground truth's first pose.
                pose: StampedPose {
                    timestamp: stamps[i],
                    ..localized.map_or(pose, |l| l.0)
                },
            }
        })
        .collect()
}

/// frame id -> (segment, pose) of the frames with ids in `ids`, as the published results
/// pose them.
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

/// A localized frame's position may depart from the one interpolated between its keyframes
/// by at most this fraction of the distance between them: between two keyframes (at most
/// 30 frames apart) a head's path stays near their chord, and where the keyframes barely
/// moved (a stop, a turn in place) the interpolation is the better position, while a PnP
/// on a few dozen points there can land many brackets off.
const MAX_DEPARTURE_OF_BRACKET: f64 = 1.0;

/// Tries every pending frame whose bracketing keyframes are both posed in one segment;
/// frames whose next keyframe is not yet in the map stay pending, unless that keyframe is
/// older than `oldest_live_keyframe` (no later window can pose it: it stays unposed).
pub fn localize_pending(
    index: &mut FrameIndex,
    map: &MapBuilder,
    camera: &PinholeRadtan,
    oldest_live_keyframe: u64,
    stats: &mut Tally,
) {
    let options = LocalizationOptions::default();
    let before = index.pending.len();
    index.pending.retain(|_, p| {
        p.next_keyframe >= oldest_live_keyframe || map.keyframe(p.next_keyframe).is_some()
    });
    stats.count("unposed_frames", (before - index.pending.len()) as u64);
    let ready: Vec<u64> = index
        .pending
        .iter()
        .filter(|(_, p)| map.keyframe(p.next_keyframe).is_some())
        .map(|(f, _)| *f)
        .collect();
    for frame_id in ready {
        let Some(pending) = index.pending.remove(&frame_id) else {
            continue;
        };
        let (Some(timestamp), Some(anchor_id)) = (
            index.frames.get(&frame_id).copied(),
            pending.next_keyframe.checked_sub(1),
        ) else {
            continue;
        };
        let (Some((sa, anchor)), Some((sb, next))) =
            (map.keyframe(anchor_id), map.keyframe(pending.next_keyframe))
        else {
            stats.count("interpolated_frames", 1);
            continue;
        };
        if sa != sb {
            stats.count("interpolated_frames", 1);
            continue;
        }
        let prior = interpolate_between(anchor, next, timestamp);
        let correspondences: Vec<_> = pending
            .tracks
            .iter()
            .filter_map(|(track, px)| match map.point(*track) {
                Some((s, x)) if s == sa => Some((*x, *px)),
                _ => None,
            })
            .collect();
        let bracket_length = (next.position - anchor.position).norm();
        let located = localize_frame(camera, &correspondences, &prior, &options).map(|mut l| {
            if let Some(departure) = keep_within_bracket(&mut l.pose, &prior, bracket_length) {
                tracing::debug!(
                    frame = frame_id,
                    departure,
                    bracket = bracket_length,
                    "localized position off the bracket: interpolated"
                );
                stats.count("frames_position_interpolated", 1);
            }
            l
        });
        match located {
            Ok(l) => {
                tracing::debug!(
                    frame = frame_id,
                    from_prior = (l.pose.position - prior.position).norm(),
                    bracket = bracket_length,
                    inliers = l.inliers,
                    "frame localized"
                );
                index.localized.insert(
                    frame_id,
                    LocalizedFrame {
                        anchor_keyframe: anchor_id,
                        relative: relative(anchor, &l.pose),
                        next_keyframe: pending.next_keyframe,
                        bracket_length,
                        interpolated: false,
                    },
                );
                stats.count("localized_frames", 1);
            }
            Err(e) => {
                tracing::debug!(frame = frame_id, reason = %e, "frame interpolated");
                stats.count("interpolated_frames", 1);
            }
        }
    }
}

/// A localized `pose` whose position departs from the interpolated `prior`'s by more than
/// [`MAX_DEPARTURE_OF_BRACKET`] times `bracket` (the distance between the keyframes) takes
/// the prior's position and keeps its rotation (PnP's rotation is sound where its
/// position is not: a few dozen points, little parallax); returns the departure then.
fn keep_within_bracket(pose: &mut StampedPose, prior: &StampedPose, bracket: f64) -> Option<f64> {
    let departure = (pose.position - prior.position).norm();
    (departure > MAX_DEPARTURE_OF_BRACKET * bracket).then(|| {
        pose.position = prior.position;
        departure
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    #[test]
    fn a_position_off_its_bracket_is_interpolated_and_its_rotation_kept() {
        let prior = StampedPose {
            timestamp: 1.0,
            position: Vector3::new(1.0, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        };
        let turned = UnitQuaternion::from_euler_angles(0.0, 0.05, 0.0);
        let near = StampedPose {
            position: Vector3::new(1.0, 0.004, 0.0),
            rotation: turned,
            ..prior
        };
        // Keyframes 5 mm apart: 4 mm off is kept, 6 mm is not.
        let mut kept = near;
        assert_eq!(keep_within_bracket(&mut kept, &prior, 0.005), None);
        assert_eq!(kept, near);
        let mut far = StampedPose {
            position: Vector3::new(1.0, 0.006, 0.0),
            ..near
        };
        let departure = keep_within_bracket(&mut far, &prior, 0.005).expect("off");
        assert!((departure - 0.006).abs() < 1e-12);
        assert_eq!(far.position, prior.position);
        assert_eq!(far.rotation, turned);
    }

    #[test]
    fn a_keyframe_ages_with_the_newest_frame() {
        let mut index = FrameIndex::default();
        for (keyframe, frame, t) in [(0, 0, 10.0), (1, 30, 11.0)] {
            index.add_stamp(&internal::KeyframeStamp {
                keyframe_id: keyframe,
                frame_id: frame,
                timestamp_s: t,
                ..Default::default()
            });
        }
        index.frames.insert(95, 13.5);
        assert_eq!(index.keyframe_age_s(0), Some(3.5));
        assert_eq!(index.keyframe_age_s(1), Some(2.5));
        assert_eq!(index.keyframe_age_s(2), None, "no stamp");
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
            interpolated: false,
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
