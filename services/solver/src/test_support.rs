//! Helpers shared by the unit tests of the estimators.

use rand::Rng;

/// A standard normal sample (Box-Muller), so the tests need only `rand`.
pub fn gaussian(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}
