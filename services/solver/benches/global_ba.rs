//! Global bundle adjustment at map scale: 1000 keyframes walking a corridor, ~100,000
//! observations (each point seen by ~6 consecutive keyframes), 0.5 px noise, poses perturbed
//! by 0.5 deg / 2 cm and points by 5 % of their depth. Median of 3 solves, one core (sparse Schur path).
//! `cargo bench -p egoslam-solver --bench global_ba`

use egoslam_geometry::PinholeRadtan;
use egoslam_solver::bundle_adjustment::{bundle_adjust, BundleAdjustmentOptions, Observation};
use egoslam_solver::triangulation::CameraPose;
use nalgebra::{Point2, Rotation3, Vector3};
use std::time::Instant;

/// New points per keyframe: with ~7 views each, ~100,000 observations for 1000 keyframes.
const POINTS_PER_KEYFRAME: usize = 18;

struct Lcg(u64);
impl Lcg {
    fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn gaussian(&mut self) -> f64 {
        let (a, b) = (self.uniform().max(1e-12), self.uniform());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }
}

fn main() {
    let camera =
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
    let mut rng = Lcg(5);
    let keyframes = 1000;
    // A corridor walk along z with a slow yaw sway.
    let truth: Vec<CameraPose> = (0..keyframes)
        .map(|k| {
            let t = k as f64;
            CameraPose {
                rotation: Rotation3::from_euler_angles(0.0, 0.15 * (0.02 * t).sin(), 0.0),
                centre: Vector3::new(0.3 * (0.01 * t).sin(), 0.0, 0.1 * t),
            }
        })
        .collect();
    // Points on the corridor walls ahead of each keyframe.
    let mut points = Vec::new();
    for k in 0..keyframes {
        for _ in 0..POINTS_PER_KEYFRAME {
            let side = if rng.uniform() < 0.5 { -2.0 } else { 2.0 };
            points.push(Vector3::new(
                side + 0.2 * rng.gaussian(),
                2.0 * rng.uniform() - 1.0,
                0.1 * k as f64 + 3.0 + 1.0 * rng.uniform(),
            ));
        }
    }
    let mut observations = Vec::new();
    for (i, x) in points.iter().enumerate() {
        let k0 = (i / POINTS_PER_KEYFRAME).saturating_sub(3);
        for (c, pose) in truth.iter().enumerate().skip(k0).take(10) {
            if let Some(p) = camera.project_undistorted(&pose.to_camera(x)) {
                if camera.contains(p) {
                    observations.push(Observation {
                        camera: c,
                        point: i,
                        pixel: Point2::new(p.x + 0.5 * rng.gaussian(), p.y + 0.5 * rng.gaussian()),
                    });
                }
            }
        }
    }
    let start_poses: Vec<CameraPose> = truth
        .iter()
        .enumerate()
        .map(|(k, p)| {
            if k == 0 {
                return *p;
            }
            let axis = Vector3::new(rng.gaussian(), rng.gaussian(), rng.gaussian()).normalize();
            CameraPose {
                rotation: Rotation3::new(axis * 0.5f64.to_radians()) * p.rotation,
                centre: p.centre
                    + Vector3::new(rng.gaussian(), rng.gaussian(), rng.gaussian()) * 0.02,
            }
        })
        .collect();
    // 5 % of a point's depth (~3.5 m ahead of the keyframe that first sees it).
    let start_points: Vec<Vector3<f64>> = points
        .iter()
        .map(|x| {
            x + Vector3::new(rng.gaussian(), rng.gaussian(), rng.gaussian())
                * (0.05 * 3.5 / 3f64.sqrt())
        })
        .collect();
    let options = BundleAdjustmentOptions {
        max_iterations: 50,
        ..BundleAdjustmentOptions::default()
    };
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..3 {
        let start = Instant::now();
        let result = bundle_adjust(
            &camera,
            &start_poses,
            &start_points,
            &observations,
            &options,
        )
        .expect("ran");
        times.push(start.elapsed().as_secs_f64());
        last = Some(result);
    }
    times.sort_by(f64::total_cmp);
    let r = last.expect("solved");
    println!(
        "global BA: {keyframes} keyframes, {} points, {} observations: median {:.2} s (min {:.2}, max {:.2}); {} LM iterations, final RMSE {:.3} px, {} outliers, converged {}",
        points.len(),
        observations.len(),
        times[1],
        times[0],
        times[2],
        r.iterations,
        r.rmse_px,
        r.outliers.len(),
        r.converged
    );
}
