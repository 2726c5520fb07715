//! Similarity (7-DoF) alignment of corresponding point sets.
//!
//! S. Umeyama, "Least-squares estimation of transformation parameters between two point
//! patterns", IEEE TPAMI 13(4), 1991. Used to compare a monocular trajectory with ground truth
//! (scale is unobservable) and by the merger to chain successive windows (paper, section 5).

use nalgebra::{Matrix3, Rotation3, Vector3};

/// Errors of [`umeyama`].
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AlignmentError {
    /// Fewer than three correspondences: a similarity is not determined.
    #[error("need at least 3 correspondences, got {0}")]
    TooFewPoints(usize),
    /// The two sets have different lengths.
    #[error("point sets differ in length: {0} vs {1}")]
    LengthMismatch(usize, usize),
    /// All source points coincide (zero spread): scale and rotation are undetermined.
    #[error("source points have no spread")]
    Degenerate,
}

/// x -> scale * rotation * x + translation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    pub scale: f64,
    pub rotation: Rotation3<f64>,
    pub translation: Vector3<f64>,
}

impl Similarity {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            scale: 1.0,
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// Maps a point.
    pub fn apply(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.scale * (self.rotation * x) + self.translation
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Self {
        let rinv = self.rotation.inverse();
        Self {
            scale: 1.0 / self.scale,
            rotation: rinv,
            translation: -(rinv * self.translation) / self.scale,
        }
    }

    /// `self ∘ other` (apply `other` first).
    pub fn compose(&self, other: &Self) -> Self {
        Self {
            scale: self.scale * other.scale,
            rotation: self.rotation * other.rotation,
            translation: self.scale * (self.rotation * other.translation) + self.translation,
        }
    }
}

/// The rotation closest to `m` in the Frobenius norm (SVD projection onto SO(3), with the
/// reflection fix). Used for chordal rotation means and Kabsch/Wahba fits: for
/// `m = sum b_i a_i^T` it is the rotation best mapping the `a_i` onto the `b_i`.
pub fn nearest_rotation(m: &Matrix3<f64>) -> Rotation3<f64> {
    let svd = m.svd(true, true);
    match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => {
            let mut d = Matrix3::identity();
            if (u * v_t).determinant() < 0.0 {
                d[(2, 2)] = -1.0;
            }
            Rotation3::from_matrix_unchecked(u * d * v_t)
        }
        _ => Rotation3::identity(),
    }
}

/// Least-squares similarity `T` minimising `sum |dst_i - T(src_i)|^2` (Umeyama 1991), with
/// the reflection fix of the paper so the result is always a proper rotation.
pub fn umeyama(src: &[Vector3<f64>], dst: &[Vector3<f64>]) -> Result<Similarity, AlignmentError> {
    if src.len() != dst.len() {
        return Err(AlignmentError::LengthMismatch(src.len(), dst.len()));
    }
    let n = src.len();
    if n < 3 {
        return Err(AlignmentError::TooFewPoints(n));
    }
    let inv_n = 1.0 / n as f64;
    let mu_s = src.iter().sum::<Vector3<f64>>() * inv_n;
    let mu_d = dst.iter().sum::<Vector3<f64>>() * inv_n;
    let mut sigma = Matrix3::zeros();
    let mut var_s = 0.0;
    for (s, d) in src.iter().zip(dst) {
        let (cs, cd) = (s - mu_s, d - mu_d);
        sigma += cd * cs.transpose();
        var_s += cs.norm_squared();
    }
    sigma *= inv_n;
    var_s *= inv_n;
    if var_s <= f64::EPSILON * (1.0 + mu_s.norm_squared()) {
        return Err(AlignmentError::Degenerate);
    }
    let svd = sigma.svd(true, true);
    let (u, v_t) = match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => (u, v_t),
        _ => return Err(AlignmentError::Degenerate),
    };
    let mut s_fix = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        s_fix[(2, 2)] = -1.0;
    }
    let r = u * s_fix * v_t;
    let trace_ds: f64 = (0..3).map(|i| svd.singular_values[i] * s_fix[(i, i)]).sum();
    let scale = trace_ds / var_s;
    let rotation = Rotation3::from_matrix_unchecked(r);
    let translation = mu_d - scale * (rotation * mu_s);
    Ok(Similarity {
        scale,
        rotation,
        translation,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_known_similarity() {
        let truth = Similarity {
            scale: 2.5,
            rotation: Rotation3::from_euler_angles(0.3, -1.1, 2.0),
            translation: Vector3::new(1.0, -2.0, 0.5),
        };
        let src: Vec<_> = (0..20)
            .map(|i| {
                let t = i as f64;
                Vector3::new(t.sin(), (0.7 * t).cos(), 0.1 * t)
            })
            .collect();
        let dst: Vec<_> = src.iter().map(|p| truth.apply(p)).collect();
        let est = umeyama(&src, &dst).expect("solvable");
        assert!((est.scale - 2.5).abs() < 1e-9);
        assert!((est.translation - truth.translation).norm() < 1e-9);
        assert!(est.rotation.angle_to(&truth.rotation) < 1e-9);
        let round = est.compose(&est.inverse());
        assert!(
            (round.apply(&Vector3::new(3.0, 4.0, 5.0)) - Vector3::new(3.0, 4.0, 5.0)).norm() < 1e-9
        );
    }

    #[test]
    fn rejects_degenerate_input() {
        let p = vec![Vector3::new(1.0, 1.0, 1.0); 5];
        assert_eq!(umeyama(&p, &p), Err(AlignmentError::Degenerate));
        assert_eq!(
            umeyama(&p[..2], &p[..2]),
            Err(AlignmentError::TooFewPoints(2))
        );
        assert_eq!(
            umeyama(&p[..3], &p[..2]),
            Err(AlignmentError::LengthMismatch(3, 2))
        );
    }
}
