//! The per-frame tables of [`super::frames::FrameIndex`] that decide a frame's pose, kept
//! so that each change is recorded: the publication recomputes only the frames whose pose
//! can have changed (`super::frame_poses`), since recomputing every frame of a day-long
//! stream after every window would cost more than the window took to arrive. They read as
//! the `BTreeMap` they wrap; writes go through their methods, which record the frame.

use super::frames::LocalizedFrame;
use std::collections::{BTreeMap, BTreeSet};
use std::ops::Deref;

/// The frames of `table` numbered below `before` that `keep` does not hold.
fn retiring<V>(table: &BTreeMap<u64, V>, before: u64, keep: &BTreeSet<u64>) -> Vec<u64> {
    let below = table.range(..before).map(|(f, _)| *f);
    below.filter(|f| !keep.contains(f)).collect()
}

/// frame id -> timestamp, recording the frames added.
#[derive(Debug, Clone, Default)]
pub struct FrameStamps {
    stamps: BTreeMap<u64, f64>,
    added: BTreeSet<u64>,
}

/// Equal when they hold the same stamps (what was recorded as added is not content).
impl PartialEq for FrameStamps {
    fn eq(&self, other: &Self) -> bool {
        self.stamps == other.stamps
    }
}

impl FrameStamps {
    /// Records a frame's timestamp; a frame new to the table is recorded as added.
    pub fn insert(&mut self, frame: u64, timestamp: f64) {
        if self.stamps.insert(frame, timestamp) != Some(timestamp) {
            self.added.insert(frame);
        }
    }

    /// The frames added or restamped since the last call.
    pub fn take_added(&mut self) -> BTreeSet<u64> {
        std::mem::take(&mut self.added)
    }

    /// Drops the frames numbered below `before` but those `keep` holds (frames retired
    /// past the horizon, `super::frame_retirement`); not recorded as a change, as nothing
    /// poses them any more. Returns how many went.
    pub fn retire(&mut self, before: u64, keep: &BTreeSet<u64>) -> usize {
        let old = retiring(&self.stamps, before, keep);
        for f in &old {
            self.stamps.remove(f);
            self.added.remove(f);
        }
        old.len()
    }
}

impl Deref for FrameStamps {
    type Target = BTreeMap<u64, f64>;
    fn deref(&self) -> &Self::Target {
        &self.stamps
    }
}

impl FromIterator<(u64, f64)> for FrameStamps {
    fn from_iter<I: IntoIterator<Item = (u64, f64)>>(iter: I) -> Self {
        Self {
            stamps: iter.into_iter().collect(),
            added: BTreeSet::new(),
        }
    }
}

/// frame id -> PnP pose relative to its anchor keyframe, with the frames posed against
/// each keyframe (as anchor or as the bracket's next keyframe) and the frames changed.
#[derive(Debug, Clone, Default)]
pub struct LocalizedFrames {
    frames: BTreeMap<u64, LocalizedFrame>,
    /// keyframe id -> the frames whose pose it enters.
    by_keyframe: BTreeMap<u64, BTreeSet<u64>>,
    changed: BTreeSet<u64>,
}

/// Equal when they hold the same frames (the index and the record follow from them).
impl PartialEq for LocalizedFrames {
    fn eq(&self, other: &Self) -> bool {
        self.frames == other.frames
    }
}

impl LocalizedFrames {
    pub fn insert(&mut self, frame: u64, localized: LocalizedFrame) {
        if let Some(old) = self.frames.insert(frame, localized) {
            self.unlink(frame, &old);
        }
        self.link(frame, &localized);
        self.changed.insert(frame);
    }

    pub fn remove(&mut self, frame: &u64) -> Option<LocalizedFrame> {
        let old = self.frames.remove(frame)?;
        self.unlink(*frame, &old);
        self.changed.insert(*frame);
        Some(old)
    }

    /// The frames whose pose keyframe `keyframe` enters.
    pub fn posed_against(&self, keyframe: u64) -> impl Iterator<Item = u64> + '_ {
        self.by_keyframe
            .get(&keyframe)
            .into_iter()
            .flatten()
            .copied()
    }

    /// The frames inserted, replaced or removed since the last call.
    pub fn take_changed(&mut self) -> BTreeSet<u64> {
        std::mem::take(&mut self.changed)
    }

    /// Drops the frames numbered below `before` but those `keep` holds, as
    /// [`FrameStamps::retire`] does (not recorded as a change).
    pub fn retire(&mut self, before: u64, keep: &BTreeSet<u64>) -> usize {
        let old = retiring(&self.frames, before, keep);
        for f in &old {
            if let Some(l) = self.frames.remove(f) {
                self.unlink(*f, &l);
            }
            self.changed.remove(f);
        }
        old.len()
    }

    fn link(&mut self, frame: u64, l: &LocalizedFrame) {
        for keyframe in [l.anchor_keyframe, l.next_keyframe] {
            self.by_keyframe.entry(keyframe).or_default().insert(frame);
        }
    }

    fn unlink(&mut self, frame: u64, l: &LocalizedFrame) {
        for keyframe in [l.anchor_keyframe, l.next_keyframe] {
            if let Some(frames) = self.by_keyframe.get_mut(&keyframe) {
                frames.remove(&frame);
                if frames.is_empty() {
                    self.by_keyframe.remove(&keyframe);
                }
            }
        }
    }
}

impl Deref for LocalizedFrames {
    type Target = BTreeMap<u64, LocalizedFrame>;
    fn deref(&self) -> &Self::Target {
        &self.frames
    }
}

impl FromIterator<(u64, LocalizedFrame)> for LocalizedFrames {
    fn from_iter<I: IntoIterator<Item = (u64, LocalizedFrame)>>(iter: I) -> Self {
        let mut table = Self::default();
        for (frame, l) in iter {
            table.insert(frame, l);
        }
        table.changed.clear();
        table
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_geometry::StampedPose;
    use nalgebra::{UnitQuaternion, Vector3};

    fn localized(anchor: u64, next: u64) -> LocalizedFrame {
        LocalizedFrame {
            anchor_keyframe: anchor,
            relative: StampedPose {
                timestamp: 0.0,
                position: Vector3::zeros(),
                rotation: UnitQuaternion::identity(),
            },
            next_keyframe: next,
            bracket_length: 0.0,
            interpolated: false,
        }
    }

    #[test]
    fn a_frame_is_listed_under_the_keyframes_it_hangs_on_now() {
        let mut table: LocalizedFrames = [(10, localized(1, 2)), (11, localized(1, 2))]
            .into_iter()
            .collect();
        assert!(
            table.take_changed().is_empty(),
            "a loaded table starts clean"
        );
        let under = |t: &LocalizedFrames, k| t.posed_against(k).collect::<Vec<_>>();
        assert_eq!(under(&table, 1), vec![10, 11]);
        // Culling re-anchors frame 11 on keyframe 7 of an earlier pass.
        table.insert(11, localized(7, 7));
        assert_eq!((under(&table, 2), under(&table, 7)), (vec![10], vec![11]));
        table.remove(&10);
        assert!(under(&table, 1).is_empty() && under(&table, 2).is_empty());
        assert_eq!(table.take_changed(), BTreeSet::from([10, 11]));
        assert!(table.take_changed().is_empty());
    }

    #[test]
    fn retired_frames_leave_the_tables_and_their_index_unrecorded() {
        let mut stamps: FrameStamps = (0..10).map(|f| (f, f as f64)).collect();
        stamps.insert(3, 3.5);
        stamps.insert(8, 8.5);
        assert_eq!(stamps.retire(6, &BTreeSet::from([2])), 5);
        assert_eq!(
            stamps.keys().copied().collect::<Vec<_>>(),
            vec![2, 6, 7, 8, 9]
        );
        assert_eq!(
            stamps.take_added(),
            BTreeSet::from([8]),
            "3 went unrecorded"
        );
        let mut table: LocalizedFrames = [(1, localized(0, 1)), (4, localized(3, 5))]
            .into_iter()
            .chain([(7, localized(3, 5))])
            .collect();
        table.insert(4, localized(3, 6));
        assert_eq!(table.retire(5, &BTreeSet::new()), 2);
        assert_eq!(table.keys().copied().collect::<Vec<_>>(), vec![7]);
        assert!(table.take_changed().is_empty());
        let under = |k| table.posed_against(k).collect::<Vec<_>>();
        assert_eq!((under(0), under(3), under(6)), (vec![], vec![7], vec![]));
    }

    #[test]
    fn only_new_or_restamped_frames_count_as_added() {
        let mut stamps: FrameStamps = [(1, 0.1)].into_iter().collect();
        stamps.insert(1, 0.1); // an overlapping window repeats it
        stamps.insert(2, 0.2);
        stamps.insert(1, 0.15);
        assert_eq!(stamps.take_added(), BTreeSet::from([1, 2]));
        assert_eq!(stamps.get(&1), Some(&0.15));
    }
}
