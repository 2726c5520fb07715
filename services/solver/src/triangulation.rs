//! Multi-view linear triangulation with the usual acceptance checks.
//!
//! Hartley and Zisserman, "Multiple View Geometry", 2nd ed., section 12.2 (the DLT method on
//! normalised image coordinates), followed by the checks COLMAP applies before trusting a
//! point (Schönberger and Frahm, CVPR 2016, section 4.5): positive depth in every view,
//! a minimum triangulation angle, and a maximum reprojection error.

use egoslam_geometry::PinholeRadtan;
use nalgebra::{Matrix4, Point2, Rotation3, Vector3, Vector4};

/// A camera pose: `x_cam = rotation * (X - centre)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPose {
    pub rotation: Rotation3<f64>,
    pub centre: Vector3<f64>,
}

impl CameraPose {
    /// World point into the camera frame.
    pub fn to_camera(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * (x - self.centre)
    }
}

/// Acceptance thresholds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangulationOptions {
    /// Minimum angle between any two rays of the point, degrees (default 1.5, COLMAP's
    /// `min_tri_angle`; below it depth is mostly noise).
    pub min_angle_deg: f64,
    /// Maximum reprojection error of an accepted observation, pixels (default 4, COLMAP's
    /// `max_reproj_error` for triangulation).
    pub max_reprojection_px: f64,
}

impl Default for TriangulationOptions {
    fn default() -> Self {
        Self {
            min_angle_deg: 1.5,
            max_reprojection_px: 4.0,
        }
    }
}

/// Why a track yielded no point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TriangulationFailure {
    /// Fewer than two observations (left).
    TooFewViews,
    /// The rays are nearly parallel.
    LowAngle,
    /// The point lies behind a camera.
    Cheirality,
    /// The linear system has no finite solution.
    Degenerate,
}

/// An accepted point and the observations it kept.
#[derive(Debug, Clone, PartialEq)]
pub struct TriangulatedPoint {
    pub position: Vector3<f64>,
    /// Indices into the observation list that passed the reprojection check.
    pub inliers: Vec<usize>,
}

/// DLT on normalised coordinates.
fn dlt(
    camera: &PinholeRadtan,
    poses: &[CameraPose],
    observations: &[(usize, Point2<f64>)],
) -> Option<Vector3<f64>> {
    let mut ata = Matrix4::<f64>::zeros();
    for (cam, px) in observations {
        let pose = &poses[*cam];
        let r = pose.rotation.matrix();
        let t = -(pose.rotation * pose.centre);
        let p = |row: usize| Vector4::new(r[(row, 0)], r[(row, 1)], r[(row, 2)], t[row]);
        let (x, y) = (
            (px.x - camera.cx) / camera.fx,
            (px.y - camera.cy) / camera.fy,
        );
        for row in [x * p(2) - p(0), y * p(2) - p(1)] {
            ata += row * row.transpose();
        }
    }
    let eig = ata.symmetric_eigen();
    let (idx, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let h = eig.eigenvectors.column(idx);
    (h[3].abs() > 1e-12).then(|| Vector3::new(h[0] / h[3], h[1] / h[3], h[2] / h[3]))
}

/// Reprojection error of `x` in an observation, pixels; `None` behind the camera.
pub fn reprojection_error(
    camera: &PinholeRadtan,
    pose: &CameraPose,
    x: &Vector3<f64>,
    px: &Point2<f64>,
) -> Option<f64> {
    camera
        .project_undistorted(&pose.to_camera(x))
        .map(|p| (p - px).norm())
}

/// Triangulates one track from `(camera index, undistorted pixel)` observations, dropping
/// observations over the reprojection threshold (worst first).
pub fn triangulate_track(
    camera: &PinholeRadtan,
    poses: &[CameraPose],
    observations: &[(usize, Point2<f64>)],
    options: &TriangulationOptions,
) -> Result<TriangulatedPoint, TriangulationFailure> {
    if observations.len() < 2 {
        return Err(TriangulationFailure::TooFewViews);
    }
    let mut kept: Vec<usize> = (0..observations.len()).collect();
    let mut x = dlt(camera, poses, observations).ok_or(TriangulationFailure::Degenerate)?;
    // Drop the worst observation while it exceeds the threshold, re-solving each time: a
    // gross outlier drags the linear solution, so one pass over all views is not enough.
    loop {
        let errors: Vec<f64> = kept
            .iter()
            .map(|&o| {
                let (cam, px) = &observations[o];
                reprojection_error(camera, &poses[*cam], &x, px).unwrap_or(f64::INFINITY)
            })
            .collect();
        let (worst, &worst_error) = errors
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .ok_or(TriangulationFailure::TooFewViews)?;
        if worst_error <= options.max_reprojection_px {
            break;
        }
        if kept.len() <= 2 {
            return Err(
                if kept
                    .iter()
                    .any(|&o| poses[observations[o].0].to_camera(&x).z <= 0.0)
                {
                    TriangulationFailure::Cheirality
                } else {
                    TriangulationFailure::TooFewViews
                },
            );
        }
        kept.remove(worst);
        let subset: Vec<_> = kept.iter().map(|&o| observations[o]).collect();
        x = dlt(camera, poses, &subset).ok_or(TriangulationFailure::Degenerate)?;
    }
    if kept
        .iter()
        .any(|&o| poses[observations[o].0].to_camera(&x).z <= 0.0)
    {
        return Err(TriangulationFailure::Cheirality);
    }
    let min_cos = options.min_angle_deg.to_radians().cos();
    let rays: Vec<Vector3<f64>> = kept
        .iter()
        .map(|&o| (x - poses[observations[o].0].centre).normalize())
        .collect();
    let wide_enough = rays
        .iter()
        .enumerate()
        .any(|(a, ra)| rays[a + 1..].iter().any(|rb| ra.dot(rb) < min_cos));
    if !wide_enough {
        return Err(TriangulationFailure::LowAngle);
    }
    Ok(TriangulatedPoint {
        position: x,
        inliers: kept,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera")
    }

    fn poses() -> Vec<CameraPose> {
        (0..4)
            .map(|i| CameraPose {
                rotation: Rotation3::from_euler_angles(0.0, -0.05 * i as f64, 0.0),
                centre: Vector3::new(0.3 * i as f64, 0.0, 0.0),
            })
            .collect()
    }

    fn observe(x: &Vector3<f64>) -> Vec<(usize, Point2<f64>)> {
        let cam = camera();
        poses()
            .iter()
            .enumerate()
            .map(|(i, p)| {
                (
                    i,
                    cam.project_undistorted(&p.to_camera(x)).expect("in front"),
                )
            })
            .collect()
    }

    #[test]
    fn exact_point_and_outlier_observation_removed() {
        let x = Vector3::new(0.5, -0.2, 5.0);
        let mut obs = observe(&x);
        let p = triangulate_track(&camera(), &poses(), &obs, &TriangulationOptions::default())
            .expect("ok");
        assert!((p.position - x).norm() < 1e-9);
        obs[2].1.x += 30.0;
        let p = triangulate_track(&camera(), &poses(), &obs, &TriangulationOptions::default())
            .expect("ok");
        assert_eq!(p.inliers, vec![0, 1, 3]);
        assert!((p.position - x).norm() < 1e-6);
    }

    #[test]
    fn rejects_far_points_and_single_views() {
        let far = Vector3::new(0.0, 0.0, 500.0);
        let obs = observe(&far);
        assert_eq!(
            triangulate_track(&camera(), &poses(), &obs, &TriangulationOptions::default()),
            Err(TriangulationFailure::LowAngle)
        );
        assert_eq!(
            triangulate_track(
                &camera(),
                &poses(),
                &obs[..1],
                &TriangulationOptions::default()
            ),
            Err(TriangulationFailure::TooFewViews)
        );
    }
}
