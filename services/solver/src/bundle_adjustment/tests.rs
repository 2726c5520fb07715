//! Tests of bundle adjustment on synthetic truth (fixed seeds).

use super::*;
use crate::test_support::gaussian;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

#[test]
fn points_pulled_onto_a_camera_are_collapsed() {
    // One camera at the origin looking along z: points in its frame as they are.
    let in_camera = vec![
        Vector3::new(0.0, 0.0, 4.0),
        Vector3::new(0.5, 0.0, 5.0),
        Vector3::new(0.0, 0.3, 3.0),
        Vector3::new(0.0, 0.0, 0.04),
    ];
    let observations: Vec<Observation> = (0..4)
        .map(|point| Observation {
            camera: 0,
            point,
            pixel: Point2::new(0.0, 0.0),
        })
        .collect();
    // Median depth 4: 0.04 is below 2 % of it, 3 is not; 0 disables the rule.
    assert_eq!(
        collapsed_points(4, &observations, &in_camera, 0.02),
        vec![false, false, false, true]
    );
    assert_eq!(
        collapsed_points(4, &observations, &in_camera, 0.0),
        vec![false; 4]
    );
}

fn small_rotation(axis: Vector3<f64>, angle: f64) -> Rotation3<f64> {
    Rotation3::new(axis.normalize() * angle)
}

#[test]
fn recovers_from_perturbed_start_and_flags_outliers() {
    let mut rng = StdRng::seed_from_u64(11);
    let camera =
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
    // 20 cameras walking and turning, 300 points in front.
    let truth_poses: Vec<CameraPose> = (0..20)
        .map(|i| CameraPose {
            rotation: Rotation3::from_euler_angles(0.02 * i as f64, 0.03 * i as f64, 0.0),
            centre: Vector3::new(0.1 * i as f64, 0.02 * i as f64, 0.05 * i as f64),
        })
        .collect();
    let truth_points: Vec<Vector3<f64>> = (0..300)
        .map(|_| {
            Vector3::new(
                rng.random_range(-3.0..5.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(5.0..10.0),
            )
        })
        .collect();
    let mut observations = Vec::new();
    let mut injected = Vec::new();
    for (k, x) in truth_points.iter().enumerate() {
        for (c, pose) in truth_poses.iter().enumerate() {
            if let Some(p) = camera.project_undistorted(&pose.to_camera(x)) {
                if !camera.contains(p) {
                    continue;
                }
                let mut px = Point2::new(p.x + gaussian(&mut rng), p.y + gaussian(&mut rng));
                if rng.random_range(0.0..1.0) < 0.05 {
                    px.x += rng.random_range(15.0..40.0)
                        * if rng.random_range(0.0..1.0) < 0.5 {
                            -1.0
                        } else {
                            1.0
                        };
                    injected.push(observations.len());
                }
                observations.push(Observation {
                    camera: c,
                    point: k,
                    pixel: px,
                });
            }
        }
    }
    // Start: poses perturbed by 2 deg and 5 % of the path, points by 10 %.
    let start_poses: Vec<CameraPose> = truth_poses
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if i == 0 {
                return *p;
            }
            let axis = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            let dir = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            CameraPose {
                rotation: small_rotation(axis, 2f64.to_radians()) * p.rotation,
                centre: p.centre + dir * 0.05 * 2.0,
            }
        })
        .collect();
    let start_points: Vec<Vector3<f64>> = truth_points
        .iter()
        .map(|x| {
            x + Vector3::new(gaussian(&mut rng), gaussian(&mut rng), gaussian(&mut rng))
                * 0.1
                * x.norm()
                / 3f64.sqrt()
        })
        .collect();
    let result = bundle_adjust(
        &camera,
        &start_poses,
        &start_points,
        &observations,
        &BundleAdjustmentOptions::default(),
    )
    .expect("ran");
    assert!(
        (result.rmse_px - 1.0).abs() < 0.1,
        "rmse {} px for 1 px noise",
        result.rmse_px
    );
    let flagged = injected
        .iter()
        .filter(|i| result.outliers.contains(i))
        .count();
    assert!(
        flagged as f64 >= 0.95 * injected.len() as f64,
        "{flagged} of {} outliers flagged",
        injected.len()
    );
    let false_alarms = result.outliers.len() - flagged;
    assert!(
        (false_alarms as f64) < 0.01 * observations.len() as f64,
        "{false_alarms} inliers flagged"
    );
    // Poses back near the truth (camera 0 fixes the gauge; scale is free: compare after
    // Umeyama on the centres).
    let est: Vec<_> = result.poses.iter().map(|p| p.centre).collect();
    let tru: Vec<_> = truth_poses.iter().map(|p| p.centre).collect();
    let sim = egoslam_geometry::umeyama(&est, &tru).expect("aligned");
    let worst = est
        .iter()
        .zip(&tru)
        .map(|(e, t)| (sim.apply(e) - t).norm())
        .fold(0.0, f64::max);
    assert!(worst < 0.02, "worst centre error {worst}");
}

#[test]
fn refines_focal_length() {
    let mut rng = StdRng::seed_from_u64(12);
    let camera =
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
    let true_camera =
        PinholeRadtan::new(640, 480, [520.0, 520.0, 320.0, 240.0], [0.0; 5]).expect("camera");
    let poses: Vec<CameraPose> = (0..10)
        .map(|i| CameraPose {
            rotation: Rotation3::from_euler_angles(0.0, 0.08 * i as f64, 0.0),
            centre: Vector3::new(0.3 * i as f64, 0.0, 0.0),
        })
        .collect();
    let points: Vec<Vector3<f64>> = (0..200)
        .map(|_| {
            Vector3::new(
                rng.random_range(-2.0..6.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(4.0..9.0),
            )
        })
        .collect();
    let mut observations = Vec::new();
    for (k, x) in points.iter().enumerate() {
        for (c, pose) in poses.iter().enumerate() {
            if let Some(p) = true_camera.project_undistorted(&pose.to_camera(x)) {
                if true_camera.contains(p) {
                    observations.push(Observation {
                        camera: c,
                        point: k,
                        pixel: Point2::new(
                            p.x + 0.3 * gaussian(&mut rng),
                            p.y + 0.3 * gaussian(&mut rng),
                        ),
                    });
                }
            }
        }
    }
    let options = BundleAdjustmentOptions {
        refine_intrinsics: true,
        max_iterations: 60,
        ..BundleAdjustmentOptions::default()
    };
    let result = bundle_adjust(&camera, &poses, &points, &observations, &options).expect("ran");
    assert!(
        (result.focal_scale - 1.04).abs() < 0.01,
        "focal scale {}",
        result.focal_scale
    );
    assert!(result.rmse_px < 0.4, "rmse {}", result.rmse_px);
}

/// Observations of `points` by cameras that turn at `turns` (rad/s) during a readout of
/// `readout_s`: each pixel is where its row's turned camera sees the point (the row time
/// found by fixed-point iteration), plus Gaussian noise of `sigma` px.
fn rolling_shutter_observations(
    camera: &PinholeRadtan,
    poses: &[CameraPose],
    turns: &[Vector3<f64>],
    points: &[Vector3<f64>],
    readout_s: f64,
    sigma: f64,
    rng: &mut StdRng,
) -> Vec<Observation> {
    let mut observations = Vec::new();
    for (c, (pose, turn)) in poses.iter().zip(turns).enumerate() {
        for (k, x) in points.iter().enumerate() {
            let pc = pose.to_camera(x);
            let Some(mut p) = camera.project_undistorted(&pc) else {
                continue;
            };
            for _ in 0..5 {
                let tau = readout_s * camera.row_offset(p.y);
                match camera.project_undistorted(&(pc + tau * turn.cross(&pc))) {
                    Some(q) => p = q,
                    None => break,
                }
            }
            if camera.contains(p) {
                observations.push(Observation {
                    camera: c,
                    point: k,
                    pixel: Point2::new(p.x + sigma * gaussian(rng), p.y + sigma * gaussian(rng)),
                });
            }
        }
    }
    observations
}

#[test]
fn rolling_shutter_turns_are_recovered_with_the_poses() {
    let mut rng = StdRng::seed_from_u64(13);
    let camera = crate::test_support::camera();
    let poses = crate::test_support::head_poses();
    let points = crate::test_support::random_points(&mut rng, 400);
    // Turns the frontend's correction missed: up to ~1.7 rad/s (100 deg/s) about any axis,
    // none on average (the correction's readout is right).
    let mut turns: Vec<Vector3<f64>> = (0..poses.len())
        .map(|_| {
            Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
        })
        .collect();
    let mean = turns.iter().sum::<Vector3<f64>>() / turns.len() as f64;
    turns.iter_mut().for_each(|t| *t -= mean);
    let readout_s = 0.03;
    let observations =
        rolling_shutter_observations(&camera, &poses, &turns, &points, readout_s, 0.5, &mut rng);
    let start_points: Vec<Vector3<f64>> = points
        .iter()
        .map(|x| {
            x + Vector3::new(gaussian(&mut rng), gaussian(&mut rng), gaussian(&mut rng)) * 0.05
        })
        .collect();
    let options = BundleAdjustmentOptions {
        fixed_cameras: 2,
        ..BundleAdjustmentOptions::default()
    };
    let global =
        bundle_adjust(&camera, &poses, &start_points, &observations, &options).expect("ran");
    let with_turns = bundle_adjust(
        &camera,
        &poses,
        &start_points,
        &observations,
        &BundleAdjustmentOptions {
            readout_s,
            ..options
        },
    )
    .expect("ran");
    // The turns come back, and with them the noise level; a global-shutter model cannot
    // explain the rows' shear.
    let worst_turn = with_turns
        .turns
        .iter()
        .zip(&turns)
        .map(|(a, b)| (a - b).norm())
        .fold(0.0, f64::max);
    assert!(worst_turn < 0.1, "worst turn error {worst_turn} rad/s");
    assert!(
        (with_turns.rmse_px - 0.5).abs() < 0.05,
        "rmse {} px for 0.5 px noise",
        with_turns.rmse_px
    );
    assert!(
        global.rmse_px > 1.5 * with_turns.rmse_px,
        "{}",
        global.rmse_px
    );
    assert!(global.turns.iter().all(|t| *t == Vector3::zeros()));
    let centre_error = |r: &BundleAdjustmentResult| {
        r.poses
            .iter()
            .zip(&poses)
            .map(|(a, b)| (a.centre - b.centre).norm())
            .fold(0.0, f64::max)
    };
    assert!(
        centre_error(&with_turns) < 0.2 * centre_error(&global),
        "centres off by {} with the turns, {} without",
        centre_error(&with_turns),
        centre_error(&global)
    );
}
