//! Poses of frames between keyframes by PnP on the map (paper, section 5: "resectioning").
//!
//! A non-keyframe's tracked points that are map points give 2-D/3-D correspondences; the
//! pose comes from OpenCV's `solvePnPRansac` (iterative PnP, started from the pose
//! interpolated between the bracketing keyframes) and a Levenberg-Marquardt refinement on
//! the inliers (`solvePnPRefineLM`). A result that is weakly supported or far from the
//! interpolated prior is refused, and the caller keeps the interpolation (marked as such).

use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Rotation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Point2d, Point3d, TermCriteria, Vector};
use opencv::prelude::*;

/// Acceptance thresholds; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalizationOptions {
    /// Fewest correspondences tried and fewest inliers accepted (default 12: PnP needs 4,
    /// but fewer than a dozen inliers are easily a degenerate, planar or clustered set).
    pub min_inliers: usize,
    /// Fraction of correspondences that must be inliers (default 0.5: tracks that are map
    /// points passed the window's BA, so most must agree).
    pub min_inlier_ratio: f64,
    /// RANSAC inlier threshold, pixels (default 2, the window BA's Huber threshold).
    pub ransac_threshold_px: f64,
    /// RANSAC iterations (default 100: with >= 50 % inliers and 4-point samples, 100
    /// draws miss an all-inlier sample with probability < 1e-3).
    pub ransac_iterations: i32,
    /// Largest rotation from the interpolated prior, degrees (default 10: between two
    /// keyframes a head turns at most the flow threshold's worth, ~20 px ~ 2-3 deg).
    pub max_rotation_from_prior_deg: f64,
}

impl Default for LocalizationOptions {
    fn default() -> Self {
        Self {
            min_inliers: 12,
            min_inlier_ratio: 0.5,
            ransac_threshold_px: 2.0,
            ransac_iterations: 100,
            max_rotation_from_prior_deg: 10.0,
        }
    }
}

/// Why a frame was not localized.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LocalizationError {
    /// Fewer correspondences than `min_inliers`.
    #[error("{0} correspondences, too few")]
    TooFewCorrespondences(usize),
    /// RANSAC found no pose, or too few inliers.
    #[error("{inliers} of {correspondences} inliers")]
    TooFewInliers {
        inliers: usize,
        correspondences: usize,
    },
    /// The pose is too far from the interpolated prior to be trusted.
    #[error("{0:.1} deg from the interpolated pose")]
    FarFromPrior(f64),
    /// OpenCV failed.
    #[error("OpenCV: {0}")]
    OpenCv(String),
}

/// A localized frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Localized {
    pub pose: StampedPose,
    pub inliers: usize,
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

/// Localizes one frame from `(map point, undistorted pixel)` correspondences, starting at
/// `prior` (the interpolated pose, world_from_camera).
pub fn localize_frame(
    camera: &PinholeRadtan,
    correspondences: &[(Vector3<f64>, Point2<f64>)],
    prior: &StampedPose,
    options: &LocalizationOptions,
) -> Result<Localized, LocalizationError> {
    if correspondences.len() < options.min_inliers.max(4) {
        return Err(LocalizationError::TooFewCorrespondences(
            correspondences.len(),
        ));
    }
    let cv = |e: opencv::Error| LocalizationError::OpenCv(e.to_string());
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
    // Prior as camera_from_world: R = R_wc^T, t = -R C.
    let r_cw = prior.rotation.inverse().to_rotation_matrix();
    let t_cw = -(r_cw * prior.position);
    let axis = r_cw.scaled_axis();
    let mut rvec = mat3(&[axis.x, axis.y, axis.z]).map_err(cv)?;
    let mut tvec = mat3(&[t_cw.x, t_cw.y, t_cw.z]).map_err(cv)?;
    let mut inliers = Vector::<i32>::new();
    let found = opencv::calib3d::solve_pnp_ransac(
        &objects,
        &pixels,
        &k,
        &no_distortion,
        &mut rvec,
        &mut tvec,
        true,
        options.ransac_iterations,
        options.ransac_threshold_px as f32,
        0.999,
        &mut inliers,
        opencv::calib3d::SOLVEPNP_ITERATIVE,
    )
    .map_err(cv)?;
    let needed = options
        .min_inliers
        .max((options.min_inlier_ratio * correspondences.len() as f64).ceil() as usize);
    if !found || inliers.len() < needed {
        return Err(LocalizationError::TooFewInliers {
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
    let rotation = UnitQuaternion::from_rotation_matrix(&r_cw.inverse());
    let deviation = rotation.angle_to(&prior.rotation).to_degrees();
    if !deviation.is_finite() || deviation > options.max_rotation_from_prior_deg {
        return Err(LocalizationError::FarFromPrior(deviation));
    }
    Ok(Localized {
        pose: StampedPose {
            timestamp: prior.timestamp,
            position: -(r_cw.inverse() * t_cw),
            rotation,
        },
        inliers: inliers.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_frame_from_noisy_correspondences_with_outliers() {
        let camera =
            PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
        let truth = StampedPose {
            timestamp: 1.0,
            position: Vector3::new(0.3, -0.1, 0.2),
            rotation: UnitQuaternion::from_euler_angles(0.05, 0.2, -0.03),
        };
        let r_cw = truth.rotation.inverse();
        let mut state = 17u64;
        let mut uniform = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut correspondences = Vec::new();
        while correspondences.len() < 150 {
            let x = Vector3::new(
                4.0 * uniform() - 2.0,
                3.0 * uniform() - 1.5,
                2.0 + 4.0 * uniform(),
            );
            let pc = r_cw * (x - truth.position);
            let Some(px) = camera.project_undistorted(&pc) else {
                continue;
            };
            if !camera.contains(px) {
                continue;
            }
            let i = correspondences.len();
            let noise = Point2::new(uniform() - 0.5, uniform() - 0.5);
            // Every fifth correspondence is a wrong match, tens of pixels off.
            let px = if i % 5 == 0 {
                Point2::new(40.0 + 560.0 * uniform(), 40.0 + 400.0 * uniform())
            } else {
                px + noise.coords
            };
            correspondences.push((x, px));
        }
        // Prior: interpolation error of 5 cm and 2 deg.
        let prior = StampedPose {
            position: truth.position + Vector3::new(0.05, 0.0, -0.02),
            rotation: UnitQuaternion::from_euler_angles(0.0, 0.035, 0.0) * truth.rotation,
            ..truth
        };
        let got = localize_frame(
            &camera,
            &correspondences,
            &prior,
            &LocalizationOptions::default(),
        )
        .expect("localized");
        assert!(
            (got.pose.position - truth.position).norm() < 0.01,
            "{got:?}"
        );
        assert!(got.pose.rotation.angle_to(&truth.rotation).to_degrees() < 0.2);
        assert!(got.inliers >= 110 && got.inliers <= 125, "{}", got.inliers);
        let too_few = &correspondences[..8];
        assert_eq!(
            localize_frame(&camera, too_few, &prior, &LocalizationOptions::default()),
            Err(LocalizationError::TooFewCorrespondences(8))
        );
    }
}
