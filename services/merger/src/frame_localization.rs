//! Poses of frames between keyframes by PnP on the map (paper, section 5: "resectioning").
//!
//! A non-keyframe's tracked points that are map points give 2-D/3-D correspondences; the
//! pose comes from OpenCV's `solvePnPRansac` (iterative PnP, started from the pose
//! interpolated between the bracketing keyframes) and a Levenberg-Marquardt refinement on
//! the inliers (`solvePnPRefineLM`). A result that is weakly supported or far from the
//! interpolated prior is refused, and the caller keeps the interpolation (marked as such).

use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_relocalization::absolute_pose::{solve_pnp, PnpError, PnpOptions};
use nalgebra::{Point2, Vector3};

/// Acceptance thresholds; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalizationOptions {
    /// PnP from the prior. Defaults: at least 12 inliers (PnP needs 4, but fewer than a
    /// dozen are easily a degenerate, planar or clustered set) making at least 50 % of the
    /// correspondences (tracks that are map points passed the window's BA, so most must
    /// agree), within 2 px (the window BA's Huber threshold), 100 RANSAC draws (with >= 50 %
    /// inliers and 4-point samples, 100 draws miss an all-inlier sample with p < 1e-3).
    pub pnp: PnpOptions,
    /// Largest rotation from the interpolated prior, degrees (default 10: between two
    /// keyframes a head turns at most the flow threshold's worth, ~20 px ~ 2-3 deg).
    pub max_rotation_from_prior_deg: f64,
    /// Correspondences whose ray is further than this from the optical axis, degrees, are
    /// left out (default 60: only a fisheye has them). PnP measures residuals on the ideal
    /// pinhole plane, which stretches a pixel's tracking noise by 1 / cos^2 of the angle
    /// (4x at 60 deg, 33x at 80): beyond it true matches fall outside the 2 px threshold,
    /// and a frame's inliers fall below half (37-50 % through a 260 px/rad fisheye).
    pub max_ray_angle_deg: f64,
}

impl Default for LocalizationOptions {
    fn default() -> Self {
        Self {
            pnp: PnpOptions {
                min_inliers: 12,
                min_inlier_ratio: 0.5,
                ransac_threshold_px: 2.0,
                ransac_iterations: 100,
            },
            max_rotation_from_prior_deg: 10.0,
            max_ray_angle_deg: 60.0,
        }
    }
}

/// Why a frame was not localized.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LocalizationError {
    /// PnP found no supported pose (too few correspondences or inliers, or OpenCV failed).
    #[error(transparent)]
    Pnp(#[from] PnpError),
    /// The pose is too far from the interpolated prior to be trusted.
    #[error("{0:.1} deg from the interpolated pose")]
    FarFromPrior(f64),
}

/// A localized frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Localized {
    pub pose: StampedPose,
    pub inliers: usize,
}

/// Localizes one frame from `(map point, undistorted pixel)` correspondences, starting at
/// `prior` (the interpolated pose, world_from_camera).
pub fn localize_frame(
    camera: &PinholeRadtan,
    correspondences: &[(Vector3<f64>, Point2<f64>)],
    prior: &StampedPose,
    options: &LocalizationOptions,
) -> Result<Localized, LocalizationError> {
    let min_cos = options.max_ray_angle_deg.to_radians().cos();
    let near_axis: Vec<(Vector3<f64>, Point2<f64>)> = correspondences
        .iter()
        .filter(|(_, px)| camera.bearing_from_undistorted(*px).z >= min_cos)
        .copied()
        .collect();
    let deviation = |solution: &egoslam_relocalization::absolute_pose::PnpSolution| {
        let d = solution
            .pose
            .rotation
            .angle_to(&prior.rotation)
            .to_degrees();
        if d.is_finite() {
            d
        } else {
            f64::INFINITY
        }
    };
    let mut solution = solve_pnp(camera, &near_axis, Some(prior), &options.pnp)?;
    if deviation(&solution) > options.max_rotation_from_prior_deg {
        // Iterated from the prior, the RANSAC's models can settle in a flipped minimum
        // (through a fisheye, 83-116 deg from the prior on 760-820 correspondences, where a
        // rendered walk stopped): solved again without the prior, a true pose near it is
        // found.
        if let Ok(again) = solve_pnp(camera, &near_axis, None, &options.pnp) {
            if deviation(&again) < deviation(&solution) {
                solution = again;
            }
        }
    }
    let deviation = deviation(&solution);
    if deviation > options.max_rotation_from_prior_deg {
        return Err(LocalizationError::FarFromPrior(deviation));
    }
    Ok(Localized {
        // The retry without the prior stamps its pose 0.
        pose: StampedPose {
            timestamp: prior.timestamp,
            ..solution.pose
        },
        inliers: solution.inliers.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

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
            Err(LocalizationError::Pnp(PnpError::TooFewCorrespondences(8)))
        );
    }

    #[test]
    fn a_fisheye_frame_is_localized_from_the_rays_near_its_axis() {
        // Through a 260 px/rad equidistant lens, with 1 px of tracking noise in its raw
        // pixels along the radius: 60 correspondences within 50 deg of the axis and 90
        // between 70 and 79.5 deg, where the ideal pinhole plane stretches that noise 8-40
        // times.
        let camera = PinholeRadtan::new(640, 480, [260.0, 260.0, 320.0, 240.0], [0.0; 5])
            .and_then(|c| c.with_lens(egoslam_geometry::LensModel::Equidistant))
            .expect("fisheye");
        let truth = StampedPose {
            timestamp: 1.0,
            position: Vector3::new(0.3, -0.1, 0.2),
            rotation: UnitQuaternion::from_euler_angles(0.05, 0.2, -0.03),
        };
        let mut correspondences = Vec::new();
        for i in 0..150u32 {
            let (from, to) = if i < 60 { (5.0, 50.0) } else { (70.0, 79.5) };
            let theta = (from + (to - from) * f64::from(i % 30) / 29.0).to_radians();
            let phi = f64::from(i) * 2.399; // golden angle: spread around the axis
            let ray = Vector3::new(
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            );
            let depth = 2.0 + f64::from(i % 7) * 0.5;
            let x = truth.rotation * (ray * depth) + truth.position;
            let raw = camera.project_raw(&(ray * depth)).expect("imaged");
            // Along the radius, where the lens compresses most, alternating in sign.
            let outward = nalgebra::Vector2::new(phi.cos(), phi.sin());
            let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
            let noisy = raw + 1.0 * sign * outward;
            if let Some(px) = camera.undistort_pixel(noisy) {
                correspondences.push((x, px));
            }
        }
        let prior = StampedPose {
            position: truth.position + Vector3::new(0.05, 0.0, -0.02),
            rotation: UnitQuaternion::from_euler_angles(0.0, 0.035, 0.0) * truth.rotation,
            ..truth
        };
        let options = LocalizationOptions::default();
        let got = localize_frame(&camera, &correspondences, &prior, &options).expect("localized");
        assert!(
            (got.pose.position - truth.position).norm() < 0.02,
            "{got:?}"
        );
        let turn = got.pose.rotation.angle_to(&truth.rotation).to_degrees();
        assert!(turn < 0.5, "{turn} deg");
        let every_ray = LocalizationOptions {
            max_ray_angle_deg: 90.0,
            ..options
        };
        let all = localize_frame(&camera, &correspondences, &prior, &every_ray);
        assert!(
            all.is_err(),
            "with the stretched rays the inliers are too few a share: {all:?} of {}",
            correspondences.len()
        );
    }
}
