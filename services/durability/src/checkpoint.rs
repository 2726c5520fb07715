//! The merger's durable state: its map, frame index and position in the solver's stream,
//! saved as a protobuf `MergerCheckpoint` (proto/egoslam/internal/v1/checkpoint.proto) after every
//! window so that a killed merger resumes with nothing lost (docs/durability.md).

use crate::write_atomically;
use egoslam_merger::session::frame_retirement::RetiredFrames;
use egoslam_merger::session::frames::{FrameIndex, LocalizedFrame, PendingFrame};
use egoslam_merger::MergerState;
use egoslam_merger::{MapBuilder, MapParts, ProvisionalScale};
use egoslam_messages::internal::v1 as internal;
use egoslam_relocalization::wire::{pose_from_pb, pose_to_pb, vec3_from_pb, vec3_to_pb};
use nalgebra::Point2;
use prost::Message;
use std::collections::BTreeMap;
use std::path::Path;

/// File name of the checkpoint inside the output folder.
pub const FILE_NAME: &str = "merger.checkpoint";

const FORMAT_VERSION: u32 = 1;

/// The merger session's state as the checkpoint file: protobuf (`MergerCheckpoint`), written
/// atomically.
pub trait Checkpoint: Sized {
    /// Writes the checkpoint atomically (a kill mid-write leaves the previous one).
    fn save(&self, path: &Path) -> crate::Result<()>;
    /// The checkpoint at `path`, or `None` when there is none. A checkpoint that exists but
    /// cannot be read is an error: starting afresh would silently drop the map.
    fn load(path: &Path) -> crate::Result<Option<Self>>;
}

impl Checkpoint for MergerState {
    fn save(&self, path: &Path) -> crate::Result<()> {
        write_atomically(path, &to_message(self).encode_to_vec())
    }

    fn load(path: &Path) -> crate::Result<Option<Self>> {
        let bytes = match std::fs::read(path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(crate::io_error("reading", path)(e)),
        };
        let message = internal::MergerCheckpoint::decode(bytes.as_slice())
            .map_err(|e| crate::invalid(path, format!("not a readable merger checkpoint ({e})")))?;
        from_message(message)
            .map(Some)
            .map_err(|reason| crate::invalid(path, reason))
    }
}

fn to_message(state: &MergerState) -> internal::MergerCheckpoint {
    let parts = state.map.to_parts();
    internal::MergerCheckpoint {
        format_version: FORMAT_VERSION,
        stream_id: state.stream_id.unwrap_or(0),
        last_sequence: state.last_sequence,
        finished: state.finished,
        keyframes: parts
            .keyframes
            .iter()
            .map(|(id, (segment, pose))| internal::CheckpointKeyframe {
                keyframe_id: *id,
                segment_id: *segment,
                pose: Some(pose_to_pb(
                    state.frames.keyframe_frames.get(id).copied().unwrap_or(0),
                    *segment,
                    pose,
                )),
            })
            .collect(),
        points: parts
            .points
            .iter()
            .map(|(track, (segment, x))| internal::CheckpointPoint {
                track_id: *track,
                segment_id: *segment,
                position: Some(vec3_to_pb(x)),
            })
            .collect(),
        observations: observations_to_pb(&parts.observations),
        current_segment: parts.current_segment,
        segments: parts.segments,
        provisional_scale: parts.provisional.map(|p| internal::ProvisionalScale {
            segment_id: p.segment,
            first_keyframe_id: p.first_keyframe,
            pace_before: p.pace_before,
            depth_before: p.depth_before,
            windows_since: p.windows_since,
        }),
        loop_pinned: parts
            .loop_pinned
            .map(|(segment, keyframe)| internal::LoopPin {
                segment_id: segment,
                keyframe_id: keyframe,
            }),
        mended_steps: parts
            .mended_steps
            .iter()
            .map(|(segment, keyframe)| internal::MendedStep {
                segment_id: *segment,
                keyframe_id: *keyframe,
            })
            .collect(),
        frames: state
            .frames
            .frames
            .iter()
            .map(|(id, t)| internal::FrameStamp {
                frame_id: *id,
                timestamp_s: *t,
                tracks: Vec::new(),
            })
            .collect(),
        keyframe_ids: state.frames.keyframe_frames.keys().copied().collect(),
        keyframe_frame_ids: state.frames.keyframe_frames.values().copied().collect(),
        windows: state.windows,
        unsolved_windows: state.unsolved_windows,
        culling_checked_before: state.culling_checked_before,
        pending_frames: state
            .frames
            .pending
            .iter()
            .map(|(frame, p)| internal::PendingFrame {
                frame_id: *frame,
                next_keyframe_id: p.next_keyframe,
                tracks: p
                    .tracks
                    .iter()
                    .map(|(track, px)| internal::TrackObservation {
                        track_id: *track,
                        x: px.x as f32,
                        y: px.y as f32,
                        ..Default::default()
                    })
                    .collect(),
            })
            .collect(),
        revision_frame_ids: state.revisions.keys().copied().collect(),
        revision_numbers: state.revisions.values().copied().collect(),
        seen_again: observations_to_pb(&parts.seen_again),
        weak_observations: parts
            .weak
            .iter()
            .flat_map(|(track, views)| {
                views.iter().map(|(kf, px)| internal::Observation {
                    keyframe_id: *kf,
                    track_id: *track,
                    x: px.x as f32,
                    y: px.y as f32,
                })
            })
            .collect(),
        retired: Some(internal::RetiredFrames {
            before_frame_id: state.frames.retired_before,
            frames: state.retired.frames,
            posed_frames: state.retired.posed,
            trajectory_bytes: state.retired.trajectory_bytes,
        }),
        localized_frames: state
            .frames
            .localized
            .iter()
            .map(|(frame, l)| internal::LocalizedFrame {
                frame_id: *frame,
                anchor_keyframe_id: l.anchor_keyframe,
                relative: Some(pose_to_pb(*frame, 0, &l.relative)),
                next_keyframe_id: l.next_keyframe,
                bracket_length: l.bracket_length,
                interpolated: l.interpolated,
            })
            .collect(),
    }
}

/// The state a checkpoint message holds, or why it cannot be one.
fn from_message(m: internal::MergerCheckpoint) -> Result<MergerState, String> {
    if m.format_version != FORMAT_VERSION {
        return Err(format!(
            "checkpoint format version {}, this egoslam reads {FORMAT_VERSION}",
            m.format_version
        ));
    }
    if m.keyframe_ids.len() != m.keyframe_frame_ids.len()
        || m.revision_frame_ids.len() != m.revision_numbers.len()
    {
        return Err("checkpoint index lists differ in length".into());
    }
    let keyframes = m
        .keyframes
        .iter()
        .map(|k| match &k.pose {
            Some(p) => Ok((k.keyframe_id, (k.segment_id, pose_from_pb(p)))),
            None => Err(format!("checkpoint keyframe {} has no pose", k.keyframe_id)),
        })
        .collect::<Result<_, String>>()?;
    let parts = MapParts {
        keyframes,
        points: m
            .points
            .iter()
            .map(|p| (p.track_id, (p.segment_id, vec3_from_pb(&p.position))))
            .collect(),
        observations: observations_from_pb(&m.observations),
        seen_again: observations_from_pb(&m.seen_again),
        weak: {
            let mut weak: BTreeMap<u64, BTreeMap<u64, Point2<f64>>> = BTreeMap::new();
            for o in &m.weak_observations {
                let px = Point2::new(f64::from(o.x), f64::from(o.y));
                weak.entry(o.track_id)
                    .or_default()
                    .insert(o.keyframe_id, px);
            }
            weak
        },
        current_segment: m.current_segment,
        segments: m.segments,
        provisional: m.provisional_scale.as_ref().map(|p| ProvisionalScale {
            segment: p.segment_id,
            first_keyframe: p.first_keyframe_id,
            pace_before: p.pace_before,
            depth_before: p.depth_before,
            windows_since: p.windows_since,
        }),
        loop_pinned: m
            .loop_pinned
            .as_ref()
            .map(|p| (p.segment_id, p.keyframe_id)),
        mended_steps: m
            .mended_steps
            .iter()
            .map(|p| (p.segment_id, p.keyframe_id))
            .collect(),
    };
    let retired = m.retired.unwrap_or_default();
    Ok(MergerState {
        map: MapBuilder::from_parts(parts),
        frames: FrameIndex {
            frames: m
                .frames
                .iter()
                .map(|f| (f.frame_id, f.timestamp_s))
                .collect(),
            keyframe_frames: m
                .keyframe_ids
                .into_iter()
                .zip(m.keyframe_frame_ids)
                .collect(),
            pending: m
                .pending_frames
                .iter()
                .map(|p| {
                    let tracks = p
                        .tracks
                        .iter()
                        .map(|t| (t.track_id, Point2::new(f64::from(t.x), f64::from(t.y))))
                        .collect();
                    let pending = PendingFrame {
                        next_keyframe: p.next_keyframe_id,
                        tracks,
                    };
                    (p.frame_id, pending)
                })
                .collect(),
            localized: m
                .localized_frames
                .iter()
                .filter_map(|l| {
                    let relative = pose_from_pb(l.relative.as_ref()?);
                    let frame = LocalizedFrame {
                        anchor_keyframe: l.anchor_keyframe_id,
                        relative,
                        next_keyframe: l.next_keyframe_id,
                        bracket_length: l.bracket_length,
                        interpolated: l.interpolated,
                    };
                    Some((l.frame_id, frame))
                })
                .collect(),
            retired_before: retired.before_frame_id,
        },
        stream_id: (m.stream_id != 0).then_some(m.stream_id),
        last_sequence: m.last_sequence,
        finished: m.finished,
        windows: m.windows,
        unsolved_windows: m.unsolved_windows,
        culling_checked_before: m.culling_checked_before,
        patched_tracks: BTreeMap::new(),
        retired: RetiredFrames {
            frames: retired.frames,
            posed: retired.posed_frames,
            trajectory_bytes: retired.trajectory_bytes,
        },
        revisions: m
            .revision_frame_ids
            .iter()
            .copied()
            .zip(m.revision_numbers.iter().copied())
            .collect(),
    })
}

/// `(keyframe, track) -> pixel` observations as their messages.
fn observations_to_pb(
    observations: &BTreeMap<(u64, u64), Point2<f64>>,
) -> Vec<internal::Observation> {
    observations
        .iter()
        .map(|((kf, track), px)| internal::Observation {
            keyframe_id: *kf,
            track_id: *track,
            x: px.x as f32,
            y: px.y as f32,
        })
        .collect()
}

/// The inverse of [`observations_to_pb`].
fn observations_from_pb(
    observations: &[internal::Observation],
) -> BTreeMap<(u64, u64), Point2<f64>> {
    observations
        .iter()
        .map(|o| {
            let px = Point2::new(f64::from(o.x), f64::from(o.y));
            ((o.keyframe_id, o.track_id), px)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_geometry::StampedPose;
    use egoslam_merger::WindowInput;
    use nalgebra::{UnitQuaternion, Vector3};

    #[test]
    fn a_saved_state_loads_back_identical() {
        let mut state = MergerState::for_stream(7);
        let poses = (0..5u64)
            .map(|i| {
                let pose = StampedPose {
                    timestamp: i as f64 * 0.1,
                    position: Vector3::new(i as f64, 0.5, -0.25),
                    rotation: UnitQuaternion::from_euler_angles(0.1 * i as f64, 0.2, 0.0),
                };
                (i, pose)
            })
            .collect();
        state.map.add_window(&WindowInput {
            poses,
            points: vec![(3, Vector3::new(1.0, 2.0, 3.0))],
            observations: vec![(1, 3, Point2::new(320.5, 240.25))],
            weak_observations: vec![(2, 9, Point2::new(100.5, 200.75))],
        });
        let mut parts = state.map.to_parts();
        parts.loop_pinned = Some((0, 3));
        parts.mended_steps = vec![(0, 2)];
        parts.seen_again.insert((4, 3), Point2::new(12.5, 40.75));
        state.map = MapBuilder::from_parts(parts);
        state.frames.frames.insert(4, 0.4);
        state.frames.keyframe_frames.insert(1, 4);
        state.frames.pending.insert(
            5,
            PendingFrame {
                next_keyframe: 2,
                tracks: vec![(3, Point2::new(10.5, 20.25))],
            },
        );
        state.frames.localized.insert(
            3,
            LocalizedFrame {
                anchor_keyframe: 0,
                relative: StampedPose {
                    timestamp: 0.3,
                    position: Vector3::new(0.01, 0.0, 0.02),
                    rotation: UnitQuaternion::from_euler_angles(0.0, 0.01, 0.0),
                },
                next_keyframe: 1,
                bracket_length: 0.05,
                interpolated: true,
            },
        );
        state.last_sequence = Some(3);
        state.revisions.insert(4, 2);
        state.windows = 4;
        state.culling_checked_before = 2;
        state.frames.retired_before = 3;
        state.retired = RetiredFrames {
            frames: 3,
            posed: 2,
            trajectory_bytes: 190,
        };
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(FILE_NAME);
        state.save(&path).expect("save");
        let back = MergerState::load(&path).expect("load").expect("present");
        assert_eq!(back.map.to_parts(), state.map.to_parts());
        assert_eq!(back.frames.frames, state.frames.frames);
        assert_eq!(back.frames.keyframe_frames, state.frames.keyframe_frames);
        assert_eq!(back.frames.pending, state.frames.pending);
        assert_eq!(back.revisions, state.revisions);
        assert_eq!(back.frames.localized, state.frames.localized);
        assert_eq!(
            (back.stream_id, back.last_sequence, back.windows),
            (Some(7), Some(3), 4)
        );
        assert_eq!(back.culling_checked_before, 2);
        assert_eq!(back.frames.retired_before, 3);
        assert_eq!(back.retired, state.retired);
        assert!(MergerState::load(&dir.path().join("none"))
            .expect("absent is fine")
            .is_none());
        std::fs::write(&path, [0xff, 0xff, 0xff]).expect("corrupt");
        assert!(MergerState::load(&path).is_err());
    }
}
