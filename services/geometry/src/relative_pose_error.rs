//! Relative pose error (Sturm et al., IROS 2012, "RPE"): drift over a fixed time step,
//! independent of where along the trajectory it happened. For every estimated pose i and
//! the first j at least `delta_s` later (both associated with ground truth), the motion
//! from i to j in i's camera frame is compared with the ground truth's; the estimate's
//! translation is first brought to metric scale with the ATE alignment's scale.

use crate::trajectory::{associate, StampedPose};

/// RPE over a time step.
#[derive(Debug, Clone, PartialEq)]
pub struct RpeReport {
    /// Pose pairs compared.
    pub pairs: usize,
    /// The time step, seconds.
    pub delta_s: f64,
    /// RMSE of the translation error of the relative motions, metres.
    pub translation_rmse_m: f64,
    /// The same over the mean ground-truth distance travelled per step (drift per metre,
    /// e.g. 0.01 = 1 %); `None` when the camera barely moved.
    pub translation_per_metre: Option<f64>,
    /// RMSE of the rotation error of the relative motions, degrees.
    pub rotation_rmse_deg: f64,
}

/// RPE of `est` (scaled by `scale`) against `gt`; `None` without a pair `delta_s` apart.
pub fn relative_pose_error(
    est: &[StampedPose],
    gt: &[StampedPose],
    max_dt: f64,
    delta_s: f64,
    scale: f64,
) -> Option<RpeReport> {
    let pairs = associate(est, gt, max_dt);
    let (mut t2, mut r2, mut travelled, mut n) = (0.0, 0.0, 0.0, 0usize);
    let mut j = 0;
    for (k, &(i, gi)) in pairs.iter().enumerate() {
        j = j.max(k + 1);
        while j < pairs.len() && est[pairs[j].0].timestamp < est[i].timestamp + delta_s {
            j += 1;
        }
        let Some(&(e_j, g_j)) = pairs.get(j) else {
            break;
        };
        let (a, b) = (&est[i], &est[e_j]);
        let (ga, gb) = (&gt[gi], &gt[g_j]);
        let rel_est = a.rotation.inverse() * ((b.position - a.position) * scale);
        let rel_gt = ga.rotation.inverse() * (gb.position - ga.position);
        let rot_est = a.rotation.inverse() * b.rotation;
        let rot_gt = ga.rotation.inverse() * gb.rotation;
        t2 += (rel_est - rel_gt).norm_squared();
        r2 += rot_est.angle_to(&rot_gt).to_degrees().powi(2);
        travelled += rel_gt.norm();
        n += 1;
    }
    if n == 0 {
        return None;
    }
    let translation_rmse_m = (t2 / n as f64).sqrt();
    let mean_travel = travelled / n as f64;
    Some(RpeReport {
        pairs: n,
        delta_s,
        translation_rmse_m,
        translation_per_metre: (mean_travel > 1e-3).then(|| translation_rmse_m / mean_travel),
        rotation_rmse_deg: (r2 / n as f64).sqrt(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    fn walk(n: usize, drift: f64) -> Vec<StampedPose> {
        (0..n)
            .map(|i| StampedPose {
                timestamp: i as f64 * 0.1,
                position: Vector3::new(0.1 * i as f64 * (1.0 + drift), 0.0, 0.0),
                rotation: UnitQuaternion::from_euler_angles(
                    0.0,
                    0.01 * i as f64 * (1.0 + drift),
                    0.0,
                ),
            })
            .collect()
    }

    #[test]
    fn zero_for_a_scaled_copy_and_measures_drift() {
        let gt = walk(50, 0.0);
        // The same trajectory at half scale: no error once the scale is applied.
        let half: Vec<StampedPose> = gt
            .iter()
            .map(|p| StampedPose {
                position: p.position * 0.5,
                ..*p
            })
            .collect();
        let r = relative_pose_error(&half, &gt, 0.01, 1.0, 2.0).expect("pairs");
        assert!(
            r.translation_rmse_m < 1e-12 && r.rotation_rmse_deg < 1e-9,
            "{r:?}"
        );
        assert_eq!(r.pairs, 40);
        // 5 % too fast and turning 5 % too much: per metre ~5 % (plus the turn's effect).
        let drifting = walk(50, 0.05);
        let r = relative_pose_error(&drifting, &gt, 0.01, 1.0, 1.0).expect("pairs");
        let per_metre = r.translation_per_metre.expect("moved");
        assert!((0.04..0.07).contains(&per_metre), "{r:?}");
        // 10 steps of 0.01 rad per second, 5 % more: 0.005 rad = 0.286 deg.
        assert!((r.rotation_rmse_deg - 0.2865).abs() < 0.005, "{r:?}");
        assert!(relative_pose_error(&gt[..5], &gt, 0.01, 1.0, 1.0).is_none());
    }
}
