//! Timestamped trajectories and their accuracy against ground truth (ATE).
//!
//! The absolute trajectory error follows Sturm et al., "A Benchmark for the Evaluation of
//! RGB-D SLAM Systems", IROS 2012: associate estimate and ground truth by timestamp (nearest
//! neighbour within a window, 0.02 s in TUM's `associate.py`), align with a similarity
//! (Umeyama, because monocular scale is free) and report the RMSE of position residuals.

use crate::alignment::{umeyama, AlignmentError, Similarity};
use nalgebra::{UnitQuaternion, Vector3};

/// A camera pose (world_from_camera) at a time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampedPose {
    pub timestamp: f64,
    pub position: Vector3<f64>,
    pub rotation: UnitQuaternion<f64>,
}

impl StampedPose {
    /// Whether `other` has this pose's centre, up to rounding: a window solved without
    /// parallax (a head turning in place) puts all its keyframes at one centre, and such
    /// keyframes measure rotation only.
    pub fn shares_centre_with(&self, other: &StampedPose) -> bool {
        (other.position - self.position).norm() <= 1e-9 * self.position.norm().max(1.0)
    }
}

/// Pairs `(estimate index, ground-truth index)` whose timestamps differ by at most
/// `max_dt`, each index used once, closest pairs first (as TUM `associate.py`).
pub fn associate(est: &[StampedPose], gt: &[StampedPose], max_dt: f64) -> Vec<(usize, usize)> {
    let mut gt_order: Vec<usize> = (0..gt.len()).collect();
    gt_order.sort_by(|&a, &b| gt[a].timestamp.total_cmp(&gt[b].timestamp));
    let mut candidates = Vec::new();
    for (i, e) in est.iter().enumerate() {
        // Binary search the first ground-truth stamp >= e - max_dt, then scan the window.
        let start = gt_order.partition_point(|&g| gt[g].timestamp < e.timestamp - max_dt);
        for &g in gt_order[start..]
            .iter()
            .take_while(|&&g| gt[g].timestamp <= e.timestamp + max_dt)
        {
            candidates.push(((gt[g].timestamp - e.timestamp).abs(), i, g));
        }
    }
    candidates.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut used_e, mut used_g) = (vec![false; est.len()], vec![false; gt.len()]);
    let mut pairs = Vec::new();
    for (_, i, g) in candidates {
        if !used_e[i] && !used_g[g] {
            used_e[i] = true;
            used_g[g] = true;
            pairs.push((i, g));
        }
    }
    pairs.sort_unstable();
    pairs
}

/// Absolute trajectory error after similarity alignment.
#[derive(Debug, Clone, PartialEq)]
pub struct AteReport {
    /// Matched pose pairs used.
    pub matched: usize,
    pub rmse: f64,
    pub mean: f64,
    pub median: f64,
    pub max: f64,
    /// Length of the ground-truth path over the matched poses (to judge errors relatively).
    pub gt_path_length: f64,
    /// The alignment estimate -> ground truth.
    pub alignment: Similarity,
}

/// ATE of `est` against `gt` with Sim(3) alignment; see the module doc.
pub fn absolute_trajectory_error(
    est: &[StampedPose],
    gt: &[StampedPose],
    max_dt: f64,
) -> Result<AteReport, AlignmentError> {
    let pairs = associate(est, gt, max_dt);
    let src: Vec<_> = pairs.iter().map(|&(i, _)| est[i].position).collect();
    let dst: Vec<_> = pairs.iter().map(|&(_, g)| gt[g].position).collect();
    let alignment = umeyama(&src, &dst)?;
    let mut errors: Vec<f64> = src
        .iter()
        .zip(&dst)
        .map(|(s, d)| (alignment.apply(s) - d).norm())
        .collect();
    let n = errors.len() as f64;
    let rmse = (errors.iter().map(|e| e * e).sum::<f64>() / n).sqrt();
    let mean = errors.iter().sum::<f64>() / n;
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    let max = errors.last().copied().unwrap_or(0.0);
    let gt_path_length = dst.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    Ok(AteReport {
        matched: pairs.len(),
        rmse,
        mean,
        median,
        max,
        gt_path_length,
        alignment,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn centres_are_shared_up_to_rounding_only() {
        let at = |x: f64| StampedPose {
            timestamp: 0.0,
            position: Vector3::new(x, 2.0, -1.0),
            rotation: UnitQuaternion::identity(),
        };
        assert!(at(1000.0).shares_centre_with(&at(1000.0 + 1e-9)));
        assert!(!at(1000.0).shares_centre_with(&at(1000.0 + 1e-3)));
        assert!(!at(0.0).shares_centre_with(&at(1e-6)));
    }

    fn pose(t: f64, p: Vector3<f64>) -> StampedPose {
        StampedPose {
            timestamp: t,
            position: p,
            rotation: UnitQuaternion::identity(),
        }
    }

    #[test]
    fn association_respects_the_window_and_uses_each_pose_once() {
        let est: Vec<_> = [0.0, 0.1, 0.2, 0.5]
            .iter()
            .map(|&t| pose(t, Vector3::zeros()))
            .collect();
        let gt: Vec<_> = [0.005, 0.095, 0.11, 0.9]
            .iter()
            .map(|&t| pose(t, Vector3::zeros()))
            .collect();
        let pairs = associate(&est, &gt, 0.02);
        assert_eq!(pairs, vec![(0, 0), (1, 1)]);
    }

    #[test]
    fn ate_is_zero_for_a_similar_copy_and_measures_noise() {
        let truth = Similarity {
            scale: 0.3,
            rotation: Rotation3::from_euler_angles(0.1, 0.2, 0.3),
            translation: Vector3::new(5.0, 0.0, -1.0),
        };
        let gt: Vec<_> = (0..50)
            .map(|i| {
                pose(
                    i as f64 * 0.1,
                    Vector3::new(i as f64 * 0.1, (i as f64 * 0.3).sin(), 0.0),
                )
            })
            .collect();
        let est: Vec<_> = gt
            .iter()
            .map(|p| pose(p.timestamp + 0.001, truth.inverse().apply(&p.position)))
            .collect();
        let rep = absolute_trajectory_error(&est, &gt, 0.02).expect("aligned");
        assert_eq!(rep.matched, 50);
        assert!(rep.rmse < 1e-9, "rmse {}", rep.rmse);
        assert!((rep.alignment.scale - 0.3).abs() < 1e-9);

        // A 1 cm offset on alternate poses (not removable by a similarity) shows up.
        let noisy: Vec<_> = est
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let off = if i % 2 == 0 { 0.01 } else { -0.01 } / 0.3;
                pose(p.timestamp, p.position + Vector3::new(0.0, 0.0, off))
            })
            .collect();
        let rep = absolute_trajectory_error(&noisy, &gt, 0.02).expect("aligned");
        assert!((rep.rmse - 0.01).abs() < 1e-3, "rmse {}", rep.rmse);
    }
}
