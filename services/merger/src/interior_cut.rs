//! A window whose keyframes fall into two groups that almost no point links: its solve
//! has no measure of the second group's scale relative to the first, and the merger must
//! not take the one the solver happened to return.
//!
//! Inside a window the scale passes from keyframe to keyframe through points seen on both
//! sides, each triangulated by at least two views on each side. On the rendered
//! 12,000-frame walk, window 199 (keyframes 2981-3000) held a quick turn after a frame gap:
//! across the cut between keyframes 2989 and 2990 three points were seen twice on either
//! side (400-600 across every other cut), and the window's solve gave the keyframes after
//! it steps 2.6x longer in window units than those before (metres per unit 5.7 before, 15
//! after). The next windows chained onto that scale through hundreds of shared points, so
//! the whole rest of the walk carried it.
//!
//! Such a cut is what a weak join between windows is ([`crate::speed_continuity`]), only
//! inside one solve: the part after it gets the scale that gives it the walking pace of the
//! part before, both measured in the window's own frame, and the points triangulated
//! across it (positions mixing the two scales) are left out.
//!
//! A solve can also break where many points cross (a degenerate stretch of a
//! rolling-shutter walk: keyframes after one cut ~3,000x too far apart). So a cut across
//! which the window's pace changes more than tenfold is rescaled the same way, however many
//! points cross it.

use crate::map::WindowInput;
use crate::scene_depth::window_scene_depth;
use crate::speed_continuity::{well_seen_pace, SpeedContinuityOptions};
use std::collections::HashMap;

/// When a cut is weak and how the pace is measured across it; defaults commented.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InteriorCutOptions {
    /// A cut is weak below this many points seen by at least two keyframes on each side
    /// (default 20). On the 12,000-frame walk the weak cut had 3 and its neighbours 5-25;
    /// cuts elsewhere have 100-600, and the shared-points join of two windows asks for 30
    /// ([`crate::window_alignment`]), of which a cut inside a solve needs fewer as the views
    /// on both sides were fitted together.
    pub min_transfer_points: usize,
    /// Shortest time of moving steps on each side, seconds (default 0.25). Both sides are
    /// parts of one window, a second of walking at most when keyframes are dense (head
    /// scans); the join between windows asks for 0.5 s.
    pub min_span_s: f64,
    /// The part after the cut is rescaled only when the paces disagree by more than this
    /// factor (default 1.25). Over a quarter to half a second the pace varies with the
    /// stride (bob, step phase) by 10-20 %; a smaller disagreement says the solve's scale,
    /// which rests on a few points, is as good as the pace. On the rendered head shake
    /// the pace gave 0.99 at a cut crossed by 7 points, and rescaling (dropping those
    /// points) moved the keyframe ATE from 0.17 to 0.20 m; the 12,000-frame walk's cut
    /// asked for 2.7.
    pub min_correction: f64,
    /// A cut crossed by many points is still taken for a broken solve when the window's
    /// pace jumps across it by more than this factor (default 10: a walking wearer's pace
    /// changes by 10-20 % within a second and a car's by < 3x, while on the 1500-frame
    /// seed-2 walk rendered with a 20 ms readout one window's keyframes moved 2,468x faster
    /// after a cut crossed by 20+ points, and the rest of the map carried it until a loop).
    pub max_pace_jump: f64,
}

impl Default for InteriorCutOptions {
    fn default() -> Self {
        Self {
            min_transfer_points: 20,
            min_span_s: 0.25,
            min_correction: 1.25,
            max_pace_jump: 10.0,
        }
    }
}

/// The weakest cut of a window: after keyframe index `after`, with `transfer_points`
/// points seen twice or more on each side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cut {
    pub after: usize,
    pub transfer_points: usize,
}

/// The weakest cut after keyframe index `first_new` (cuts before the first new keyframe are
/// the join with the map, judged when chaining) with two keyframes or more on each side, or
/// `None` when the window has no such cut.
pub fn weakest_cut(window: &WindowInput, first_new: usize) -> Option<Cut> {
    weakest_cut_of(&track_views(window), window.poses.len(), first_new)
}

/// Indices (in `window.poses`) of the keyframes that observe each track.
fn track_views(window: &WindowInput) -> HashMap<u64, Vec<usize>> {
    let index: HashMap<u64, usize> = window
        .poses
        .iter()
        .enumerate()
        .map(|(i, (id, _))| (*id, i))
        .collect();
    let mut views: HashMap<u64, Vec<usize>> = HashMap::new();
    for (kf, track, _) in &window.observations {
        if let Some(i) = index.get(kf) {
            views.entry(*track).or_default().push(*i);
        }
    }
    views
}

/// [`weakest_cut`] over the track views of a window of `keyframes` keyframes.
fn weakest_cut_of(
    views: &HashMap<u64, Vec<usize>>,
    keyframes: usize,
    first_new: usize,
) -> Option<Cut> {
    // Two keyframes on each side at least: a side of one has nothing seen twice.
    let last = keyframes.checked_sub(3)?;
    (first_new.max(1)..=last)
        .map(|after| Cut {
            after,
            transfer_points: transfer_points(views, after),
        })
        // The weakest; of equals the earliest.
        .min_by_key(|c| (c.transfer_points, c.after))
}

/// Points seen twice or more on each side of the cut after keyframe index `after`.
fn transfer_points(views: &HashMap<u64, Vec<usize>>, after: usize) -> usize {
    views
        .values()
        .filter(|v| {
            let before = v.iter().filter(|&&i| i <= after).count();
            before >= 2 && v.len() - before >= 2
        })
        .count()
}

/// `window` with the keyframes after `cut` scaled about the last keyframe before it so
/// that they walk at the pace of those before, and without the points triangulated across
/// it. `None` when the cut is not weak, either side has no pace, or the paces agree within
/// [`InteriorCutOptions::min_correction`]; then a cut crossed by more points is rescaled
/// the same way when the pace jumps across it by more than
/// [`InteriorCutOptions::max_pace_jump`] ([`strongest_pace_jump`]).
pub fn rescale_after_weak_cut(
    window: &WindowInput,
    first_new: usize,
    options: &InteriorCutOptions,
) -> Option<(WindowInput, Cut, f64)> {
    let views = track_views(window);
    let pace_options = SpeedContinuityOptions {
        min_span_s: options.min_span_s,
        ..SpeedContinuityOptions::default()
    };
    let floor = pace_options.min_speed_depths_per_s * window_scene_depth(window)?;
    let seen = window.observation_counts();
    let weak = weakest_cut_of(&views, window.poses.len(), first_new)
        .filter(|cut| cut.transfer_points < options.min_transfer_points)
        .and_then(|cut| {
            let scale = pace_ratio(window, &seen, cut.after, floor, &pace_options)?;
            Some((cut, scale))
        })
        .filter(|(_, scale)| scale.max(1.0 / scale) > options.min_correction);
    let (cut, scale) = match weak {
        Some(weak) => weak,
        None => strongest_pace_jump(window, (&views, &seen), first_new, floor, &pace_options)
            .filter(|(_, scale)| scale.max(1.0 / scale) > options.max_pace_jump)?,
    };
    Some((rescaled_after(window, &views, cut.after, scale), cut, scale))
}

/// The window's pace before the cut after index `after` over its pace after it: the
/// scale that gives the part after the pace before. `None` when a side has no pace.
/// `seen`: the window's observations per keyframe, counted once for all its cuts.
fn pace_ratio(
    window: &WindowInput,
    seen: &HashMap<u64, usize>,
    after: usize,
    floor: f64,
    options: &SpeedContinuityOptions,
) -> Option<f64> {
    let (before, rest) = window.poses.split_at(after + 1);
    let scale =
        well_seen_pace(before, seen, floor, options)? / well_seen_pace(rest, seen, floor, options)?;
    (scale.is_finite() && scale > 0.0).then_some(scale)
}

/// The cut after `first_new` (two keyframes or more on each side) across which the pace
/// changes the most, with [`pace_ratio`] there. Each side's pace is a median over its
/// steps, so the cuts next to a jump show nearly the same change: of those within 1 % of
/// the largest, the one fewest points cross (the earliest of equals).
fn strongest_pace_jump(
    window: &WindowInput,
    (views, seen): (&HashMap<u64, Vec<usize>>, &HashMap<u64, usize>),
    first_new: usize,
    floor: f64,
    options: &SpeedContinuityOptions,
) -> Option<(Cut, f64)> {
    let last = window.poses.len().checked_sub(3)?;
    let ratios: Vec<(usize, f64)> = (first_new.max(1)..=last)
        .filter_map(|after| Some((after, pace_ratio(window, seen, after, floor, options)?)))
        .collect();
    let strongest = ratios
        .iter()
        .map(|(_, r)| r.ln().abs())
        .max_by(f64::total_cmp)?;
    ratios
        .into_iter()
        .filter(|(_, r)| r.ln().abs() >= 0.99 * strongest)
        .map(|(after, scale)| {
            let cut = Cut {
                after,
                transfer_points: transfer_points(views, after),
            };
            (cut, scale)
        })
        .min_by_key(|(cut, _)| (cut.transfer_points, cut.after))
}

/// `window` with the keyframes after index `after` scaled by `scale` about the keyframe at
/// `after`, and without the points seen on both sides (their positions mix two scales).
fn rescaled_after(
    window: &WindowInput,
    views: &HashMap<u64, Vec<usize>>,
    after: usize,
    scale: f64,
) -> WindowInput {
    let pivot = window.poses[after].1.position;
    // (seen before the cut, seen after it) per track.
    let sides = |track: &u64| {
        views.get(track).map_or((false, false), |v| {
            (v.iter().any(|&i| i <= after), v.iter().any(|&i| i > after))
        })
    };
    let across = |track: &u64| sides(track) == (true, true);
    let mut rescaled = window.clone();
    for (i, (_, pose)) in rescaled.poses.iter_mut().enumerate() {
        if i > after {
            pose.position = pivot + (pose.position - pivot) * scale;
        }
    }
    rescaled.points.retain(|(track, _)| !across(track));
    for (track, x) in &mut rescaled.points {
        if sides(track).1 {
            *x = pivot + (*x - pivot) * scale;
        }
    }
    rescaled.observations.retain(|(_, track, _)| !across(track));
    rescaled
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_geometry::StampedPose;
    use nalgebra::{Point2, UnitQuaternion, Vector3};

    /// 20 keyframes at 20 per second walking along x at 1 unit/s; the solve gave those
    /// from index 10 on `jump` times longer steps. Points: 60 seen by keyframes 0-9, 60 by
    /// 10-19, 60 by 7-10 and 60 by 9-12 (each crosses the cut between 9 and 10 with one
    /// view on one side), and `across` seen by 8-11.
    fn window(jump: f64, across: u64) -> WindowInput {
        let mut x = 0.0;
        let poses: Vec<(u64, StampedPose)> = (0..20u64)
            .map(|i| {
                if i > 0 {
                    x += if i >= 10 { 0.05 * jump } else { 0.05 };
                }
                let pose = StampedPose {
                    timestamp: i as f64 * 0.05,
                    position: Vector3::new(x, 0.0, 0.0),
                    rotation: UnitQuaternion::identity(),
                };
                (100 + i, pose)
            })
            .collect();
        let mut points = Vec::new();
        let mut observations = Vec::new();
        let mut add = |track: u64, kfs: std::ops::Range<u64>, at: Vector3<f64>| {
            points.push((track, at));
            for k in kfs {
                observations.push((100 + k, track, Point2::new(0.0, 0.0)));
            }
        };
        for t in 0..60 {
            add(t, 0..10, Vector3::new(0.01 * t as f64, 1.0, 3.0));
            add(
                1000 + t,
                10..20,
                Vector3::new(0.5 + jump * 0.01 * t as f64, 1.0, 3.0),
            );
        }
        for t in 0..60 {
            add(3000 + t, 7..11, Vector3::new(0.4, 0.0, 3.0));
            add(4000 + t, 9..13, Vector3::new(0.6, 0.0, 3.0));
        }
        for t in 0..across {
            add(2000 + t, 8..12, Vector3::new(0.5, 0.0, 3.0));
        }
        WindowInput {
            poses,
            points,
            observations,
            weak_observations: Vec::new(),
        }
    }

    /// `rescaled` (from `window`, cut after index 9) walks at the pace before the cut
    /// (0.05 per keyframe) after it too, the part before unmoved and the points seen on
    /// both sides dropped.
    fn assert_walks_at_the_pace_before(window: &WindowInput, rescaled: &WindowInput) {
        let step = (rescaled.poses[15].1.position - rescaled.poses[14].1.position).norm();
        assert!((step - 0.05).abs() < 1e-9, "{step}");
        assert_eq!(rescaled.poses[9], window.poses[9], "the part before stays");
        assert!(
            rescaled.points.iter().all(|(t, _)| *t < 2000),
            "points across dropped"
        );
    }

    #[test]
    fn the_part_after_a_weak_cut_walks_at_the_pace_of_the_part_before() {
        let w = window(2.6, 3);
        assert_eq!(
            weakest_cut(&w, 5),
            Some(Cut {
                after: 9,
                transfer_points: 3
            })
        );
        let (rescaled, cut, scale) =
            rescale_after_weak_cut(&w, 5, &InteriorCutOptions::default()).expect("weak");
        assert_eq!(cut.after, 9);
        assert!((scale - 1.0 / 2.6).abs() < 1e-9, "{scale}");
        assert_walks_at_the_pace_before(&w, &rescaled);
        assert_eq!(rescaled.points.len(), 120);
        assert!(rescaled.observations.iter().all(|(_, t, _)| *t < 2000));
    }

    #[test]
    fn a_cut_many_points_cross_or_paces_that_agree_are_left_alone() {
        let w = window(2.6, 40);
        assert_eq!(weakest_cut(&w, 5).map(|c| c.transfer_points), Some(40));
        assert!(rescale_after_weak_cut(&w, 5, &InteriorCutOptions::default()).is_none());
        let w = window(1.1, 3);
        assert!(rescale_after_weak_cut(&w, 5, &InteriorCutOptions::default()).is_none());
    }

    #[test]
    fn a_cut_many_points_cross_is_still_rescaled_when_the_pace_jumps_tenfold() {
        // 40 points cross the cut: not weak. A 2.6x jump stays (above); 30x does not.
        let w = window(30.0, 40);
        let (rescaled, cut, scale) =
            rescale_after_weak_cut(&w, 5, &InteriorCutOptions::default()).expect("jump");
        assert_eq!((cut.after, cut.transfer_points), (9, 40));
        assert!((scale - 1.0 / 30.0).abs() < 1e-9, "{scale}");
        assert_walks_at_the_pace_before(&w, &rescaled);
        // A threshold above the jump leaves it.
        let lenient = InteriorCutOptions {
            max_pace_jump: 40.0,
            ..Default::default()
        };
        assert!(rescale_after_weak_cut(&w, 5, &lenient).is_none());
    }
}
