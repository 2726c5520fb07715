//! Orientation error of a trajectory: the angle between each estimated and true camera
//! orientation after the best constant rotation between the two frames, the chordal L2
//! mean of `R_true R_estimate^T` (Hartley et al., "Rotation Averaging", IJCV 2013, section
//! 5.3: the projection of the summed matrices onto SO(3)). It does not depend on the
//! positions or on the Sim(3) alignment, so it is defined for a trajectory that never
//! translates, and it is what a head-mounted client's rendering gets wrong when it is off.

use crate::trajectory::{associate, StampedPose};
use nalgebra::{Matrix3, Rotation3};

/// Orientation errors over the matched poses, degrees.
#[derive(Debug, Clone, PartialEq)]
pub struct OrientationReport {
    pub matched: usize,
    pub rmse_deg: f64,
    pub median_deg: f64,
    pub max_deg: f64,
    /// The constant rotation estimate -> ground truth.
    pub alignment: Rotation3<f64>,
}

/// Orientation error of `est` against `gt`, poses matched within `max_dt` seconds; `None`
/// when fewer than three match.
pub fn orientation_error(
    est: &[StampedPose],
    gt: &[StampedPose],
    max_dt: f64,
) -> Option<OrientationReport> {
    let pairs = associate(est, gt, max_dt);
    if pairs.len() < 3 {
        return None;
    }
    let rotations: Vec<(Matrix3<f64>, Matrix3<f64>)> = pairs
        .iter()
        .map(|&(i, g)| {
            (
                est[i].rotation.to_rotation_matrix().into_inner(),
                gt[g].rotation.to_rotation_matrix().into_inner(),
            )
        })
        .collect();
    let sum: Matrix3<f64> = rotations.iter().map(|(e, g)| g * e.transpose()).sum();
    let svd = sum.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let sign = (u * v_t).determinant().signum();
    let alignment = u * Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 1.0, sign)) * v_t;
    let mut angles: Vec<f64> = rotations
        .iter()
        .map(|(e, g)| {
            let residual = g.transpose() * alignment * e;
            ((residual.trace() - 1.0) / 2.0)
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees()
        })
        .collect();
    let n = angles.len() as f64;
    let rmse_deg = (angles.iter().map(|a| a * a).sum::<f64>() / n).sqrt();
    angles.sort_by(f64::total_cmp);
    Some(OrientationReport {
        matched: angles.len(),
        rmse_deg,
        median_deg: angles[angles.len() / 2],
        max_deg: angles.last().copied().unwrap_or(0.0),
        alignment: Rotation3::from_matrix_unchecked(alignment),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    fn pose(t: f64, rotation: UnitQuaternion<f64>) -> StampedPose {
        StampedPose {
            timestamp: t,
            position: Vector3::zeros(),
            rotation,
        }
    }

    #[test]
    fn a_constant_rotation_is_no_error_and_a_tilt_of_one_pose_is_its_angle() {
        // A turning head; the estimate is the truth in another frame (a constant rotation
        // apart), so its error is zero however the frame turns it.
        let truth: Vec<StampedPose> = (0..20)
            .map(|k| {
                let yaw = UnitQuaternion::from_euler_angles(0.0, 0.05 * k as f64, 0.01 * k as f64);
                pose(k as f64, yaw)
            })
            .collect();
        let frame = UnitQuaternion::from_euler_angles(0.3, -1.2, 2.0);
        let estimate: Vec<StampedPose> = truth
            .iter()
            .map(|p| pose(p.timestamp, frame * p.rotation))
            .collect();
        let r = orientation_error(&estimate, &truth, 0.01).expect("matched");
        assert_eq!(r.matched, 20);
        assert!(r.rmse_deg < 1e-6 && r.max_deg < 1e-6, "{r:?}");
        let back = r.alignment * frame.to_rotation_matrix();
        assert!(
            (back.matrix() - Matrix3::identity()).norm() < 1e-9,
            "the alignment undoes the frame"
        );
        // One pose tilted by 2 degrees about its own x axis: the largest error is about
        // 2 degrees, the median stays near zero, and the RMSE is about 2 / sqrt(20).
        let mut tilted = estimate.clone();
        tilted[7].rotation *= UnitQuaternion::from_euler_angles(2f64.to_radians(), 0.0, 0.0);
        let r = orientation_error(&tilted, &truth, 0.01).expect("matched");
        assert!((r.max_deg - 2.0).abs() < 0.15, "{r:?}");
        assert!(r.median_deg < 0.15, "{r:?}");
        assert!((r.rmse_deg - 2.0 / 20f64.sqrt()).abs() < 0.1, "{r:?}");
        assert!(orientation_error(&tilted[..2], &truth, 0.01).is_none());
    }
}
