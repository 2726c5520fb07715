//! The scale of a stretch chained with nothing to measure it, settled once the wearer walks.
//!
//! A window chained with [`ScaleSource::Weak`] (no shared points with support, no
//! relocalization, no pace on its side) gets a scale from the centres or the scene depth,
//! and the windows after it chain onto that scale through their shared points. On the
//! rendered 12,000-frame walk this happens where the wearer starts walking again after a
//! stop: the window that spans the restart walks for 0.2 s of its 20 keyframes, too little
//! for a pace, and the scale it got (from the scene depth) was 1.6x off; every later window
//! inherited it (metres per map unit 10 before keyframe 1980, 16 after).
//!
//! Such a stretch is marked provisional. After each later window of the segment, once the
//! keyframes from the stretch's first one on walk long enough for a pace
//! ([`crate::speed_continuity`]), the whole stretch (its keyframes, and the points only its
//! keyframes see) is scaled about its first keyframe to the pace the segment had
//! before the stretch. It is the walking-pace prior of a weak join, applied when the pace
//! after the join can be measured instead of at the join.

use crate::map::{MapBuilder, ProvisionalScale, ScaleSource};
use crate::speed_continuity::SpeedContinuityOptions;
use std::collections::HashSet;

/// Tries after which an unsettled stretch is given up (its scale stays): 5 windows, ~4 s of
/// keyframes while walking, by which a restart after a stop has long shown its pace.
const MAX_TRIES: u32 = 5;

/// What settling a provisional stretch did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SettledScale {
    pub first_keyframe: u64,
    /// Factor applied about the keyframe before the stretch (1 when the paces agreed).
    pub scale: f64,
    pub keyframes: usize,
    pub points: usize,
}

/// Paces that agree within this factor leave the stretch as it is (as for a weak cut inside
/// a window, [`crate::interior_cut::InteriorCutOptions::min_correction`]: the pace varies by
/// 10-20 % over a second of walking).
const MIN_CORRECTION: f64 = 1.25;

/// Largest factor by which the rescaled stretch's scene depth may differ from the depth
/// before it (3). A walk's scene depth changes across a turn or a door (2.5x at the
/// 12,000-frame walk's corner turn), but not by an order of magnitude; a pace that asks
/// for one was measured on noise.
const MAX_DEPTH_CHANGE: f64 = 3.0;

impl MapBuilder {
    /// When a window is chained onto `segment` with `source`, its keyframes from `first_new`
    /// on being new, before they join the map: a weak scale starts a provisional stretch
    /// (replacing any older one).
    pub(crate) fn note_chaining_scale(
        &mut self,
        segment: u32,
        first_new: u64,
        source: ScaleSource,
    ) {
        if source != ScaleSource::Weak {
            return;
        }
        // Called before the window's keyframes join the map: what is there is the past.
        let options = SpeedContinuityOptions::default();
        let Some(depth) = self.recent_scene_depth(segment) else {
            return;
        };
        let floor = options.min_speed_depths_per_s * depth;
        let Some(before) = self
            .keyframes
            .range(..first_new)
            .rev()
            .find(|(_, (s, _))| *s == segment)
            .map(|(_, (_, p))| *p)
        else {
            return;
        };
        self.provisional = self
            .recent_pace(segment, (first_new, &before), floor, &options)
            .map(|pace_before| ProvisionalScale {
                segment,
                first_keyframe: first_new,
                pace_before,
                depth_before: depth,
                windows_since: 0,
            });
        tracing::debug!(first_new, provisional = ?self.provisional, "weakly chained stretch");
    }

    /// The stretch waiting for a pace, if any.
    pub fn provisional_scale(&self) -> Option<ProvisionalScale> {
        self.provisional
    }

    /// Settles the provisional stretch when its keyframes have walked long enough for a
    /// pace; gives it up after [`MAX_TRIES`] or when new windows go elsewhere. The caller
    /// must not run it while a background refinement holds a copy of the stretch's
    /// keyframes (its fold would undo the rescale).
    pub fn settle_provisional_scale(&mut self) -> Option<SettledScale> {
        let p = self.provisional.as_mut()?;
        p.windows_since += 1;
        let p = *p;
        if self.current_segment != Some(p.segment) || p.windows_since > MAX_TRIES {
            tracing::debug!(?p, "provisional scale given up");
            self.provisional = None;
            return None;
        }
        let options = SpeedContinuityOptions::default();
        let depth = self.recent_scene_depth(p.segment)?;
        let floor = options.min_speed_depths_per_s * depth;
        // The newest keyframes: a stretch often starts where the wearer slows into a stop,
        // and the pace to compare is the one walked after it.
        let mut poses: Vec<_> = self
            .keyframes
            .range(p.first_keyframe..)
            .rev()
            .filter(|(_, (s, _))| *s == p.segment)
            .filter(|(id, _)| self.observed_points(**id) >= options.min_observations)
            .map(|(_, (_, pose))| pose)
            .take(options.keyframes)
            .collect();
        poses.reverse();
        let pace_after = crate::speed_continuity::walking_pace(&poses, floor, &options)?;
        self.provisional = None;
        let scale = p.pace_before / pace_after;
        let depth_ratio = scale * depth / p.depth_before;
        let implausible = depth_ratio.max(1.0 / depth_ratio) > MAX_DEPTH_CHANGE;
        if !(scale.is_finite() && scale > 0.0)
            || scale.max(1.0 / scale) <= MIN_CORRECTION
            || implausible
        {
            if implausible {
                tracing::debug!(
                    scale,
                    depth_ratio,
                    "pace correction refused by the scene depth"
                );
            }
            return Some(SettledScale {
                first_keyframe: p.first_keyframe,
                scale: 1.0,
                keyframes: 0,
                points: 0,
            });
        }
        // About the stretch's first keyframe: the step from the keyframe before it carries
        // the weak alignment's error, which a rescale about that keyframe would multiply
        // (21x on the 12,000-frame walk, throwing a 30-keyframe stretch metres away).
        let (keyframes, points) = self.scale_stretch(p.segment, p.first_keyframe, scale)?;
        Some(SettledScale {
            first_keyframe: p.first_keyframe,
            scale,
            keyframes,
            points,
        })
    }
}

impl MapBuilder {
    /// Scales the keyframes of `segment` from `first_keyframe` on about that keyframe's
    /// position by `scale`, and the points only they see; points older keyframes see too
    /// were in the map before the stretch and keep their place. Returns the keyframes and
    /// points moved; `None` when the segment has no keyframe from `first_keyframe` on.
    pub(crate) fn scale_stretch(
        &mut self,
        segment: u32,
        first_keyframe: u64,
        scale: f64,
    ) -> Option<(usize, usize)> {
        let pivot = self
            .keyframes
            .range(first_keyframe..)
            .find(|(_, (s, _))| *s == segment)
            .map(|(_, (_, pose))| pose.position)?;
        let mut keyframes = 0;
        for (_, (s, pose)) in self.keyframes.range_mut(first_keyframe..) {
            if *s == segment {
                pose.position = pivot + (pose.position - pivot) * scale;
                keyframes += 1;
            }
        }
        let seen_after: HashSet<u64> = self
            .observations
            .range((first_keyframe, 0)..)
            .map(|((_, track), _)| *track)
            .collect();
        let seen_before: HashSet<u64> = self
            .observations
            .range(..(first_keyframe, 0))
            .map(|((_, track), _)| *track)
            .filter(|track| seen_after.contains(track))
            .collect();
        let mut points = 0;
        for track in seen_after.difference(&seen_before) {
            if let Some((s, x)) = self.points.get_mut(track) {
                if *s == segment {
                    *x = pivot + (*x - pivot) * scale;
                    points += 1;
                }
            }
        }
        Some((keyframes, points))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::WindowInput;
    use crate::speed_continuity::NEW_SEGMENT_PACE;
    use egoslam_geometry::StampedPose;
    use nalgebra::{UnitQuaternion, Vector3};

    /// Keyframes `ids` at 20 per second at x = `x(time)`, each seeing 60 points 3 units
    /// ahead of `x(first time)` (tracks from `tracks`), the first `blind` seeing nothing.
    fn window(
        ids: std::ops::Range<u64>,
        x: impl Fn(f64) -> f64,
        tracks: u64,
        blind: usize,
    ) -> WindowInput {
        let poses: Vec<(u64, StampedPose)> = ids
            .clone()
            .map(|id| {
                let t = id as f64 * 0.05;
                let pose = StampedPose {
                    timestamp: t,
                    position: Vector3::new(x(t), 0.0, 0.0),
                    rotation: UnitQuaternion::identity(),
                };
                (id, pose)
            })
            .collect();
        let x0 = x(ids.start as f64 * 0.05);
        let points = (0..60)
            .map(|k| (tracks + k, Vector3::new(x0 + 0.1 * k as f64, 0.2, 3.0)))
            .collect();
        WindowInput::seeing_all(poses, points, blind)
    }

    /// A map that walked at a new segment's pace (1 unit/s) until t = 1.5 s (keyframe 30) and then stood, with
    /// the stop chained weakly: the keyframes it shares with the map see nothing in its
    /// window, no point is shared and nothing moves, so nothing measures its scale.
    fn stopped_after_a_walk() -> MapBuilder {
        let mut map = MapBuilder::new();
        let walk = |t: f64| NEW_SEGMENT_PACE * t.min(1.5);
        map.add_window(&window(0..35, walk, 1000, 0));
        map.add_window(&window(30..50, walk, 2000, 5));
        let p = map.provisional_scale().expect("weakly chained");
        assert_eq!(p.first_keyframe, 35);
        assert!((p.pace_before - NEW_SEGMENT_PACE).abs() < 1e-9, "{p:?}");
        map
    }

    #[test]
    fn a_stretch_chained_at_a_stop_takes_the_pace_once_it_walks() {
        let mut map = stopped_after_a_walk();
        assert!(map.settle_provisional_scale().is_none(), "no pace yet");
        // Walking again from t = 2.5 s (keyframe 50); this window's frame is 3x the
        // stop's, but it shares the stop window's points, so it takes that frame's
        // (unmeasured) scale.
        let restart = |t: f64| 1.5 + 3.0 * (t - 2.5).max(0.0);
        let mut walking = window(45..80, restart, 2000, 0);
        for (_, x) in &mut walking.points {
            x.x = 1.5 + (x.x - 1.5) * 3.0;
        }
        map.add_window(&walking);
        let settled = map.settle_provisional_scale().expect("walks now");
        assert_eq!(settled.first_keyframe, 35);
        assert!(settled.keyframes >= 40, "{settled:?}");
        // The map's pace after the stop is the pace before it.
        let (a, b) = (
            map.keyframe(60).expect("kf").1,
            map.keyframe(70).expect("kf").1,
        );
        let pace = (b.position - a.position).norm() / (b.timestamp - a.timestamp);
        assert!((pace - NEW_SEGMENT_PACE).abs() < 0.05, "pace {pace}");
        assert!(map.provisional_scale().is_none());
    }

    #[test]
    fn a_pace_that_would_change_the_scene_depth_fourfold_is_refused() {
        let mut map = stopped_after_a_walk();
        // After the stop the stretch creeps at a quarter of the pace with the scene as deep
        // as before: a slower wearer, not a scale error.
        let creep = |t: f64| 1.5 + 0.25 * (t - 2.5).max(0.0);
        map.add_window(&window(45..80, creep, 2000, 0));
        let before = map.keyframe(79).expect("posed").1.position;
        let settled = map.settle_provisional_scale().expect("settled");
        assert_eq!((settled.scale, settled.keyframes), (1.0, 0), "{settled:?}");
        assert_eq!(map.keyframe(79).expect("posed").1.position, before);
        assert!(map.provisional_scale().is_none());
    }
}
