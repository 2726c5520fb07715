//! How well a triangulated point is determined by the views that saw it, with the cameras
//! held fixed: the first-order covariance of the point, `sigma^2 (sum J^T J)^-1`, where `J`
//! is the 2 x 3 Jacobian of each view's pinhole projection (Hartley and Zisserman 2004,
//! section 5.2.1, forward propagation of covariance). Its largest standard deviation (the
//! depth direction for a point seen from a short or forward baseline) over the distance to
//! the nearest camera says whether the point is known: a point seen at 10 m from a 2 m
//! forward move has a depth standard deviation of metres though every ray reprojects
//! within a pixel. Like LSD-SLAM's and DSO's depth variances, it decides which points a map
//! publishes; unlike a minimum triangulation angle alone, it also counts the number of
//! views and where in the image the point is (near the focus of expansion a forward move
//! gives no depth at all).

use crate::trajectory::StampedPose;
use nalgebra::{Matrix2x3, Matrix3, Vector3};

/// Information (inverse covariance at unit pixel noise) gathered over a point's views.
/// Accumulated one observation at a time, so that a map with millions of observations
/// needs no per-point list.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointInformation {
    information: Matrix3<f64>,
    nearest_depth: f64,
}

impl Default for PointInformation {
    fn default() -> Self {
        Self {
            information: Matrix3::zeros(),
            nearest_depth: f64::INFINITY,
        }
    }
}

impl PointInformation {
    /// Adds the view `world_from_camera` of an ideal pinhole camera with focal length
    /// `focal_px`. A view with the point behind or on the camera adds nothing. Returns the
    /// point in that camera's frame (callers that also reproject it need not transform it
    /// again).
    pub fn add_view(
        &mut self,
        point: &Vector3<f64>,
        world_from_camera: &StampedPose,
        focal_px: f64,
    ) -> Vector3<f64> {
        let camera_from_world = world_from_camera.rotation.inverse();
        let p = camera_from_world * (point - world_from_camera.position);
        if p.z <= 1e-9 {
            return p;
        }
        let z = p.z;
        let projection =
            Matrix2x3::new(1.0 / z, 0.0, -p.x / (z * z), 0.0, 1.0 / z, -p.y / (z * z)) * focal_px;
        let jacobian = projection * camera_from_world.to_rotation_matrix().matrix();
        self.information += jacobian.transpose() * jacobian;
        self.nearest_depth = self.nearest_depth.min(z);
        p
    }

    /// Largest standard deviation of the point (pixel noise `pixel_sigma`) over its depth in
    /// the nearest view. `None` when the views do not fix the point (fewer than two, or
    /// rays that are parallel to working precision).
    pub fn relative_std(&self, pixel_sigma: f64) -> Option<f64> {
        if !self.nearest_depth.is_finite() {
            return None;
        }
        let (weakest, strongest) = symmetric_eigenvalue_range(&self.information);
        // The strongest direction bounds the scale of the matrix: below 1e-12 of it the
        // weakest is rounding noise, not information.
        if weakest <= 1e-12 * strongest {
            return None;
        }
        Some(pixel_sigma / weakest.sqrt() / self.nearest_depth)
    }
}

/// Smallest and largest eigenvalue of a symmetric 3 x 3 matrix in closed form (Smith,
/// "Eigenvalues of a symmetric 3 x 3 matrix", CACM 1961): a map's points are scored every
/// few seconds, hundreds of thousands at a time, where an iterative decomposition cost
/// ~0.5 s per pass on the 12,000-frame walk.
fn symmetric_eigenvalue_range(a: &Matrix3<f64>) -> (f64, f64) {
    let off = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    let q = a.trace() / 3.0;
    let diagonal = (a[(0, 0)] - q).powi(2) + (a[(1, 1)] - q).powi(2) + (a[(2, 2)] - q).powi(2);
    let p2 = diagonal + 2.0 * off;
    if p2 <= f64::MIN_POSITIVE {
        return (q, q);
    }
    let p = (p2 / 6.0).sqrt();
    let b = (a - Matrix3::identity() * q) / p;
    let r = (b.determinant() / 2.0).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    let largest = q + 2.0 * p * phi.cos();
    let smallest = q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos();
    (smallest, largest)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    fn at(x: f64, z: f64) -> StampedPose {
        StampedPose {
            timestamp: 0.0,
            position: Vector3::new(x, 0.0, z),
            rotation: UnitQuaternion::identity(),
        }
    }

    #[test]
    fn sideways_baseline_gives_the_textbook_depth_std() {
        // Two views 1 m apart, a point 10 m ahead between them, f = 500 px: depth std of
        // the two-view stereo formula: the disparity f b / z carries the noise of both
        // rays (sqrt(2) sigma), so the depth std is sqrt(2) z^2 sigma / (f b).
        let point = Vector3::new(0.5, 0.0, 10.0);
        let mut info = PointInformation::default();
        info.add_view(&point, &at(0.0, 0.0), 500.0);
        info.add_view(&point, &at(1.0, 0.0), 500.0);
        let relative = info.relative_std(1.0).expect("determined");
        let stereo = 2f64.sqrt() * 10.0 * 10.0 / (500.0 * 1.0) / 10.0;
        assert!(
            (relative - stereo).abs() < 0.05 * stereo,
            "{relative} vs {stereo}"
        );
    }

    #[test]
    fn forward_move_does_not_fix_a_point_near_the_focus_of_expansion() {
        let mut ahead = PointInformation::default();
        let mut aside = PointInformation::default();
        for z in [0.0, 0.5, 1.0, 1.5, 2.0] {
            ahead.add_view(&Vector3::new(0.1, 0.0, 10.0), &at(0.0, z), 500.0);
            aside.add_view(&Vector3::new(4.0, 0.0, 10.0), &at(0.0, z), 500.0);
        }
        let ahead = ahead.relative_std(1.0).expect("determined");
        let aside = aside.relative_std(1.0).expect("determined");
        assert!(ahead > 20.0 * aside, "ahead {ahead}, aside {aside}");
        assert!(aside < 0.05, "aside {aside}");
    }

    #[test]
    fn closed_form_eigenvalues_match_the_iterative_ones() {
        let m =
            nalgebra::Matrix3x4::new(1.0, 0.2, -0.3, 2.0, 0.5, 1.5, 0.1, -1.0, 0.0, 0.3, 2.5, 0.7);
        for a in [m * m.transpose(), Matrix3::from_diagonal_element(2.0)] {
            let (lo, hi) = symmetric_eigenvalue_range(&a);
            let eig = a.symmetric_eigenvalues();
            assert!((lo - eig.min()).abs() < 1e-9 && (hi - eig.max()).abs() < 1e-9);
        }
    }

    #[test]
    fn one_view_or_points_behind_fix_nothing() {
        let point = Vector3::new(0.0, 0.0, 5.0);
        let mut info = PointInformation::default();
        assert_eq!(info.relative_std(1.0), None);
        info.add_view(&point, &at(0.0, 0.0), 500.0);
        assert_eq!(info.relative_std(1.0), None);
        info.add_view(&point, &at(0.0, 6.0), 500.0); // behind this one
        assert_eq!(info.relative_std(1.0), None);
    }
}
