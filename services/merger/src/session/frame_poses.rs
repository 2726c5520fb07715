//! Which frames' poses can have changed since the last publication, and their poses now.
//!
//! A frame's pose ([`super::frames::pose_frames`]) depends on the keyframes around it in
//! time (interpolation, and the segment it is posed in), on its PnP pose if localized, and
//! on that pose's anchor and next keyframe. So after a window only these frames are posed
//! again: the frames added or localized anew ([`super::frame_tables`] records them), the
//! frames localized against a keyframe that moved, changed segment, came or went, and the
//! frames between the neighbours in time of such a keyframe (before and after the change).
//! Everything else keeps its pose bit for bit, which is what makes the update exact: the
//! poses it yields are those a recomputation of every frame would yield (unit test).
//! Frames past the horizon (`super::frame_retirement`) are not posed again.
//!
//! Between keyframes "in time" is read as "in frame id": the frontend numbers frames in
//! the order of their timestamps (it skips a frame stamped out of order). Should that ever
//! not hold, every frame is posed again at each update.

use super::frames::{pose_frames, posed_keyframes, FrameIndex, PosedFrame};
use crate::MapBuilder;
use egoslam_geometry::StampedPose;
use std::collections::{BTreeSet, HashMap};

/// The keyframes as last seen, to tell what changed.
#[derive(Default)]
pub struct FramePoseTracker {
    /// Every keyframe of the map: id -> (segment, pose).
    keyframes: HashMap<u64, (u32, StampedPose)>,
    /// The keyframes with a frame of this run, in time order (what interpolation uses).
    posed_keyframes: Vec<PosedFrame>,
    /// Set once every frame was posed (the first update poses them all).
    primed: bool,
    /// Cleared, for good, by a frame numbered out of time order.
    in_time_order: bool,
}

/// One update's result.
pub struct FramePoseUpdate {
    /// The map's keyframes with a frame of this run, in time order.
    pub keyframes: Vec<PosedFrame>,
    /// The frames posed again that have a pose, in frame id order.
    pub posed: Vec<PosedFrame>,
    /// The frames posed again that have none now.
    pub unposed: Vec<u64>,
}

impl FramePoseTracker {
    /// Poses again every frame whose pose can have changed since the last call.
    pub fn update(&mut self, map: &MapBuilder, index: &mut FrameIndex) -> FramePoseUpdate {
        let added = index.frames.take_added();
        let relocalized = index.localized.take_changed();
        let keyframes: HashMap<u64, (u32, StampedPose)> =
            map.keyframes().map(|(k, s, p)| (k, (s, *p))).collect();
        let posed_keyframes = posed_keyframes(map, index);
        if !self.primed {
            self.in_time_order = true;
        }
        self.in_time_order &= added.iter().all(|f| in_time_order(index, *f));
        let dirty: Option<BTreeSet<u64>> = (self.primed && self.in_time_order).then(|| {
            let mut dirty: BTreeSet<u64> = added.into_iter().chain(relocalized).collect();
            for k in changed_keys(&self.keyframes, &keyframes) {
                dirty.extend(index.localized.posed_against(k));
            }
            let spans = changed_spans(&self.posed_keyframes, &posed_keyframes)
                .into_iter()
                .chain(changed_spans(&posed_keyframes, &self.posed_keyframes));
            for (from, to) in spans {
                dirty.extend(index.frames.range(from..=to).map(|(f, _)| *f));
            }
            dirty
        });
        // Frames past the horizon are final (`super::frame_retirement`).
        let live = index.retired_before..;
        let frames: Vec<(u64, f64)> = match &dirty {
            Some(dirty) => dirty
                .range(live)
                .filter_map(|f| index.frames.get(f).map(|t| (*f, *t)))
                .collect(),
            None => index.frames.range(live).map(|(f, t)| (*f, *t)).collect(),
        };
        let posed = pose_frames(map, index, &posed_keyframes, frames.iter().copied());
        let posed_ids: BTreeSet<u64> = posed.iter().map(|f| f.frame_id).collect();
        let unposed = frames
            .iter()
            .map(|(f, _)| *f)
            .filter(|f| !posed_ids.contains(f))
            .collect();
        self.keyframes = keyframes;
        self.posed_keyframes.clone_from(&posed_keyframes);
        self.primed = true;
        FramePoseUpdate {
            keyframes: posed_keyframes,
            posed,
            unposed,
        }
    }
}

/// Whether frame `frame` is stamped after the frame numbered before it and before the one
/// numbered after it.
fn in_time_order(index: &FrameIndex, frame: u64) -> bool {
    let Some(t) = index.frames.get(&frame) else {
        return true;
    };
    let before = index.frames.range(..frame).next_back();
    let after = index.frames.range(frame + 1..).next();
    before.is_none_or(|(_, b)| b < t) && after.is_none_or(|(_, a)| a > t)
}

/// The keys whose value differs between `old` and `new`, or that only one holds.
fn changed_keys(
    old: &HashMap<u64, (u32, StampedPose)>,
    new: &HashMap<u64, (u32, StampedPose)>,
) -> Vec<u64> {
    let moved = new.iter().filter(|(k, v)| old.get(k) != Some(v));
    let gone = old.keys().filter(|k| !new.contains_key(k));
    moved.map(|(k, _)| *k).chain(gone.copied()).collect()
}

/// For each keyframe of `list` that `other` lacks or holds differently (segment, pose):
/// the frame ids from its neighbour before to its neighbour after in `list` (from the
/// first id, to the last, at the ends), the frames whose interpolation it can enter.
fn changed_spans(list: &[PosedFrame], other: &[PosedFrame]) -> Vec<(u64, u64)> {
    let other: HashMap<u64, (u32, StampedPose)> = other
        .iter()
        .map(|k| (k.frame_id, (k.segment, k.pose)))
        .collect();
    (0..list.len())
        .filter(|&i| other.get(&list[i].frame_id) != Some(&(list[i].segment, list[i].pose)))
        .map(|i| {
            let from = i.checked_sub(1).map_or(0, |p| list[p].frame_id);
            let to = list.get(i + 1).map_or(u64::MAX, |n| n.frame_id);
            (from, to.max(from))
        })
        .collect()
}

#[cfg(test)]
mod tests;
