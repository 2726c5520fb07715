//! Frames older than the horizon leave the merger: a day of 30 fps video is ~1.7 million
//! frames, and each held its stamp, its PnP pose and its published pose in memory and in
//! the checkpoint (~250 B), rewritten with trajectory.tum at every persist. Past the
//! horizon a frame's pose is final: the service appends it to trajectory.tum's frozen head
//! and drops it (docs/merger.md, "Frame horizon"). The map itself is not touched: its
//! keyframes keep their frames (poses, ages), and so do the culled keyframes whose patches
//! relocalization still places at their frame's pose.

use super::frames::FrameIndex;
use super::state::MergerState;
use std::collections::BTreeSet;

/// What the frames retired so far were (counted across restarts, in the checkpoint).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RetiredFrames {
    /// Frames dropped from the index.
    pub frames: u64,
    /// Of those, the frames the map posed when they went (trajectory.tum's frozen rows).
    pub posed: u64,
    /// Length of trajectory.tum's frozen head, bytes: the rows of retired frames, never
    /// rewritten.
    pub trajectory_bytes: u64,
}

/// What one retirement did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Retirement {
    /// Frames numbered below this are retired now (the index's `retired_before`).
    pub before: u64,
    /// Frames dropped from the index by this retirement.
    pub frames: usize,
    /// Of those, frames still waiting for a keyframe (never posed).
    pub pending: usize,
}

/// The first frame whose timestamp lies within `horizon_s` of the newest frame's (frames
/// are numbered in time order); `None` when no frame is past the horizon.
fn horizon_start(index: &FrameIndex, horizon_s: f64) -> Option<u64> {
    let (_, newest) = index.frames.last_key_value()?;
    let oldest_kept = newest - horizon_s;
    let first_within = index
        .frames
        .range(index.retired_before..)
        .find(|(_, t)| **t >= oldest_kept)
        .map(|(f, _)| *f)?;
    (first_within > index.retired_before).then_some(first_within)
}

/// The frames of `keyframes` (those the index knows).
fn frames_of(state: &MergerState, keyframes: impl Iterator<Item = u64>) -> BTreeSet<u64> {
    let frame = |k| state.frames.keyframe_frames.get(&k).copied();
    keyframes.filter_map(frame).collect()
}

/// The frames of the map's keyframes (their poses and ages).
pub fn map_keyframe_frames(state: &MergerState) -> BTreeSet<u64> {
    frames_of(state, state.map.keyframes().map(|(k, _, _)| k))
}

/// The frames the map itself still needs below any horizon: its keyframes' and those of
/// culled keyframes whose patches it keeps (placed at their frame's pose).
fn frames_the_map_needs(state: &MergerState) -> BTreeSet<u64> {
    let mut frames = map_keyframe_frames(state);
    frames.extend(frames_of(state, state.patched_tracks.keys().copied()));
    frames
}

/// Retires the frames more than `horizon_s` seconds of stream time older than the newest:
/// their stamps, PnP poses and pending tracks go, and the keyframe -> frame entries of
/// keyframes gone from the map with them. `None` when nothing is past the horizon (or it
/// is infinite).
pub fn retire_frames(state: &mut MergerState, horizon_s: f64) -> Option<Retirement> {
    if !horizon_s.is_finite() {
        return None;
    }
    let before = horizon_start(&state.frames, horizon_s)?;
    let keep = frames_the_map_needs(state);
    let retirement = retire_index(&mut state.frames, before, &keep);
    state.retired.frames += retirement.frames as u64;
    Some(retirement)
}

/// Retires from `index` the frames numbered below `before` but those in `keep`.
pub fn retire_index(index: &mut FrameIndex, before: u64, keep: &BTreeSet<u64>) -> Retirement {
    let frames = index.frames.retire(before, keep);
    index.localized.retire(before, keep);
    let pending_before = index.pending.len();
    index.pending.retain(|f, _| *f >= before);
    let pending = pending_before - index.pending.len();
    index
        .keyframe_frames
        .retain(|_, frame| *frame >= before || keep.contains(frame));
    index.retired_before = before;
    Retirement {
        before,
        frames,
        pending,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::frames::{LocalizedFrame, PendingFrame};
    use egoslam_geometry::StampedPose;
    use nalgebra::{UnitQuaternion, Vector3};

    fn at(t: f64) -> StampedPose {
        StampedPose {
            timestamp: t,
            position: Vector3::new(t, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        }
    }

    /// 100 frames at 10 fps, keyframe k at frame 10 k (k = 0..10), frames 1-9 of each
    /// keyframe localized against it.
    fn state() -> MergerState {
        let mut state = MergerState::default();
        for f in 0..100u64 {
            state.frames.frames.insert(f, f as f64 / 10.0);
            if f % 10 == 0 {
                state.frames.keyframe_frames.insert(f / 10, f);
                state.map.keyframes.insert(f / 10, (0, at(f as f64 / 10.0)));
            } else {
                let l = LocalizedFrame {
                    anchor_keyframe: f / 10,
                    relative: at(0.0),
                    next_keyframe: f / 10 + 1,
                    bracket_length: 1.0,
                    interpolated: false,
                };
                state.frames.localized.insert(f, l);
            }
        }
        state
    }

    #[test]
    fn frames_past_the_horizon_go_but_what_the_map_needs_stays() {
        let mut state = state();
        // Keyframe 2 was culled (gone), keyframe 3 too but keeps patches, keyframe 6
        // culled within the horizon.
        for k in [2, 3, 6] {
            state.map.keyframes.remove(&k);
        }
        state.patched_tracks.insert(3, vec![(77, 128)]);
        state.frames.pending.insert(
            5,
            PendingFrame {
                next_keyframe: 1,
                tracks: Vec::new(),
            },
        );
        assert_eq!(retire_frames(&mut state, f64::INFINITY), None);
        // Newest frame 9.9 s: a 4.55 s horizon keeps frames from 5.35 s, i.e. 54 on.
        let r = retire_frames(&mut state, 4.55).expect("frames past the horizon");
        assert_eq!((r.before, r.pending), (54, 1));
        let kept: Vec<u64> = state.frames.frames.range(..54).map(|(f, _)| *f).collect();
        assert_eq!(kept, vec![0, 10, 30, 40, 50], "map keyframes' and 3's");
        assert_eq!(r.frames, 54 - 5);
        assert_eq!(state.retired.frames, 49);
        assert_eq!(state.frames.localized.range(..54).count(), 0);
        assert!(state.frames.localized.contains_key(&54));
        let keyframes: Vec<u64> = state.frames.keyframe_frames.keys().copied().collect();
        assert_eq!(
            keyframes,
            vec![0, 1, 3, 4, 5, 6, 7, 8, 9],
            "2 gone with its frame"
        );
        assert_eq!(state.frames.retired_before, 54);
        // Nothing new past the horizon: nothing to do; the next frames move it on.
        assert_eq!(retire_frames(&mut state, 4.55), None);
        state.frames.frames.insert(100, 10.0);
        let r = retire_frames(&mut state, 4.55).expect("one more");
        assert_eq!((r.before, r.frames), (55, 1));
        assert_eq!(state.retired.frames, 50);
    }
}
