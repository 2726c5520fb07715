//! A step of the map's scale inside a sharp turn while walking, mended by the walking pace.
//!
//! Through a fast turn with motion blur, the points seen on both sides of the turn are few
//! and poorly measured, and a window solved across it can stretch or shrink its keyframes
//! after the turn against those before: on a rendered 900-frame walk with blur over the
//! frame time (`egoslam synth --blur-samples 9`), the turn's windows came out with their
//! second half 0.76x the scale of their first, bundle adjustment started from the truth
//! settling at 1-2.5 % of their path (0.3-0.5 % without blur), and every window after was
//! chained onto that scale: the map's length per true metre stepped from 0.80 to 0.65 in
//! 0.4 s and stayed there, 1.7 % ATE over the walk.
//!
//! A walker's pace is steady on either side of a turn (the prior of
//! [`crate::speed_continuity`] and [`crate::scale_break`]), so the step shows as a jump of
//! the map's pace: the median speed of the keyframes over two seconds before a keyframe
//! against the two seconds after it. After each window the newest keyframes are searched
//! for such a jump; it is mended (the keyframes after it, and the points only they see,
//! scaled about it) only where everything says it is the solve and not the wearer: the
//! pace is steady on both sides (a walker's steps vary by a few per cent, a hand-held
//! camera's by 30-50 %), the head turns sharply there (where few points link the two
//! sides), and the jump is larger than the pace's wander but smaller than a break the loop
//! closure or the pace join handle.
//!
//! The map's background refinement (global bundle adjustment) can pull a mended step
//! back: on that walk, whose whole-walk adjustment started from the truth settles at
//! 0.06 m, the refinement started from the mended map settled with the step at 0.88x
//! (0.32 m), as the blurred turn's observations fit either. So each mended step is
//! remembered and, after every refinement is folded in, mended again where the pace
//! still jumps there.

use crate::map::MapBuilder;
use crate::scale_break::{pace_steps, paces_around, PaceStep};
use crate::speed_continuity::SpeedContinuityOptions;
use egoslam_geometry::StampedPose;

/// When a jump of the pace is mended; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TurnScaleStepOptions {
    /// Seconds of keyframes on each side of a candidate whose paces are compared (default
    /// 2, [`crate::scale_break::ScaleBreakOptions::pace_window_s`]: a few strides).
    pub pace_window_s: f64,
    /// Fewest moving keyframe steps on each side (default 8).
    pub min_steps: usize,
    /// Largest spread of the steps' paces on each side: median absolute deviation over
    /// the median (default 0.15; the rendered walks' keyframes 0.01-0.06, a hand-held
    /// camera's (TUM fr1_rpy) 0.3-0.5, a head shake's 0.37 on one side).
    pub max_pace_spread: f64,
    /// Smallest jump mended, a factor either way (default 1.1: the rendered 900-frame walk
    /// without blur jumps by at most 1.04 between two seconds and the next; the blurred
    /// walks' second corner by 1.11, 0.185 -> 0.071 m on seed 12 when mended; the
    /// 1500-frame walks of the walks suite are unchanged at 1.1).
    pub min_jump: f64,
    /// Largest jump mended (default 1.6): beyond, a window broke outright, which the pace
    /// join and the interior cut take (`window_alignment`, `interior_cut`).
    pub max_jump: f64,
    /// The step is the solve's only inside a sharp turn: the head turned by at least this
    /// much between the keyframes `turn_span_s` before and after it (defaults 45 deg and
    /// 0.5 s; the blurred walks' corners turned 49-79 deg there). Elsewhere a step of the
    /// pace is a wearer slowing down or speeding up, and is left alone: the recorded Aria
    /// head trajectory (`egoslam synth --path replay`) slows by 1.15x during a 31 deg
    /// glance, and mended at 30 deg its ATE went from 0.006 to 0.078 m.
    pub min_turn_deg: f64,
    pub turn_span_s: f64,
    /// A jump is mended once the keyframes reach this long past its pace window (default
    /// 1 s): the strongest jump found with fewer keyframes after it lies before the step,
    /// and its pace window then mixes both scales.
    pub settle_s: f64,
    /// Smallest jump mended again after a refinement, where a step was mended before
    /// (default 1.05, the pace's wander between two seconds and the next on the walks).
    pub min_jump_again: f64,
}

impl Default for TurnScaleStepOptions {
    fn default() -> Self {
        Self {
            pace_window_s: 2.0,
            min_steps: 8,
            max_pace_spread: 0.15,
            min_jump: 1.1,
            max_jump: 1.6,
            min_turn_deg: 45.0,
            turn_span_s: 0.5,
            settle_s: 1.0,
            min_jump_again: 1.05,
        }
    }
}

/// A mended step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MendedStep {
    /// The last keyframe with the old scale.
    pub after_keyframe: u64,
    /// The pace after it over the pace before, as found.
    pub pace_ratio: f64,
    pub keyframes: usize,
    pub points: usize,
}

/// Mended steps remembered for mending again, the newest (32: a background refinement
/// adjusts the newest 1500 keyframes, a minute or two of walking, with a sharp corner every
/// 10-25 s on the rendered walks; the state stays bounded on an all-day run).
const MAX_REMEMBERED_STEPS: usize = 32;

impl MapBuilder {
    /// Finds a pace jump inside the current segment's newest keyframes (see the module)
    /// and mends it. The caller must not run it while a background refinement holds a copy
    /// of the keyframes after the jump (its fold would undo the mend); `may_touch` says
    /// whether keyframes from an id on may be moved.
    pub fn mend_turn_scale_step(
        &mut self,
        options: &TurnScaleStepOptions,
        may_touch: impl Fn(u64) -> bool,
    ) -> Option<MendedStep> {
        let segment = self.current_segment?;
        let (newest_id, newest) = self
            .keyframes
            .iter()
            .rev()
            .find(|(_, (s, _))| *s == segment)
            .map(|(id, (_, p))| (*id, p.timestamp))?;
        // Two pace windows on each side of the newest candidate, which lies a pace window
        // and `settle_s` before the newest keyframe.
        let since = newest - 3.0 * options.pace_window_s - options.settle_s;
        let keyframes = self.well_seen_keyframes(segment, newest_id, since..=newest);
        let steps = walking_steps(&keyframes, self.walking_floor(segment)?);
        let first = keyframes.first()?.1.timestamp;
        let latest = newest - options.pace_window_s - options.settle_s;
        let (index, _) = keyframes
            .iter()
            .enumerate()
            .filter(|(_, (_, p))| {
                p.timestamp >= first + options.pace_window_s
                    && p.timestamp <= newest - options.pace_window_s
            })
            .filter_map(|(i, (_, p))| Some((i, pace_ratio_at(&steps, p.timestamp, options)?)))
            .max_by(|a, b| a.1.ln().abs().total_cmp(&b.1.ln().abs()))?;
        let index = step_location(&keyframes, &steps, index, options.pace_window_s);
        let ratio = pace_ratio_at(&steps, keyframes[index].1.timestamp, options)?;
        let (after_keyframe, pose) = keyframes[index];
        // The strongest jump is where the step is only once the keyframes around it have
        // all been compared: one found nearer the newest may move on with the next window.
        if pose.timestamp > latest {
            return None;
        }
        let turn_deg = turn_around(&keyframes, pose.timestamp, options.turn_span_s);
        tracing::debug!(
            after_keyframe,
            pace_ratio = ratio,
            turn_deg,
            "strongest pace jump in the newest keyframes"
        );
        let off = ratio.max(1.0 / ratio);
        if !(options.min_jump..=options.max_jump).contains(&off)
            || turn_deg < options.min_turn_deg
            || !may_touch(after_keyframe)
        {
            return None;
        }
        let (keyframes, points) = self.scale_stretch(segment, after_keyframe, 1.0 / ratio)?;
        self.mended_steps.push((segment, after_keyframe));
        if self.mended_steps.len() > MAX_REMEMBERED_STEPS {
            self.mended_steps.remove(0);
        }
        Some(MendedStep {
            after_keyframe,
            pace_ratio: ratio,
            keyframes,
            points,
        })
    }

    /// Mends again, after a refinement, the steps mended before where the pace still
    /// jumps by [`TurnScaleStepOptions::min_jump_again`] or more.
    pub fn mend_turn_scale_steps_again(
        &mut self,
        options: &TurnScaleStepOptions,
    ) -> Vec<MendedStep> {
        let mut mended = Vec::new();
        // A step whose keyframe left the map (culled, or a map started again) is forgotten.
        let keyframes = &self.keyframes;
        self.mended_steps
            .retain(|(segment, id)| keyframes.get(id).is_some_and(|(s, _)| s == segment));
        for (segment, after_keyframe) in self.mended_steps.clone() {
            let Some((_, pose)) = self.keyframes.get(&after_keyframe).copied() else {
                continue;
            };
            let Some(floor) = self.walking_floor(segment) else {
                continue;
            };
            let span = options.pace_window_s;
            let keyframes = self.well_seen_keyframes(
                segment,
                after_keyframe,
                pose.timestamp - span..=pose.timestamp + span,
            );
            let steps = walking_steps(&keyframes, floor);
            let Some(ratio) = pace_ratio_at(&steps, pose.timestamp, options) else {
                continue;
            };
            let off = ratio.max(1.0 / ratio);
            if !(options.min_jump_again..=options.max_jump).contains(&off) {
                continue;
            }
            if let Some((keyframes, points)) =
                self.scale_stretch(segment, after_keyframe, 1.0 / ratio)
            {
                mended.push(MendedStep {
                    after_keyframe,
                    pace_ratio: ratio,
                    keyframes,
                    points,
                });
            }
        }
        mended
    }

    /// The keyframes of `segment` in the time range with enough inlier observations for
    /// their centres to count ([`SpeedContinuityOptions::min_observations`]), in order.
    fn well_seen_keyframes(
        &self,
        segment: u32,
        anchor: u64,
        times: std::ops::RangeInclusive<f64>,
    ) -> Vec<(u64, StampedPose)> {
        let min_observations = SpeedContinuityOptions::default().min_observations;
        // Keyframe ids follow the frames' time: the range is walked out from the anchor.
        let well_seen = |(id, (s, p)): (&u64, &(u32, StampedPose))| {
            (*s == segment && self.observed_points(*id) >= min_observations).then_some((*id, *p))
        };
        let mut keyframes: Vec<(u64, StampedPose)> = self
            .keyframes
            .range(..=anchor)
            .rev()
            .take_while(|(_, (_, p))| p.timestamp >= *times.start())
            .filter(|(_, (_, p))| p.timestamp <= *times.end())
            .filter_map(well_seen)
            .collect();
        keyframes.reverse();
        keyframes.extend(
            self.keyframes
                .range(anchor.saturating_add(1)..)
                .take_while(|(_, (_, p))| p.timestamp <= *times.end())
                .filter_map(well_seen),
        );
        keyframes
    }

    /// The slowest keyframe step that counts as walking, map units per second
    /// ([`SpeedContinuityOptions::min_speed_depths_per_s`] of the recent scene depth).
    fn walking_floor(&self, segment: u32) -> Option<f64> {
        let depth = self.recent_scene_depth(segment)?;
        Some(SpeedContinuityOptions::default().min_speed_depths_per_s * depth)
    }
}

/// The steps between consecutive `keyframes` at `floor` per second or faster.
fn walking_steps(keyframes: &[(u64, StampedPose)], floor: f64) -> Vec<PaceStep> {
    pace_steps(keyframes)
        .into_iter()
        .filter(|s| s.2.is_finite() && s.2 >= floor)
        .collect()
}

/// The median pace of the steps in the pace window after `t` over that of the window
/// before it; `None` unless both sides have enough steps and are steady.
fn pace_ratio_at(steps: &[PaceStep], t: f64, options: &TurnScaleStepOptions) -> Option<f64> {
    let (before, after) = paces_around(steps, t, options.pace_window_s);
    if before.len() < options.min_steps || after.len() < options.min_steps {
        return None;
    }
    let (b, b_spread) = steady(before)?;
    let (a, a_spread) = steady(after)?;
    let ratio = a / b;
    (b_spread <= options.max_pace_spread
        && a_spread <= options.max_pace_spread
        && ratio.is_finite()
        && ratio > 0.0)
        .then_some(ratio)
}

/// Where in the half pace window around `keyframes[found]` a step of the pace fits the
/// steps best: the medians compare equally anywhere the step is inside both pace windows,
/// so the split is the one whose two sides' log paces deviate least from their medians.
fn step_location(
    keyframes: &[(u64, StampedPose)],
    steps: &[PaceStep],
    found: usize,
    pace_window_s: f64,
) -> usize {
    let t = keyframes[found].1.timestamp;
    let (times, near): (Vec<f64>, Vec<f64>) = steps
        .iter()
        .filter(|s| s.0 >= t - pace_window_s && s.1 <= t + pace_window_s)
        .map(|s| (s.1, s.2.ln()))
        .unzip();
    let deviation = |v: &[f64]| {
        crate::median(v.to_vec()).map_or(0.0, |m| v.iter().map(|x| (x - m).abs()).sum())
    };
    let cost = |split: f64| {
        let k = times.partition_point(|&end| end <= split);
        deviation(&near[..k]) + deviation(&near[k..])
    };
    (0..keyframes.len())
        .filter(|&i| (keyframes[i].1.timestamp - t).abs() <= pace_window_s / 2.0)
        .min_by(|&a, &b| cost(keyframes[a].1.timestamp).total_cmp(&cost(keyframes[b].1.timestamp)))
        .unwrap_or(found)
}

/// The median of `paces` and their median absolute deviation over it.
fn steady(paces: Vec<f64>) -> Option<(f64, f64)> {
    let m = crate::median(paces.clone())?;
    let deviation = crate::median(paces.iter().map(|p| (p - m).abs()).collect())?;
    (m > 0.0).then_some((m, deviation / m))
}

/// The angle between the orientations of the keyframes nearest `span` before and after
/// `t`, degrees.
fn turn_around(keyframes: &[(u64, StampedPose)], t: f64, span: f64) -> f64 {
    let at = |t: f64| {
        keyframes
            .iter()
            .min_by(|a, b| {
                (a.1.timestamp - t)
                    .abs()
                    .total_cmp(&(b.1.timestamp - t).abs())
            })
            .map(|(_, p)| p.rotation)
    };
    match (at(t - span), at(t + span)) {
        (Some(a), Some(b)) => a.angle_to(&b).to_degrees(),
        _ => 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::MapParts;
    use nalgebra::{UnitQuaternion, Vector3};

    const RATE: f64 = 30.0;
    const PACE: f64 = 1.2;

    /// A walk along x at 1.2 units/s for 10 s, one keyframe per frame at 30 fps, whose head
    /// yaws by `turn_deg` between 5.5 and 6.5 s; every keyframe sees 40 points 3 units ahead
    /// (each point seen by ten keyframes). From 6 s on the map's scale is `step` times the
    /// walk's (keyframes and the points only they see), about the keyframe at 6 s; the
    /// pace of keyframe `k` is also multiplied by `wobble(k)`.
    fn walk(turn_deg: f64, step: f64, wobble: impl Fn(u64) -> f64) -> MapBuilder {
        let mut parts = MapParts::default();
        let mut x = 0.0;
        let step_at = (6.0 * RATE) as u64;
        let mut pivot = 0.0;
        for k in 0..=(10.0 * RATE) as u64 {
            let t = k as f64 / RATE;
            if k > 0 {
                x += PACE / RATE * wobble(k) * if k > step_at { step } else { 1.0 };
            }
            if k == step_at {
                pivot = x;
            }
            let yaw = turn_deg.to_radians() * ((t - 5.5).clamp(0.0, 1.0));
            let rotation = UnitQuaternion::from_euler_angles(0.0, yaw, 0.0);
            let position = Vector3::new(x, 0.0, 0.0);
            parts.keyframes.insert(
                k,
                (
                    0,
                    StampedPose {
                        timestamp: t,
                        position,
                        rotation,
                    },
                ),
            );
            let depth = if k > step_at { 3.0 * step } else { 3.0 };
            for j in 0..40u64 {
                let track = (k / 10) * 1000 + j;
                let ahead = rotation * Vector3::new(0.05 * j as f64 - 1.0, 0.3, depth);
                parts.points.entry(track).or_insert((0, position + ahead));
                parts
                    .observations
                    .insert((k, track), nalgebra::Point2::new(0.0, 0.0));
            }
        }
        assert!(pivot > 0.0);
        parts.current_segment = Some(0);
        parts.segments = 1;
        MapBuilder::from_parts(parts)
    }

    /// The map's pace over `[from, to)` seconds, units per second.
    fn pace(map: &MapBuilder, from: f64, to: f64) -> f64 {
        let at = |t: f64| {
            map.keyframe((t * RATE).round() as u64)
                .expect("keyframe")
                .1
                .position
        };
        (at(to) - at(from)).norm() / (to - from)
    }

    #[test]
    fn a_step_of_the_scale_in_a_turn_takes_the_pace_before_it() {
        let mut map = walk(90.0, 0.8, |_| 1.0);
        assert!((pace(&map, 7.5, 9.5) / pace(&map, 2.0, 4.0) - 0.8).abs() < 1e-6);
        let mended = map
            .mend_turn_scale_step(&TurnScaleStepOptions::default(), |_| true)
            .expect("mended");
        assert!((mended.pace_ratio - 0.8).abs() < 0.01, "{mended:?}");
        let at = mended.after_keyframe as f64 / RATE;
        assert!((at - 6.0).abs() <= 0.1, "step found at {at} s");
        let ratio = pace(&map, 7.5, 9.5) / pace(&map, 2.0, 4.0);
        assert!((ratio - 1.0).abs() < 0.01, "pace after over before {ratio}");
        assert_eq!(map.mended_steps, vec![(0, mended.after_keyframe)]);
        // Nothing left to mend.
        assert!(map
            .mend_turn_scale_step(&TurnScaleStepOptions::default(), |_| true)
            .is_none());
    }

    #[test]
    fn a_step_in_a_glance_or_held_by_a_refinement_is_left_alone() {
        let options = TurnScaleStepOptions::default();
        // A glance of 30 deg: a wearer slowing down in it.
        let mut ahead = walk(30.0, 0.8, |_| 1.0);
        assert!(ahead.mend_turn_scale_step(&options, |_| true).is_none());
        assert!((pace(&ahead, 7.5, 9.5) / pace(&ahead, 2.0, 4.0) - 0.8).abs() < 1e-6);
        let mut held = walk(90.0, 0.8, |_| 1.0);
        assert!(held.mend_turn_scale_step(&options, |_| false).is_none());
        assert!(held.mended_steps.is_empty());
    }

    #[test]
    fn an_unsteady_pace_says_nothing_about_the_scale() {
        // A hand-held camera: steps alternately 1.5x and 0.5x the pace.
        let mut map = walk(90.0, 0.8, |k| if k % 2 == 0 { 1.5 } else { 0.5 });
        assert!(map
            .mend_turn_scale_step(&TurnScaleStepOptions::default(), |_| true)
            .is_none());
    }

    #[test]
    fn a_step_pulled_back_by_a_refinement_is_mended_again() {
        let options = TurnScaleStepOptions::default();
        let mut map = walk(90.0, 0.8, |_| 1.0);
        let mended = map
            .mend_turn_scale_step(&options, |_| true)
            .expect("mended");
        // A refinement settles with part of the step back.
        map.scale_stretch(0, mended.after_keyframe, 0.9)
            .expect("scaled");
        let again = map.mend_turn_scale_steps_again(&options);
        assert_eq!(again.len(), 1, "{again:?}");
        let ratio = pace(&map, 7.5, 9.5) / pace(&map, 2.0, 4.0);
        assert!((ratio - 1.0).abs() < 0.01, "pace after over before {ratio}");
        // Within the pace's wander: left as it is.
        map.scale_stretch(0, mended.after_keyframe, 1.03)
            .expect("scaled");
        assert!(map.mend_turn_scale_steps_again(&options).is_empty());
    }
}
