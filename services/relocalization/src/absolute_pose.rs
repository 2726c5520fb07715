//! Camera pose from 2-D/3-D correspondences: OpenCV's `solvePnPRansac` then a
//! Levenberg-Marquardt refinement on the inliers (`solvePnPRefineLM`).
//!
//! Two uses: with a prior (a frame between keyframes, started from its interpolated pose:
//! iterative PnP from the guess) and from scratch (relocalization: AP3P minimal samples, Ke
//! and Roumeliotis, "An Efficient Algebraic Solution to the Perspective-Three-Point
//! Problem", CVPR 2017, which needs no initial guess).

use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Rotation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Point2d, Point3d, TermCriteria, Vector};
use opencv::prelude::*;

/// RANSAC settings and acceptance thresholds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PnpOptions {
    /// Fewest correspondences tried and fewest inliers accepted.
    pub min_inliers: usize,
    /// Fraction of correspondences that must be inliers.
    pub min_inlier_ratio: f64,
    /// RANSAC inlier threshold, pixels.
    pub ransac_threshold_px: f64,
    /// RANSAC iterations.
    pub ransac_iterations: i32,
}

impl PnpOptions {
    /// Inliers a pose from `correspondences` needs: `min_inliers`, and `min_inlier_ratio`
    /// of them.
    pub fn inliers_needed(&self, correspondences: usize) -> usize {
        self.min_inliers
            .max((self.min_inlier_ratio * correspondences as f64).ceil() as usize)
    }
}

/// Why no pose was found.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PnpError {
    /// Fewer correspondences than `min_inliers`.
    #[error("{0} correspondences, too few")]
    TooFewCorrespondences(usize),
    /// RANSAC found no pose, or too few inliers.
    #[error("{inliers} of {correspondences} inliers")]
    TooFewInliers {
        inliers: usize,
        correspondences: usize,
    },
    /// OpenCV failed.
    #[error("OpenCV: {0}")]
    OpenCv(String),
}

/// A pose with its support.
#[derive(Debug, Clone, PartialEq)]
pub struct PnpSolution {
    /// world_from_camera (timestamp copied from the prior, 0 without one).
    pub pose: StampedPose,
    /// Indices of the inlier correspondences.
    pub inliers: Vec<usize>,
}

fn mat3(values: &[f64; 3]) -> Result<Mat, opencv::Error> {
    Mat::from_slice(values).and_then(|m| m.try_clone())
}

fn vec3_of(m: &Mat) -> Result<Vector3<f64>, opencv::Error> {
    Ok(Vector3::new(
        *m.at::<f64>(0)?,
        *m.at::<f64>(1)?,
        *m.at::<f64>(2)?,
    ))
}

/// Pose of a camera (ideal pinhole `camera`, undistorted pixels) from `(world point, pixel)`
/// correspondences; `prior` (world_from_camera) starts the search when given.
pub fn solve_pnp(
    camera: &PinholeRadtan,
    correspondences: &[(Vector3<f64>, Point2<f64>)],
    prior: Option<&StampedPose>,
    options: &PnpOptions,
) -> Result<PnpSolution, PnpError> {
    if correspondences.len() < options.min_inliers.max(4) {
        return Err(PnpError::TooFewCorrespondences(correspondences.len()));
    }
    let cv = |e: opencv::Error| PnpError::OpenCv(e.to_string());
    let objects: Vector<Point3d> = correspondences
        .iter()
        .map(|(x, _)| Point3d::new(x.x, x.y, x.z))
        .collect();
    let pixels: Vector<Point2d> = correspondences
        .iter()
        .map(|(_, p)| Point2d::new(p.x, p.y))
        .collect();
    let k = Mat::from_slice_2d(&[
        [camera.fx, 0.0, camera.cx],
        [0.0, camera.fy, camera.cy],
        [0.0, 0.0, 1.0],
    ])
    .map_err(cv)?;
    let no_distortion = Mat::default();
    let (mut rvec, mut tvec, method) = match prior {
        Some(prior) => {
            // The prior as camera_from_world: R = R_wc^T, t = -R C.
            let r_cw = prior.rotation.inverse().to_rotation_matrix();
            let t_cw = -(r_cw * prior.position);
            let axis = r_cw.scaled_axis();
            (
                mat3(&[axis.x, axis.y, axis.z]).map_err(cv)?,
                mat3(&[t_cw.x, t_cw.y, t_cw.z]).map_err(cv)?,
                opencv::calib3d::SOLVEPNP_ITERATIVE,
            )
        }
        None => (
            mat3(&[0.0; 3]).map_err(cv)?,
            mat3(&[0.0; 3]).map_err(cv)?,
            opencv::calib3d::SOLVEPNP_AP3P,
        ),
    };
    let mut inliers = Vector::<i32>::new();
    let found = opencv::calib3d::solve_pnp_ransac(
        &objects,
        &pixels,
        &k,
        &no_distortion,
        &mut rvec,
        &mut tvec,
        prior.is_some(),
        options.ransac_iterations,
        options.ransac_threshold_px as f32,
        0.999,
        &mut inliers,
        method,
    )
    .map_err(cv)?;
    if !found || inliers.len() < options.inliers_needed(correspondences.len()) {
        return Err(PnpError::TooFewInliers {
            inliers: inliers.len(),
            correspondences: correspondences.len(),
        });
    }
    let inlier_objects: Vector<Point3d> = inliers
        .iter()
        .filter_map(|i| objects.get(i as usize).ok())
        .collect();
    let inlier_pixels: Vector<Point2d> = inliers
        .iter()
        .filter_map(|i| pixels.get(i as usize).ok())
        .collect();
    let criteria = TermCriteria::new(
        opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
        20,
        f64::EPSILON,
    )
    .map_err(cv)?;
    opencv::calib3d::solve_pnp_refine_lm(
        &inlier_objects,
        &inlier_pixels,
        &k,
        &no_distortion,
        &mut rvec,
        &mut tvec,
        criteria,
    )
    .map_err(cv)?;
    let r_cw = Rotation3::from_scaled_axis(vec3_of(&rvec).map_err(cv)?);
    let t_cw = vec3_of(&tvec).map_err(cv)?;
    if !(r_cw.matrix().iter().all(|v| v.is_finite()) && t_cw.iter().all(|v| v.is_finite())) {
        return Err(PnpError::TooFewInliers {
            inliers: 0,
            correspondences: correspondences.len(),
        });
    }
    Ok(PnpSolution {
        pose: StampedPose {
            timestamp: prior.map_or(0.0, |p| p.timestamp),
            position: -(r_cw.inverse() * t_cw),
            rotation: UnitQuaternion::from_rotation_matrix(&r_cw.inverse()),
        },
        inliers: inliers.iter().map(|i| i as usize).collect(),
    })
}
