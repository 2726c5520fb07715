//! Keyframes that bundle adjustment turned away together with points only they see.
//!
//! In a fast head shake a window can end in a few keyframes that share many tracks with one
//! another but almost none with the rest of the window: their mutual edges have no parallax
//! (a turn), so their points are triangulated from their own near-coincident centres and
//! seen by nobody else. Bundle adjustment can then turn the group and its points as one
//! rigid body at almost no cost: nothing outside the group pins its orientation. On a
//! rendered 300 deg/s shake three such keyframes, each with 200+ inlier observations (so
//! not unobserved in the sense of `unobserved_keyframes.rs`), ended 14 deg away from the
//! averaged rotations, which were within 0.3 deg of the truth; the merger then placed the
//! next window from them, and the map kept the turn.
//!
//! The group is found by comparing the adjusted rotations with the averaged ones. A world
//! gauge change acts on every keyframe alike, so each keyframe's difference is measured
//! against the one most keyframes share; the keyframes departing from it by more than
//! `max_departure_deg` form the group. It is restored only when few points tie it to the
//! rest of the window (points with inlier observations both in and outside the group):
//! a keyframe whose averaged rotation was wrong (an edge the averaging trusted too much)
//! and that bundle adjustment corrected through hundreds of shared points keeps the
//! adjusted rotation. A restored keyframe takes its averaged rotation in the majority's
//! gauge; its observations are dropped from the solution (the points it saw were placed
//! for the turned pose), and its centre is placed from the motion around it, as an
//! unobserved keyframe's is.

use crate::bundle_adjustment::Observation;
use crate::triangulation::CameraPose;
use nalgebra::Rotation3;
use std::collections::HashSet;

/// When a group of keyframes counts as turned away; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetachedKeyframeOptions {
    /// A keyframe departs when its adjusted rotation differs from its averaged one by more
    /// than this beyond the majority's gauge, degrees (default 5: the rotation averaging's
    /// robust scale, `WindowSolverOptions::max_edge_rotation_residual_deg`; adjustment moves
    /// well-tied keyframes of the rendered walks and KITTI by well under 1 deg).
    pub max_departure_deg: f64,
    /// Points seen both in the departing group and outside it at or above which the group
    /// is taken to be held by the window, and its adjusted rotations kept (default 20,
    /// `UnobservedKeyframeOptions::min_observations`: 20 points spread over the image pin a
    /// rotation well within a degree).
    pub min_tie_points: usize,
}

impl Default for DetachedKeyframeOptions {
    fn default() -> Self {
        Self {
            max_departure_deg: 5.0,
            min_tie_points: 20,
        }
    }
}

/// Angle of a rotation, radians; `Rotation3::angle` gives NaN when rounding takes the
/// trace of a near-identity past 3.
fn angle(r: &Rotation3<f64>) -> f64 {
    ((r.matrix().trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}

/// Finds the keyframes bundle adjustment turned away with points only they see (module
/// doc), gives them their `averaged` rotations in the gauge most keyframes share, and
/// returns them in order (empty when none is found, when no gauge is shared by at least
/// half of the keyframes, or when the lengths disagree). `observations` are the adjusted
/// problem's, `outlier[o]` true for the ones adjustment rejected.
pub fn restore_detached_keyframes(
    poses: &mut [CameraPose],
    averaged: &[Rotation3<f64>],
    observations: &[Observation],
    outlier: &[bool],
    options: &DetachedKeyframeOptions,
) -> Vec<usize> {
    let n = poses.len();
    if n < 3 || averaged.len() != n || outlier.len() != observations.len() {
        return Vec::new();
    }
    // Camera-from-world rotations: a change of the world's gauge acts on the right,
    // adjusted = averaged * gauge.
    let gauges: Vec<Rotation3<f64>> = (0..n)
        .map(|k| averaged[k].inverse() * poses[k].rotation)
        .collect();
    let limit = options.max_departure_deg.to_radians();
    // The gauge most keyframes agree with (within half the limit), earliest on ties.
    let agreeing = |g: &Rotation3<f64>| {
        gauges
            .iter()
            .filter(|h| angle(&(g.inverse() * *h)) < 0.5 * limit)
            .count()
    };
    let Some((support, std::cmp::Reverse(first))) = (0..n)
        .map(|k| (agreeing(&gauges[k]), std::cmp::Reverse(k)))
        .max()
    else {
        return Vec::new();
    };
    if 2 * support < n {
        return Vec::new();
    }
    let shared = gauges[first];
    let group: Vec<usize> = (0..n)
        .filter(|&k| angle(&(shared.inverse() * gauges[k])) > limit)
        .collect();
    if group.is_empty() {
        return group;
    }
    let in_group = |k: usize| group.binary_search(&k).is_ok();
    let mut seen_inside = HashSet::new();
    let mut seen_outside = HashSet::new();
    for (o, _) in observations.iter().zip(outlier).filter(|(_, out)| !**out) {
        if in_group(o.camera) {
            seen_inside.insert(o.point);
        } else {
            seen_outside.insert(o.point);
        }
    }
    let ties = seen_inside.intersection(&seen_outside).count();
    if ties >= options.min_tie_points {
        return Vec::new();
    }
    for &k in &group {
        poses[k].rotation = averaged[k] * shared;
    }
    group
}

#[cfg(test)]
mod tests;
