//! Helpers shared by the unit tests of the estimators.

use nalgebra::{Rotation3, Vector3};
use rand::Rng;

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
