//! Poses of the keyframes a window's points barely see, taken from their well-seen
//! neighbours and the rotation averaging instead of left where bundle adjustment put them.
//!
//! In a fast head turn (~250 deg/s while walking on the rendered walks) or at the start of
//! a stop, consecutive keyframes share few tracks and almost none triangulates: such a
//! keyframe ends bundle adjustment with 0-10 inlier observations. Its centre was set by a
//! few two-view translation directions that carry no parallax, and bundle adjustment had
//! nothing to correct it with. Decoded from the journal of the 12,000-frame walk, such
//! centres sat up to 2 m off the path (0.2 map units at 10 m per unit) and moved by 4x the
//! walking step. They matter beyond their own pose: these are the keyframes a window
//! shares with the next one when the window ends in the turn, and the merger places the
//! next window from them.
//!
//! A centre no point constrains is replaced by the motion around it: interpolated in time
//! between the nearest well-observed keyframes on either side, or, at the window's ends,
//! continued at the velocity of the nearest well-observed keyframes (the constant-velocity
//! motion model of visual odometry; for the walking wearer the pace holds through a turn).
//!
//! Its rotation needs no parallax and the rotation averaging had it from the keyframe's
//! relative rotations, but bundle adjustment can turn it anywhere: the few observations it
//! kept pull on it while the rest are outliers (a rendered head shake at 300 deg/s with
//! 40 px of blur: a keyframe with 6 inlier observations turned 81 deg from its averaged
//! rotation). It is taken from the averaging, relative to the nearest well-observed
//! keyframe in time (bundle adjustment may have moved the gauge).

use crate::triangulation::CameraPose;
use nalgebra::{Rotation3, Vector3};

/// When a keyframe counts as unobserved, and when its adjusted rotation is replaced;
/// defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UnobservedKeyframeOptions {
    /// A keyframe with fewer inlier observations after bundle adjustment has its centre
    /// replaced (default 20: the turn keyframes of the rendered walks had 0-10; a keyframe
    /// that sees 20 points spread over the image is placed to well within its step).
    pub min_observations: usize,
    /// Well-observed keyframes whose centres give the velocity at a window's end (default
    /// 5: a sixth of a second at 30 keyframes per second, less than one stride).
    pub velocity_keyframes: usize,
    /// Such a keyframe's adjusted rotation is replaced by its averaged one only when they
    /// differ by more than this, degrees (default 5, the rotation averaging's robust
    /// scale, `WindowSolverOptions::max_edge_rotation_residual_deg`): a dozen observations
    /// still refine a rotation, while one turned tens of degrees away was pulled off by them).
    pub max_rotation_departure_deg: f64,
}

impl Default for UnobservedKeyframeOptions {
    fn default() -> Self {
        Self {
            min_observations: 20,
            velocity_keyframes: 5,
            max_rotation_departure_deg: 5.0,
        }
    }
}

/// Velocity (centre units per second) over the well-observed keyframes `strong` (indices in
/// time order), `None` when they span no time.
fn velocity(poses: &[CameraPose], timestamps: &[f64], strong: &[usize]) -> Option<Vector3<f64>> {
    let (&a, &b) = (strong.first()?, strong.last()?);
    let dt = timestamps[b] - timestamps[a];
    (dt > 0.0).then(|| (poses[b].centre - poses[a].centre) / dt)
}

/// Indices of the keyframes (of `n`) with at least `options.min_observations` inlier
/// observations, in order.
fn well_observed(
    n: usize,
    observations: &[usize],
    options: &UnobservedKeyframeOptions,
) -> Vec<usize> {
    (0..n)
        .filter(|&k| observations.get(k).copied().unwrap_or(0) >= options.min_observations)
        .collect()
}

/// Replaces the rotations of the keyframes with fewer than `options.min_observations`
/// observations by their `averaged` rotations relative to the nearest well-observed keyframe
/// in time, where the two differ by more than `options.max_rotation_departure_deg` (module
/// doc); returns how many were replaced (none with no well-observed keyframe, or when the
/// lengths disagree).
pub fn restore_unobserved_rotations(
    poses: &mut [CameraPose],
    timestamps: &[f64],
    observations: &[usize],
    averaged: &[Rotation3<f64>],
    options: &UnobservedKeyframeOptions,
) -> usize {
    let strong = well_observed(poses.len(), observations, options);
    if strong.is_empty() || timestamps.len() != poses.len() || averaged.len() != poses.len() {
        return 0;
    }
    let mut replaced = 0;
    for k in 0..poses.len() {
        if strong.binary_search(&k).is_ok() {
            continue;
        }
        let Some(&nearest) = strong.iter().min_by(|a, b| {
            (timestamps[**a] - timestamps[k])
                .abs()
                .total_cmp(&(timestamps[**b] - timestamps[k]).abs())
        }) else {
            continue;
        };
        // Camera-from-world rotations: a change of the world's gauge acts on the right.
        let restored = averaged[k] * averaged[nearest].inverse() * poses[nearest].rotation;
        let departure = (restored.inverse() * poses[k].rotation).angle();
        if departure > options.max_rotation_departure_deg.to_radians() {
            poses[k].rotation = restored;
            replaced += 1;
        }
    }
    replaced
}

/// Replaces the centres of the keyframes with fewer than `options.min_observations`
/// observations (`observations[k]` for keyframe `k`, taken at `timestamps[k]`, in time
/// order) from their well-observed neighbours; rotations are kept. Returns how many were
/// replaced; none when fewer than two keyframes are well observed (nothing to take the
/// motion from).
pub fn place_unobserved_centres(
    poses: &mut [CameraPose],
    timestamps: &[f64],
    observations: &[usize],
    options: &UnobservedKeyframeOptions,
) -> usize {
    let strong = well_observed(poses.len(), observations, options);
    if strong.len() < 2 || timestamps.len() != poses.len() {
        return 0;
    }
    let span = options.velocity_keyframes.max(2);
    let head_velocity = velocity(poses, timestamps, &strong[..span.min(strong.len())]);
    let tail_velocity = velocity(
        poses,
        timestamps,
        &strong[strong.len().saturating_sub(span)..],
    );
    let mut replaced = 0;
    for k in 0..poses.len() {
        if strong.binary_search(&k).is_ok() {
            continue;
        }
        let after = strong.partition_point(|&s| s < k);
        let centre = match (after.checked_sub(1).map(|i| strong[i]), strong.get(after)) {
            (Some(p), Some(&q)) => {
                let dt = timestamps[q] - timestamps[p];
                let f = if dt > 0.0 {
                    (timestamps[k] - timestamps[p]) / dt
                } else {
                    0.5
                };
                poses[p].centre + (poses[q].centre - poses[p].centre) * f
            }
            (Some(p), None) => match tail_velocity {
                Some(v) => poses[p].centre + v * (timestamps[k] - timestamps[p]),
                None => poses[p].centre,
            },
            (None, Some(&q)) => match head_velocity {
                Some(v) => poses[q].centre - v * (timestamps[q] - timestamps[k]),
                None => poses[q].centre,
            },
            (None, None) => continue,
        };
        if centre.iter().all(|c| c.is_finite()) {
            poses[k].centre = centre;
            replaced += 1;
        }
    }
    replaced
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    fn at(x: f64) -> CameraPose {
        CameraPose {
            rotation: Rotation3::from_euler_angles(0.0, x, 0.0),
            centre: Vector3::new(x, 0.0, 0.0),
        }
    }

    /// A weakly seen keyframe turned by bundle adjustment gets its averaged rotation back,
    /// in the adjusted gauge (here a world turned 0.5 rad about y from the averaging's).
    #[test]
    fn unseen_keyframes_keep_their_averaged_rotation() {
        let timestamps: Vec<f64> = (0..5).map(|k| k as f64 * 0.1).collect();
        let averaged: Vec<Rotation3<f64>> = (0..5)
            .map(|k| Rotation3::from_euler_angles(0.1 * k as f64, 0.2 * k as f64, 0.0))
            .collect();
        let gauge = Rotation3::from_euler_angles(0.0, 0.5, 0.0);
        let mut poses: Vec<CameraPose> = averaged
            .iter()
            .map(|r| CameraPose {
                rotation: r * gauge,
                centre: Vector3::zeros(),
            })
            .collect();
        let truth = poses.clone();
        poses[3].rotation = Rotation3::from_euler_angles(1.4, 0.0, 0.3);
        let observations = [50, 60, 40, 6, 80];
        let n = restore_unobserved_rotations(
            &mut poses,
            &timestamps,
            &observations,
            &averaged,
            &UnobservedKeyframeOptions::default(),
        );
        assert_eq!(n, 1);
        for (p, t) in poses.iter().zip(&truth) {
            let e = (p.rotation.matrix() - t.rotation.matrix()).norm();
            assert!(e < 1e-12, "{e}");
        }
    }

    #[test]
    fn unseen_keyframes_follow_the_motion_around_them() {
        // Walking at 1 unit/s, a keyframe every 0.1 s; keyframes 0, 4, 5 and 9 see nothing
        // and were put far off.
        let timestamps: Vec<f64> = (0..10).map(|k| k as f64 * 0.1).collect();
        let mut poses: Vec<CameraPose> = timestamps.iter().map(|t| at(*t)).collect();
        let observations = [3, 50, 60, 40, 0, 5, 80, 90, 70, 2];
        for k in [0, 4, 5, 9] {
            poses[k].centre = Vector3::new(7.0, -3.0, 2.0);
        }
        let rotations: Vec<_> = poses.iter().map(|p| p.rotation).collect();
        let n = place_unobserved_centres(
            &mut poses,
            &timestamps,
            &observations,
            &UnobservedKeyframeOptions::default(),
        );
        assert_eq!(n, 4);
        for (k, p) in poses.iter().enumerate() {
            let truth = Vector3::new(k as f64 * 0.1, 0.0, 0.0);
            assert!(
                (p.centre - truth).norm() < 1e-9,
                "keyframe {k}: {}",
                p.centre
            );
            assert_eq!(p.rotation, rotations[k], "rotations are kept");
        }
    }

    #[test]
    fn with_fewer_than_two_seen_keyframes_nothing_moves() {
        let timestamps = [0.0, 0.1, 0.2];
        let mut poses = vec![at(0.0), at(5.0), at(9.0)];
        let before = poses.clone();
        let n = place_unobserved_centres(
            &mut poses,
            &timestamps,
            &[0, 100, 0],
            &UnobservedKeyframeOptions::default(),
        );
        assert_eq!(n, 0);
        assert_eq!(poses, before);
    }
}
