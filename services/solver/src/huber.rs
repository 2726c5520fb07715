//! The Huber loss (Huber, "Robust Estimation of a Location Parameter", 1964), as the
//! estimators here use it: quadratic up to `delta`, linear beyond, so that a few wrong
//! observations pull with bounded force. One copy for bundle adjustment, translation
//! averaging and the relative-pose refinement.

/// IRLS weight of a residual of size `r >= 0`: 1 inside `delta`, `delta / r` beyond.
pub(crate) fn weight(r: f64, delta: f64) -> f64 {
    if r <= delta {
        1.0
    } else {
        delta / r
    }
}

/// Cost of a residual of size `r >= 0`: `r^2 / 2` inside `delta`, `delta (r - delta / 2)`
/// beyond (continuous with its slope at `delta`).
pub(crate) fn cost(r: f64, delta: f64) -> f64 {
    if r <= delta {
        0.5 * r * r
    } else {
        delta * (r - 0.5 * delta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quadratic_inside_linear_outside_and_continuous() {
        assert_eq!(weight(0.5, 1.0), 1.0);
        assert_eq!(weight(4.0, 1.0), 0.25);
        assert_eq!(cost(0.5, 1.0), 0.125);
        assert_eq!(cost(3.0, 1.0), 2.5);
        let (below, above) = (cost(1.0 - 1e-9, 1.0), cost(1.0 + 1e-9, 1.0));
        assert!((below - above).abs() < 1e-8);
    }
}
