//! Helpers shared by the unit tests of the estimators.

use crate::triangulation::CameraPose;
use crate::view_graph::KeyframeObservations;
use egoslam_geometry::PinholeRadtan;
use nalgebra::{Point2, Rotation3, Vector3};
use rand::rngs::StdRng;
use rand::Rng;
use std::collections::BTreeMap;

/// A standard normal sample (Box-Muller), so the tests need only `rand`.
pub fn gaussian(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// `n` matches of random points 3-15 m ahead seen from the origin and from the camera
/// `x_j = r x_i + t`: homogeneous normalised coordinates `(x_i, x_j)` (third entry 1), with
/// Gaussian noise of `noise_px` pixels at focal length `focal_px` on every coordinate.
pub fn noisy_matches(
    rng: &mut impl Rng,
    n: usize,
    (r, t): (&Rotation3<f64>, &Vector3<f64>),
    noise_px: f64,
    focal_px: f64,
) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    (0..n)
        .map(|_| {
            let x = Vector3::new(
                rng.random_range(-6.0..6.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(3.0..15.0),
            );
            let y = r * x + t;
            let mut noisy = |p: Vector3<f64>| {
                let mut q = p / p.z;
                q.x += gaussian(rng) * noise_px / focal_px;
                q.y += gaussian(rng) * noise_px / focal_px;
                q
            };
            (noisy(x), noisy(y))
        })
        .collect()
}

/// The 640x480 pinhole camera of the synthetic windows.
pub fn camera() -> PinholeRadtan {
    PinholeRadtan::new(640, 480, [520.0, 520.0, 320.0, 240.0], [0.0; 5]).expect("camera")
}

/// A head walking forward and looking around, 20 keyframes.
pub fn head_poses() -> Vec<CameraPose> {
    (0..20)
        .map(|i| {
            let t = i as f64;
            CameraPose {
                rotation: Rotation3::from_euler_angles(
                    0.03 * (0.7 * t).sin(),
                    0.12 * (0.3 * t).sin(),
                    0.02 * t.cos(),
                ),
                centre: Vector3::new(0.03 * (0.5 * t).sin(), 0.01 * t.cos(), 0.08 * t),
            }
        })
        .collect()
}

pub fn random_points(rng: &mut StdRng, n: usize) -> Vec<Vector3<f64>> {
    (0..n)
        .map(|_| {
            Vector3::new(
                rng.random_range(-6.0..6.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(3.0..15.0),
            )
        })
        .collect()
}

/// Tracks of every visible point in every keyframe, with Gaussian pixel noise `sigma`.
pub fn observe(
    poses: &[CameraPose],
    points: &[Vector3<f64>],
    sigma: f64,
    rng: &mut StdRng,
) -> Vec<KeyframeObservations> {
    let camera = camera();
    poses
        .iter()
        .enumerate()
        .map(|(k, pose)| {
            let mut tracks = BTreeMap::new();
            for (id, x) in points.iter().enumerate() {
                if let Some(p) = camera.project_undistorted(&pose.to_camera(x)) {
                    if camera.contains(p) {
                        tracks.insert(
                            id as u64,
                            Point2::new(p.x + sigma * gaussian(rng), p.y + sigma * gaussian(rng)),
                        );
                    }
                }
            }
            KeyframeObservations {
                id: k as u64,
                timestamp: k as f64 * 0.2,
                tracks,
            }
        })
        .collect()
}
