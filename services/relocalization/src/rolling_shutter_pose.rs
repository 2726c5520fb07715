//! The pose of a single rolling-shutter frame: the camera's pose at the middle row and its
//! angular velocity, from 2-D/3-D correspondences.
//!
//! A rolling-shutter camera reads its rows one after the other: a row `(y - h/2) / h` of
//! the readout after the middle one was exposed that much later, from a camera that had
//! turned on. Tracked frames are corrected in the frontend, from each track's image motion
//! (`egoslam_frontend`); a query frame relocalized from scratch has no motion to read, so
//! its pose is refined here with the turn as three more unknowns (the first-order model of
//! Albl et al., "R6P - Rolling Shutter Absolute Camera Pose", CVPR 2015, and of Magerand
//! et al., "Global Optimization of Object Pose and Motion from a Single Rolling Shutter
//! Image", ECCV 2012). A head turns far faster than it walks (TUM fr1_rpy: ~64 deg/s, 1 cm
//! of travel over a 22 ms readout at most), so the linear velocity is left out.
//!
//! Levenberg-Marquardt on 9 parameters (rotation and centre increments, angular velocity in
//! the camera frame) with a Huber loss, started from the global-shutter pose with no turn.

use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Rotation3, SMatrix, SVector, UnitQuaternion, Vector3};

/// Settings of the refinement; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RollingShutterPoseOptions {
    /// Levenberg-Marquardt iterations (default 15: from the global-shutter pose the cost
    /// settles in 3-6).
    pub iterations: usize,
    /// Huber threshold, pixels (default 2, as the window bundle adjustment).
    pub huber_px: f64,
    /// Fewest correspondences (default 12: nine unknowns, and a turn is only seen across
    /// rows, so a handful of points on one row would not do).
    pub min_correspondences: usize,
    /// Largest angular velocity accepted, rad/s (default 15, ~860 deg/s: beyond any head;
    /// a larger one is the refinement fitting noise on an ill-spread point set).
    pub max_angular_velocity: f64,
}

impl Default for RollingShutterPoseOptions {
    fn default() -> Self {
        Self {
            iterations: 15,
            huber_px: 2.0,
            min_correspondences: 12,
            max_angular_velocity: 15.0,
        }
    }
}

/// A refined rolling-shutter pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RollingShutterPose {
    /// world_from_camera at the middle row's time.
    pub pose: StampedPose,
    /// Angular velocity in the camera frame, rad/s.
    pub angular_velocity: Vector3<f64>,
    /// Reprojection RMSE before and after, pixels.
    pub rmse_before_px: f64,
    pub rmse_after_px: f64,
}

impl RollingShutterPose {
    /// A pose and turn known from elsewhere (no refinement measured it: both errors 0).
    pub fn from_motion(pose: StampedPose, angular_velocity: Vector3<f64>) -> Self {
        Self {
            pose,
            angular_velocity,
            rmse_before_px: 0.0,
            rmse_after_px: 0.0,
        }
    }

    /// Undistorted pixel of `point` in `camera`, on the row whose exposure sees it: the
    /// row is found by fixed-point iteration from the middle-row projection (three steps:
    /// a head's turn moves a point by a few pixels over the readout, and each step shrinks
    /// the row error by that fraction of the image height).
    pub fn project(
        &self,
        camera: &PinholeRadtan,
        point: &Vector3<f64>,
        readout_s: f64,
    ) -> Option<Point2<f64>> {
        let mut pixel = self.on_row(camera, point, f64::from(camera.height) / 2.0, readout_s)?;
        for _ in 0..3 {
            pixel = self.on_row(camera, point, pixel.y, readout_s)?;
        }
        Some(pixel)
    }

    /// Distance, pixels, between `observed` (undistorted) and where `point` is seen on
    /// `observed`'s row.
    pub fn reprojection_error(
        &self,
        camera: &PinholeRadtan,
        point: &Vector3<f64>,
        observed: &Point2<f64>,
        readout_s: f64,
    ) -> Option<f64> {
        let q = self.on_row(camera, point, observed.y, readout_s)?;
        Some((q - observed).norm())
    }

    /// Undistorted pixel of `point` seen by the camera as it was when row `y` was read.
    fn on_row(
        &self,
        camera: &PinholeRadtan,
        point: &Vector3<f64>,
        y: f64,
        readout_s: f64,
    ) -> Option<Point2<f64>> {
        let tau = camera.row_offset(y) * readout_s;
        let rotation =
            self.pose.rotation * UnitQuaternion::from_scaled_axis(self.angular_velocity * tau);
        camera.project_undistorted(&(rotation.inverse() * (point - self.pose.position)))
    }
}

type Params = SVector<f64, 9>;

/// Pixels of `correspondences`' points seen by the camera `pose` (with `params` applied)
/// turning at the angular velocity in `params`, each on the row of its observation, minus
/// the observations. The increment and centre are applied once, not per point: the
/// forward-difference Jacobian evaluates this ten times per iteration.
fn residuals(
    camera: &PinholeRadtan,
    pose: &StampedPose,
    params: &Params,
    correspondences: &[(Vector3<f64>, Point2<f64>)],
    readout_s: f64,
) -> Option<Vec<[f64; 2]>> {
    let camera_from_base = (pose.rotation.to_rotation_matrix()
        * Rotation3::new(Vector3::new(params[0], params[1], params[2])))
    .inverse();
    let centre = pose.position + Vector3::new(params[3], params[4], params[5]);
    let omega = Vector3::new(params[6], params[7], params[8]);
    correspondences
        .iter()
        .map(|(x, p)| {
            let tau = camera.row_offset(p.y) * readout_s;
            let turned = Rotation3::new(omega * tau).inverse() * (camera_from_base * (x - centre));
            let q = camera.project_undistorted(&turned)?;
            Some([q.x - p.x, q.y - p.y])
        })
        .collect()
}

fn huber_cost(r: &[[f64; 2]], k: f64) -> f64 {
    r.iter()
        .map(|e| {
            let n = (e[0] * e[0] + e[1] * e[1]).sqrt();
            if n <= k {
                0.5 * n * n
            } else {
                k * (n - 0.5 * k)
            }
        })
        .sum()
}

fn rmse(r: &[[f64; 2]]) -> f64 {
    (r.iter().map(|e| e[0] * e[0] + e[1] * e[1]).sum::<f64>() / r.len().max(1) as f64).sqrt()
}

/// Refines `start` (world_from_camera, a global-shutter PnP pose) on inlier
/// `correspondences` (map point, undistorted pixel in `camera`, the ideal camera) with a
/// rolling shutter of `readout_s` seconds (`start` itself, with no turn, when no step lowers
/// the cost); `None` when there are too few correspondences, a point falls behind the
/// camera, or the turn found is beyond `max_angular_velocity` (the global-shutter pose then
/// stands).
pub fn refine_rolling_shutter_pose(
    camera: &PinholeRadtan,
    correspondences: &[(Vector3<f64>, Point2<f64>)],
    start: &StampedPose,
    readout_s: f64,
    options: &RollingShutterPoseOptions,
) -> Option<RollingShutterPose> {
    if readout_s.is_nan() || readout_s <= 0.0 || correspondences.len() < options.min_correspondences
    {
        return None;
    }
    let k = options.huber_px;
    let mut params = Params::zeros();
    let first = residuals(camera, start, &params, correspondences, readout_s)?;
    let mut cost = huber_cost(&first, k);
    // The residuals at `params`, carried from the step that was accepted.
    let mut current = first.clone();
    let mut lambda = 1e-3;
    for _ in 0..options.iterations {
        let r0 = &current;
        // Forward-difference Jacobian: 9 columns, a few hundred points.
        let mut jacobian = vec![[[0.0; 2]; 9]; r0.len()];
        for j in 0..9 {
            let step = if j >= 6 { 1e-4 } else { 1e-7 };
            let mut moved = params;
            moved[j] += step;
            let r1 = residuals(camera, start, &moved, correspondences, readout_s)?;
            for (i, (a, b)) in r1.iter().zip(r0).enumerate() {
                jacobian[i][j] = [(a[0] - b[0]) / step, (a[1] - b[1]) / step];
            }
        }
        let (mut jtj, mut jtr) = (SMatrix::<f64, 9, 9>::zeros(), Params::zeros());
        for (i, e) in r0.iter().enumerate() {
            let n = (e[0] * e[0] + e[1] * e[1]).sqrt();
            let w = if n <= k { 1.0 } else { k / n };
            for c in 0..2 {
                let row = Params::from_fn(|j, _| jacobian[i][j][c]);
                jtj += w * row * row.transpose();
                jtr += w * row * e[c];
            }
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut damped = jtj;
            for d in 0..9 {
                damped[(d, d)] += lambda * jtj[(d, d)].max(1e-9);
            }
            let Some(delta) = damped.cholesky().map(|c| c.solve(&(-jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let candidate = params + delta;
            if let Some(r) = residuals(camera, start, &candidate, correspondences, readout_s) {
                let c = huber_cost(&r, k);
                if c < cost {
                    params = candidate;
                    cost = c;
                    current = r;
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = true;
                    break;
                }
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let angular_velocity = Vector3::new(params[6], params[7], params[8]);
    if angular_velocity.norm() > options.max_angular_velocity {
        return None;
    }
    let rotation = start.rotation
        * UnitQuaternion::from_scaled_axis(Vector3::new(params[0], params[1], params[2]));
    Some(RollingShutterPose {
        pose: StampedPose {
            timestamp: start.timestamp,
            position: start.position + Vector3::new(params[3], params[4], params[5]),
            rotation,
        },
        angular_velocity,
        rmse_before_px: rmse(&first),
        rmse_after_px: rmse(&current),
    })
}

/// `start` refined with the turn on all `correspondences` (Huber), then again on those the
/// first refinement explains within `threshold_px`: the pose and the indices of the
/// correspondences kept. `None` when a refinement fails or fewer than `min_kept` remain.
pub fn refine_rolling_shutter_inliers(
    camera: &PinholeRadtan,
    correspondences: &[(Vector3<f64>, Point2<f64>)],
    start: &StampedPose,
    readout_s: f64,
    threshold_px: f64,
    min_kept: usize,
    options: &RollingShutterPoseOptions,
) -> Option<(RollingShutterPose, Vec<usize>)> {
    let first = refine_rolling_shutter_pose(camera, correspondences, start, readout_s, options)?;
    let kept: Vec<usize> = (0..correspondences.len())
        .filter(|&i| {
            let (point, observed) = &correspondences[i];
            first
                .reprojection_error(camera, point, observed, readout_s)
                .is_some_and(|e| e <= threshold_px)
        })
        .collect();
    if kept.len() < min_kept.max(1) {
        return None;
    }
    let pairs: Vec<_> = kept.iter().map(|&i| correspondences[i]).collect();
    let second = refine_rolling_shutter_pose(camera, &pairs, &first.pose, readout_s, options)?;
    Some((second, kept))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [520.0, 520.0, 320.0, 240.0], [0.0; 5]).expect("camera")
    }

    /// Points on a wall 2-4 m ahead, seen by a camera at `pose` turning at `omega` (camera
    /// frame, rad/s) with a `readout_s` rolling shutter: each point's pixel is found on the
    /// row whose exposure sees it there (fixed-point iteration on the row).
    fn observe(
        pose: &StampedPose,
        omega: Vector3<f64>,
        readout_s: f64,
    ) -> Vec<(Vector3<f64>, Point2<f64>)> {
        let cam = camera();
        let mut out = Vec::new();
        for i in 0..15 {
            for j in 0..12 {
                let x = Vector3::new(
                    -1.6 + 0.23 * i as f64,
                    -1.2 + 0.22 * j as f64,
                    2.0 + 0.13 * ((i * 7 + j * 3) % 16) as f64,
                );
                let mut row = 240.0;
                let mut pixel = None;
                for _ in 0..20 {
                    let tau = (row - 240.0) / 480.0 * readout_s;
                    let r = pose.rotation.to_rotation_matrix() * Rotation3::new(omega * tau);
                    pixel = cam.project_undistorted(&(r.inverse() * (x - pose.position)));
                    row = pixel.map_or(row, |p| p.y);
                }
                if let Some(p) = pixel.filter(|p| cam.contains(*p)) {
                    out.push((x, p));
                }
            }
        }
        out
    }

    #[test]
    fn a_turning_frame_is_posed_at_its_middle_row_with_its_turn() {
        let truth = StampedPose {
            timestamp: 0.0,
            position: Vector3::new(0.1, -0.05, 0.2),
            rotation: UnitQuaternion::from_euler_angles(0.05, -0.1, 0.02),
        };
        // 120 deg/s about the vertical axis and a little pitch: a head scan.
        let omega = Vector3::new(0.3, 2.1, 0.0);
        let readout = 0.025;
        let seen = observe(&truth, omega, readout);
        assert!(seen.len() > 100, "{}", seen.len());
        // Started from a global-shutter pose a little off (as PnP gives it).
        let start = StampedPose {
            position: truth.position + Vector3::new(0.01, 0.0, -0.01),
            rotation: truth.rotation * UnitQuaternion::from_euler_angles(0.004, 0.006, 0.0),
            ..truth
        };
        let found = refine_rolling_shutter_pose(
            &camera(),
            &seen,
            &start,
            readout,
            &RollingShutterPoseOptions::default(),
        )
        .expect("refined");
        assert!(found.rmse_after_px < 0.01, "{}", found.rmse_after_px);
        assert!((found.pose.position - truth.position).norm() < 1e-4);
        assert!(found.pose.rotation.angle_to(&truth.rotation) < 1e-5);
        assert!(
            (found.angular_velocity - omega).norm() < 0.01,
            "{}",
            found.angular_velocity
        );
        // Told the wrong readout of 0 there is nothing to refine.
        assert!(refine_rolling_shutter_pose(
            &camera(),
            &seen,
            &start,
            0.0,
            &RollingShutterPoseOptions::default()
        )
        .is_none());
    }

    #[test]
    fn a_still_frame_keeps_its_pose_and_finds_no_turn() {
        let truth = StampedPose {
            timestamp: 0.0,
            position: Vector3::new(0.0, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        };
        let seen = observe(&truth, Vector3::zeros(), 0.03);
        let found = refine_rolling_shutter_pose(
            &camera(),
            &seen,
            &truth,
            0.03,
            &RollingShutterPoseOptions::default(),
        )
        .expect("refined");
        assert!(found.angular_velocity.norm() < 1e-6);
        assert!((found.pose.position - truth.position).norm() < 1e-9);
        // Too few points: refused.
        assert!(refine_rolling_shutter_pose(
            &camera(),
            &seen[..5],
            &truth,
            0.03,
            &RollingShutterPoseOptions::default()
        )
        .is_none());
    }

    #[test]
    fn a_turning_pose_sees_points_on_their_rows_and_outliers_are_dropped() {
        let truth = StampedPose {
            timestamp: 0.0,
            position: Vector3::new(-0.1, 0.05, 0.1),
            rotation: UnitQuaternion::from_euler_angles(-0.03, 0.08, 0.01),
        };
        let omega = Vector3::new(-0.4, 1.8, 0.2);
        let readout = 0.022;
        let mut seen = observe(&truth, omega, readout);
        let turning = RollingShutterPose::from_motion(truth, omega);
        let cam = camera();
        // The projection finds each point's pixel on the row that sees it, to within the
        // fixed-point iteration's residue; the middle row's pose alone misses by pixels.
        let (mut worst, mut worst_still) = (0.0f64, 0.0f64);
        for (x, p) in &seen {
            let q = turning.project(&cam, x, readout).expect("in front");
            worst = worst.max((q - p).norm());
            let still = cam
                .project_undistorted(&(truth.rotation.inverse() * (x - truth.position)))
                .expect("in front");
            worst_still = worst_still.max((still - p).norm());
            let e = turning
                .reprojection_error(&cam, x, p, readout)
                .expect("in front");
            assert!(e < 1e-9, "{e}");
        }
        assert!(worst < 0.01, "{worst}");
        assert!(worst_still > 5.0, "{worst_still}");
        // A fifth of the correspondences moved 20 px: refined with the turn, they are the
        // ones left out, and the pose is the truth's.
        let moved: Vec<usize> = (0..seen.len()).step_by(5).collect();
        for &i in &moved {
            seen[i].1.x += 20.0;
        }
        let start = StampedPose {
            position: truth.position + Vector3::new(0.01, -0.01, 0.0),
            ..truth
        };
        let (found, kept) = refine_rolling_shutter_inliers(
            &cam,
            &seen,
            &start,
            readout,
            1.5,
            15,
            &RollingShutterPoseOptions::default(),
        )
        .expect("refined");
        assert_eq!(kept.len(), seen.len() - moved.len());
        assert!(kept.iter().all(|i| !moved.contains(i)));
        assert!((found.pose.position - truth.position).norm() < 1e-4);
        assert!((found.angular_velocity - omega).norm() < 0.01);
        // Asked to keep more than it can explain: refused.
        assert!(refine_rolling_shutter_inliers(
            &cam,
            &seen,
            &start,
            readout,
            1.5,
            seen.len(),
            &RollingShutterPoseOptions::default()
        )
        .is_none());
    }
}
