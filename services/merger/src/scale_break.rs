//! Where the chain of windows broke its scale, found from the walking pace.
//!
//! A loop whose scale correction is far beyond drift (say 0.65: the newest keyframes sit
//! in a map 1.55 times too large) is not gradual drift but a break: one window across a
//! sharp turn came out with the wrong scale and every window chained after it inherited
//! it (measured on rendered 1500-frame walks with a rolling shutter: the map's length per
//! true metre is flat for seconds, then steps by 0.86-1.56x at turns starting at
//! 4000-5000 deg/s^2). Spreading such a correction along the loop, as drift is, would
//! bend all of it, so such loops used to be refused.
//!
//! A step in scale is a step in the map's walking pace: a walker's speed in metres per
//! second changes gradually, so the map's speed in its own units per second, compared
//! over a few seconds before and after each keyframe, jumps by the break's factor exactly
//! where the break is. The loop then corrects that jump as a step there
//! ([`crate::loop_closure`]) instead of spreading it, and spreads only what is left; a
//! break spread over two windows shows as two jumps ([`locate_second_break`]).

use crate::median;
use egoslam_geometry::StampedPose;

/// How a scale break is located; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaleBreakOptions {
    /// Seconds of keyframes on each side of a candidate whose paces are compared (default
    /// 2: ~40 keyframes of walking, enough for a median to ignore the jitter of the turn
    /// itself, short enough that two breaks seconds apart are told apart).
    pub pace_window_s: f64,
    /// Keyframe steps slower than this fraction of the loop's median pace are left out
    /// (default 0.3: a stop's steps are the map's noise, and their ratio says nothing).
    pub min_pace_fraction: f64,
    /// Fewest moving steps on each side of a candidate (default 8).
    pub min_steps: usize,
    /// The pace must jump by the loop's factor within this factor either way, else nothing
    /// is located (default 1.5, `LoopOptions::max_scale_change`: the loop spreads what the
    /// jump leaves as drift, so the rest may be as large as drift a loop may correct).
    /// It was 1.25 while the step took the loop's whole factor; on a 1500-frame
    /// rolling-shutter walk (seed 7) a loop asking for 3.16 then found a 2.16x jump and
    /// was refused, leaving its map collapsed 3.8x.
    pub max_mismatch: f64,
    /// What a first break leaves beyond this factor either way is looked for as a second
    /// break, which must match it within this factor too (default 1.25). On the seed-7
    /// rolling-shutter walk the map collapsed over two windows: the first jump found was
    /// 2.16x of the loop's 3.16, and spreading the remaining 1.46 as drift inflated the
    /// map's middle by up to 1.46x.
    pub second_break_above: f64,
}

impl Default for ScaleBreakOptions {
    fn default() -> Self {
        Self {
            pace_window_s: 2.0,
            min_pace_fraction: 0.3,
            min_steps: 8,
            max_mismatch: 1.5,
            second_break_above: 1.25,
        }
    }
}

/// A located break.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaleBreak {
    /// The last keyframe with the old scale: those after it take the new one.
    pub after_keyframe: u64,
    /// The map's pace after the break over its pace before.
    pub pace_ratio: f64,
}

/// The keyframe after which `keyframes` (in order, one segment, map poses) change their
/// pace by the factor that `loop_scale` undoes (the pace after is `1 / loop_scale` times
/// the pace before); `None` when no keyframe shows that step within
/// `ScaleBreakOptions::max_mismatch`.
pub fn locate_scale_break(
    keyframes: &[(u64, StampedPose)],
    loop_scale: f64,
    options: &ScaleBreakOptions,
) -> Option<ScaleBreak> {
    let found = strongest_pace_jump(keyframes, loop_scale, options)?;
    let wanted = -loop_scale.ln();
    ((found.pace_ratio.ln() - wanted).abs() <= options.max_mismatch.ln()).then_some(found)
}

/// A second break for what `first` leaves of `loop_scale`, when that is beyond
/// `ScaleBreakOptions::second_break_above`: located as [`locate_scale_break`] does, in the
/// map with the first break undone, and within `second_break_above` of the remainder.
pub fn locate_second_break(
    keyframes: &[(u64, StampedPose)],
    loop_scale: f64,
    first: &ScaleBreak,
    options: &ScaleBreakOptions,
) -> Option<ScaleBreak> {
    let remainder = loop_scale * first.pace_ratio;
    if remainder.ln().abs() <= options.second_break_above.ln() {
        return None;
    }
    let pivot = keyframes
        .iter()
        .find(|(id, _)| *id == first.after_keyframe)?
        .1
        .position;
    let undone: Vec<(u64, StampedPose)> = keyframes
        .iter()
        .map(|(id, p)| {
            let mut p = *p;
            if *id > first.after_keyframe {
                p.position = pivot + (p.position - pivot) / first.pace_ratio;
            }
            (*id, p)
        })
        .collect();
    let strict = ScaleBreakOptions {
        max_mismatch: options.second_break_above,
        ..*options
    };
    locate_scale_break(&undone, remainder, &strict)
        .filter(|second| second.after_keyframe != first.after_keyframe)
}

/// A step between consecutive keyframes: start time, end time, pace (map units per
/// second).
pub(crate) type PaceStep = (f64, f64, f64);

/// The steps between consecutive `keyframes` (in time order, map poses) that take time.
pub(crate) fn pace_steps(keyframes: &[(u64, StampedPose)]) -> Vec<PaceStep> {
    keyframes
        .windows(2)
        .filter_map(|w| {
            let (a, b) = (&w[0].1, &w[1].1);
            let dt = b.timestamp - a.timestamp;
            (dt > 0.0).then(|| {
                (
                    a.timestamp,
                    b.timestamp,
                    (b.position - a.position).norm() / dt,
                )
            })
        })
        .collect()
}

/// The paces of the `steps` ending in the `window_s` before `t`, and of those within the
/// `window_s` after it.
pub(crate) fn paces_around(steps: &[PaceStep], t: f64, window_s: f64) -> (Vec<f64>, Vec<f64>) {
    let before = steps
        .iter()
        .filter(|s| s.1 <= t && s.1 > t - window_s)
        .map(|s| s.2)
        .collect();
    let after = steps
        .iter()
        .filter(|s| s.0 >= t && s.1 <= t + window_s)
        .map(|s| s.2)
        .collect();
    (before, after)
}

/// The keyframe with the strongest jump of the map's pace in the direction `loop_scale`
/// asks for, whatever its size (what [`locate_scale_break`] then holds to the loop's
/// factor; also what a refused loop logs).
pub fn strongest_pace_jump(
    keyframes: &[(u64, StampedPose)],
    loop_scale: f64,
    options: &ScaleBreakOptions,
) -> Option<ScaleBreak> {
    if !(loop_scale.is_finite() && loop_scale > 0.0) || keyframes.len() < 2 * options.min_steps {
        return None;
    }
    // Each step's pace (map units per second), stamped with its end time.
    let steps = pace_steps(keyframes);
    // The typical pace of the steps that moved: a map that keeps mostly the keyframes of
    // turns in place (a long walk's culling leaves those) has more steps of no length than
    // of walking, and a typical pace of zero would let those in, whose ratio is 0 / 0.
    let paces: Vec<f64> = steps.iter().map(|s| s.2).filter(|p| *p > 0.0).collect();
    let typical = median(paces)?;
    let moving: Vec<PaceStep> = steps
        .into_iter()
        .filter(|s| s.2 > 0.0 && s.2 >= options.min_pace_fraction * typical)
        .collect();
    let wanted = -loop_scale.ln();
    let mut best: Option<(f64, ScaleBreak)> = None;
    for (id, pose) in keyframes {
        let (before, after) = paces_around(&moving, pose.timestamp, options.pace_window_s);
        if before.len() < options.min_steps || after.len() < options.min_steps {
            continue;
        }
        let (Some(b), Some(a)) = (median(before), median(after)) else {
            continue;
        };
        let jump = (a / b).ln();
        if !jump.is_finite() {
            continue;
        }
        // The strongest jump in the direction the loop asks for.
        let strength = jump * wanted.signum();
        if best.as_ref().is_none_or(|(s, _)| strength > *s) {
            best = Some((
                strength,
                ScaleBreak {
                    after_keyframe: *id,
                    pace_ratio: a / b,
                },
            ));
        }
    }
    best.map(|(_, found)| found)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    /// A walk at 1.2 m/s with 20 keyframes per second, a stop of 2 s at 5-7 s, turning
    /// its direction by 90 deg every 4 s; the map's scale is 1 before `break_at` seconds
    /// and `after` from then on.
    fn walk(break_at: f64, after: f64) -> Vec<(u64, StampedPose)> {
        let mut position = Vector3::zeros();
        let mut out = Vec::new();
        for i in 0..400u64 {
            let t = i as f64 * 0.05;
            if i > 0 {
                let speed = if (5.0..7.0).contains(&t) { 0.0 } else { 1.2 };
                let heading = (t / 4.0).floor() * std::f64::consts::FRAC_PI_2;
                let scale = if t > break_at { after } else { 1.0 };
                // A little jitter, as a window leaves it.
                let wobble = 1.0 + 0.05 * (i as f64 * 1.7).sin();
                position +=
                    scale * wobble * speed * 0.05 * Vector3::new(heading.cos(), 0.0, heading.sin());
            }
            out.push((
                i,
                StampedPose {
                    timestamp: t,
                    position,
                    rotation: UnitQuaternion::identity(),
                },
            ));
        }
        out
    }

    #[test]
    fn a_break_over_two_windows_is_found_as_two_steps() {
        // The map shrank 2x at 11 s and 1.4x more at 14 s: the loop asks for 2.8.
        let mut keyframes = walk(11.0, 0.5);
        let second_at = keyframes
            .iter()
            .position(|(_, p)| p.timestamp > 14.0)
            .expect("keyframe");
        let pivot = keyframes[second_at - 1].1.position;
        for (_, p) in &mut keyframes[second_at..] {
            p.position = pivot + (p.position - pivot) / 1.4;
        }
        let options = ScaleBreakOptions::default();
        let first = locate_scale_break(&keyframes, 2.8, &options).expect("first");
        assert!((218..=222).contains(&first.after_keyframe), "{first:?}");
        let second = locate_second_break(&keyframes, 2.8, &first, &options).expect("second");
        assert!((278..=282).contains(&second.after_keyframe), "{second:?}");
        assert!((second.pace_ratio - 1.0 / 1.4).abs() < 0.05, "{second:?}");
        // One break of the loop's whole factor leaves nothing to look for.
        let single = walk(11.0, 1.0 / 3.0);
        let first = locate_scale_break(&single, 3.0, &options).expect("first");
        assert!(locate_second_break(&single, 3.0, &first, &options).is_none());
    }

    #[test]
    fn a_step_in_scale_is_found_where_the_pace_jumps() {
        // The map after the break is 1.55 times too large: the loop asks for 1 / 1.55.
        let keyframes = walk(11.0, 1.55);
        let found = locate_scale_break(&keyframes, 1.0 / 1.55, &ScaleBreakOptions::default())
            .expect("located");
        // Keyframe 220 is at 11.0 s; the median needs a step or two of the new pace.
        assert!(
            (218..=222).contains(&found.after_keyframe),
            "{}",
            found.after_keyframe
        );
        assert!(
            (found.pace_ratio - 1.55).abs() < 0.05,
            "{}",
            found.pace_ratio
        );
        // The other way round (the map shrank).
        let shrunk = walk(14.0, 0.6);
        let found =
            locate_scale_break(&shrunk, 1.0 / 0.6, &ScaleBreakOptions::default()).expect("located");
        assert!((278..=282).contains(&found.after_keyframe));
    }

    #[test]
    fn a_step_is_found_where_most_keyframes_are_turns_in_place() {
        // The walk with three keyframes on the spot (a turn in place) after each step, as
        // a long walk's map keeps them after culling: three quarters of the steps have no
        // length, so their median pace is zero.
        let mut keyframes = Vec::new();
        for (i, (_, p)) in walk(11.0, 1.55).into_iter().enumerate() {
            for k in 0..4u64 {
                let mut turn = p;
                turn.timestamp = p.timestamp + 0.01 * k as f64;
                keyframes.push((4 * i as u64 + k, turn));
            }
        }
        let found = locate_scale_break(&keyframes, 1.0 / 1.55, &ScaleBreakOptions::default())
            .expect("located");
        assert!(
            (4 * 218..=4 * 222 + 3).contains(&found.after_keyframe),
            "{found:?}"
        );
        assert!((found.pace_ratio - 1.55).abs() < 0.1, "{found:?}");
    }

    #[test]
    fn no_break_is_claimed_where_the_pace_does_not_jump_by_the_loop_s_factor() {
        // Steady scale: a loop asking for 0.6 is not explained by any step.
        let steady = walk(100.0, 1.0);
        assert_eq!(
            locate_scale_break(&steady, 0.6, &ScaleBreakOptions::default()),
            None
        );
        // A break of 1.2 does not explain a loop asking for 1 / 2.
        let small = walk(11.0, 1.2);
        assert_eq!(
            locate_scale_break(&small, 0.5, &ScaleBreakOptions::default()),
            None
        );
        // Too few keyframes, or a nonsense scale.
        assert_eq!(
            locate_scale_break(&steady[..10], 0.6, &ScaleBreakOptions::default()),
            None
        );
        assert_eq!(
            locate_scale_break(&steady, f64::NAN, &ScaleBreakOptions::default()),
            None
        );
    }
}
