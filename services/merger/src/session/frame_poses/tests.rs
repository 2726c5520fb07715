//! The tracker's poses against a recomputation of every frame, through the changes a
//! session makes: windows arriving, keyframes moved, culled (and back), split into
//! segments and joined again, frames localized, re-anchored on an earlier pass and dropped,
//! frames retired past a horizon.

use super::*;
use crate::session::frame_retirement::retire_index;
use crate::session::frames::{posed_frames, LocalizedFrame};
use crate::MapParts;
use nalgebra::{UnitQuaternion, Vector3};
use std::collections::{BTreeMap, BTreeSet};

/// Frames per keyframe: keyframe k is frame `FRAMES_PER_KEYFRAME * k`.
const FRAMES_PER_KEYFRAME: u64 = 5;

struct Session {
    map: MapBuilder,
    index: FrameIndex,
    tracker: FramePoseTracker,
    /// What a client holds: every frame's pose as the updates gave it.
    held: BTreeMap<u64, PosedFrame>,
    next_keyframe: u64,
    random: u64,
    retirements: usize,
}

fn pose(t: f64, x: f64, yaw: f64) -> StampedPose {
    StampedPose {
        timestamp: t,
        position: Vector3::new(x, 0.1 * x, 0.0),
        rotation: UnitQuaternion::from_euler_angles(0.0, yaw, 0.0),
    }
}

impl Session {
    fn new() -> Self {
        Self {
            map: MapBuilder::from_parts(MapParts::default()),
            index: FrameIndex::default(),
            tracker: FramePoseTracker::default(),
            held: BTreeMap::new(),
            next_keyframe: 0,
            random: 0x9e37_79b9_7f4a_7c15,
            retirements: 0,
        }
    }

    fn draw(&mut self, below: u64) -> u64 {
        self.random ^= self.random << 13;
        self.random ^= self.random >> 7;
        self.random ^= self.random << 17;
        self.random % below.max(1)
    }

    fn keyframe_ids(&self) -> Vec<u64> {
        self.map.keyframes().map(|(k, _, _)| k).collect()
    }

    fn add_window(&mut self, keyframes: u64) {
        for _ in 0..keyframes {
            let k = self.next_keyframe;
            self.next_keyframe += 1;
            for f in (k * FRAMES_PER_KEYFRAME).saturating_sub(FRAMES_PER_KEYFRAME - 1)
                ..=k * FRAMES_PER_KEYFRAME
            {
                self.index.frames.insert(f, f as f64 / 30.0);
            }
            let frame = k * FRAMES_PER_KEYFRAME;
            self.index.keyframe_frames.insert(k, frame);
            let segment = self.map.keyframes.values().last().map_or(0, |(s, _)| *s);
            let at = pose(frame as f64 / 30.0, k as f64, 0.01 * k as f64);
            self.map.keyframes.insert(k, (segment, at));
        }
    }

    fn pick_keyframe(&mut self) -> Option<u64> {
        let ids = self.keyframe_ids();
        let i = self.draw(ids.len() as u64) as usize;
        ids.get(i).copied()
    }

    fn apply(&mut self, step: u64) {
        match step {
            0 => {
                let n = 1 + self.draw(4);
                self.add_window(n);
            }
            1 => {
                if let Some(k) = self.pick_keyframe() {
                    let shift = self.draw(100) as f64 * 1e-3;
                    if let Some((_, p)) = self.map.keyframes.get_mut(&k) {
                        p.position.x += shift;
                    }
                }
            }
            2 => {
                if let Some(k) = self.pick_keyframe() {
                    self.map.keyframes.remove(&k);
                }
            }
            3 => {
                // A break from keyframe k on, or its healing.
                if let Some(k) = self.pick_keyframe() {
                    let segment = self.draw(2) as u32;
                    for (_, (s, _)) in self.map.keyframes.range_mut(k..) {
                        *s = segment;
                    }
                }
            }
            4 | 5 => {
                // A frame localized between its keyframes, or re-anchored on a keyframe of
                // an earlier pass (culling's nearest in space).
                let Some(anchor) = self.pick_keyframe() else {
                    return;
                };
                let far = step == 5;
                let frame = if far {
                    let newest = self.index.frames.keys().last().copied().unwrap_or(0);
                    self.draw(newest + 1)
                } else {
                    anchor * FRAMES_PER_KEYFRAME + 1 + self.draw(FRAMES_PER_KEYFRAME - 1)
                };
                if self.index.frames.get(&frame).is_none() {
                    return;
                }
                let next = if far { anchor } else { anchor + 1 };
                // Stamped 0 when far: a posed frame carries its own stamp, whatever the
                // pose it hangs on was stamped with (a PnP without a prior stamps 0).
                let relative = pose(if far { 0.0 } else { frame as f64 / 30.0 }, 0.3, 0.02);
                let bracket_length = if far { 0.0 } else { 1.0 };
                let localized = LocalizedFrame {
                    anchor_keyframe: anchor,
                    relative,
                    next_keyframe: next,
                    bracket_length,
                    interpolated: far,
                };
                self.index.localized.insert(frame, localized);
            }
            6 => {
                // A keyframe culled earlier comes back (frames already known).
                let k = self.draw(self.next_keyframe);
                if self.map.keyframes.contains_key(&k) {
                    return;
                }
                let frame = k * FRAMES_PER_KEYFRAME;
                let segment = self.map.keyframes.range(..k).last().map_or(0, |(_, v)| v.0);
                let at = pose(frame as f64 / 30.0, k as f64 + 0.5, 0.0);
                self.map.keyframes.insert(k, (segment, at));
            }
            7 => {
                // Frames past a horizon of 100-300 frames retire; the map's keyframes
                // keep theirs.
                let newest = self.index.frames.keys().last().copied().unwrap_or(0);
                let before = newest.saturating_sub(100 + self.draw(200));
                if before <= self.index.retired_before {
                    return;
                }
                let keep: BTreeSet<u64> = (self.keyframe_ids().iter())
                    .filter_map(|k| self.index.keyframe_frames.get(k).copied())
                    .collect();
                retire_index(&mut self.index, before, &keep);
                self.held.retain(|f, _| *f >= before);
                self.retirements += 1;
            }
            _ => {
                let localized: Vec<u64> = self.index.localized.keys().copied().collect();
                let i = self.draw(localized.len() as u64) as usize;
                if let Some(frame) = localized.get(i) {
                    self.index.localized.remove(frame);
                }
            }
        }
    }

    /// Updates, checks what is held against every frame posed afresh; returns how many
    /// frames the update posed again.
    fn update_and_check(&mut self) -> usize {
        let update = self.tracker.update(&self.map, &mut self.index);
        let again = update.posed.len() + update.unposed.len();
        for f in update.posed {
            self.held.insert(f.frame_id, f);
        }
        for f in update.unposed {
            self.held.remove(&f);
        }
        let keyframes = posed_keyframes(&self.map, &self.index);
        let live = self.index.retired_before..;
        let fresh = posed_frames(&self.map, &self.index, &keyframes, live);
        let ids = |v: &mut dyn Iterator<Item = u64>| v.collect::<Vec<_>>();
        assert_eq!(
            ids(&mut self.held.keys().copied()),
            ids(&mut fresh.iter().map(|f| f.frame_id))
        );
        for f in &fresh {
            assert_eq!(
                Some(f.pose.timestamp),
                self.index.frames.get(&f.frame_id).copied(),
                "frame {} posed with another frame's stamp",
                f.frame_id
            );
            let held = &self.held[&f.frame_id];
            let same =
                (held.segment, held.pose, held.interpolated) == (f.segment, f.pose, f.interpolated);
            assert!(same, "frame {}: {held:?} != {f:?}", f.frame_id);
        }
        again
    }
}

#[test]
fn the_updated_poses_are_those_of_a_full_recomputation() {
    let mut session = Session::new();
    session.add_window(20);
    assert_eq!(
        session.update_and_check(),
        session.index.frames.len(),
        "first: all"
    );
    for round in 0..400 {
        let step = session.draw(9);
        session.apply(step);
        if round % 3 == 0 {
            session.add_window(2);
        }
        session.update_and_check();
    }
    let newest = session.index.frames.keys().last().copied().unwrap_or(0);
    assert!(newest > 1000, "{newest} frames");
    assert!(session.retirements > 5 && session.index.retired_before > 500);
}

#[test]
fn a_window_poses_again_only_the_frames_around_what_it_changed() {
    let mut session = Session::new();
    session.add_window(200);
    session.update_and_check();
    // A new window of 10 keyframes, whose refinement moved the newest 5 before it.
    for k in 195..200 {
        if let Some((_, p)) = session.map.keyframes.get_mut(&k) {
            p.position.y += 0.01;
        }
    }
    session.add_window(10);
    let again = session.update_and_check();
    let expected = (210 - 194) * FRAMES_PER_KEYFRAME as usize + 1;
    assert!(
        again <= expected,
        "{again} frames posed again, of {}",
        session.index.frames.len()
    );
    assert_eq!(session.update_and_check(), 0, "nothing changed");
}

#[test]
fn frames_out_of_time_order_are_all_posed_again() {
    let mut session = Session::new();
    session.add_window(10);
    session.update_and_check();
    // A frame numbered after the newest but stamped before it.
    session.index.frames.insert(1000, 0.01);
    assert_eq!(session.update_and_check(), session.index.frames.len());
    assert_eq!(session.update_and_check(), session.index.frames.len());
}
