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

/// The rotation `R` minimising `sum |R a_i - b_i|^2` over the pairs `(a_i, b_i)` (Kabsch
/// 1976 / Wahba's problem): the bearings of one view turned onto another's. Used by the
/// rotation-only model of a keyframe pair and by placing a frame by rotation.
pub fn rotation_aligning(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> Rotation3<f64> {
    nearest_rotation(
        &pairs
            .iter()
            .map(|(a, b)| b * a.transpose())
            .sum::<Matrix3<f64>>(),
    )
}

/// A bearing pair `(a, b)`: the same point seen from two views.
pub type BearingPair = (Vector3<f64>, Vector3<f64>);

/// [`rotation_aligning`] made robust to the pairs no rotation explains (moving objects,
/// mismatches, parallax): fitted, then twice refitted on the pairs whose `residual` is
/// within 3x the median (at least `floor`). Returns the rotation and the pairs of the last
/// trimming; when that left fewer than 3 pairs the rotation is the one before it and the
/// flag is false. Used by the solver's rotation-only edge model and the readout estimate.
pub fn rotation_aligning_trimmed(
    pairs: &[BearingPair],
    residual: impl Fn(&Rotation3<f64>, &BearingPair) -> f64,
    floor: f64,
) -> (Rotation3<f64>, Vec<BearingPair>, bool) {
    let mut kept = pairs.to_vec();
    let mut r = rotation_aligning(&kept);
    for _ in 0..2 {
        let res: Vec<f64> = pairs.iter().map(|p| residual(&r, p)).collect();
        let cut = 3.0 * crate::median(res.clone()).max(floor);
        kept = pairs
            .iter()
            .zip(&res)
            .filter(|(_, e)| **e <= cut)
            .map(|(p, _)| *p)
            .collect();
        if kept.len() < 3 {
            return (r, kept, false);
        }
        r = rotation_aligning(&kept);
    }
    (r, kept, true)
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

/// Least-squares rigid motion (scale 1) minimising `sum |dst_i - T(src_i)|^2`: Kabsch on
/// the centred points. For trajectories whose scale is known (metric sensors, or to judge
/// a monocular estimate's scale too).
pub fn rigid_alignment(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
) -> Result<Similarity, AlignmentError> {
    if src.len() != dst.len() {
        return Err(AlignmentError::LengthMismatch(src.len(), dst.len()));
    }
    if src.len() < 3 {
        return Err(AlignmentError::TooFewPoints(src.len()));
    }
    let n = src.len() as f64;
    let cs = src.iter().sum::<Vector3<f64>>() / n;
    let cd = dst.iter().sum::<Vector3<f64>>() / n;
    let pairs: Vec<_> = src.iter().zip(dst).map(|(s, d)| (s - cs, d - cd)).collect();
    let rotation = rotation_aligning(&pairs);
    Ok(Similarity {
        scale: 1.0,
        rotation,
        translation: cd - rotation * cs,
    })
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

/// Options of [`umeyama_ransac`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobustAlignmentOptions {
    /// A correspondence is an inlier when `|dst - T(src)|` is below this (destination units).
    pub inlier_threshold: f64,
    /// Minimal-sample iterations (default 200: with 30 % outliers a 3-point sample is clean
    /// with probability 0.34, so 200 draws miss a clean one with probability < 1e-35).
    pub iterations: usize,
    /// Seed of the deterministic sampler (runs are reproducible).
    pub seed: u64,
}

impl Default for RobustAlignmentOptions {
    fn default() -> Self {
        Self {
            inlier_threshold: 0.05,
            iterations: 200,
            seed: 1,
        }
    }
}

/// Umeyama in RANSAC (Fischler and Bolles 1981): similarities from random 3-point samples,
/// the one with the most inliers refitted on all of its inliers. Returns the transform and
/// the inlier mask.
pub fn umeyama_ransac(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    options: &RobustAlignmentOptions,
) -> Result<(Similarity, Vec<bool>), AlignmentError> {
    if src.len() != dst.len() {
        return Err(AlignmentError::LengthMismatch(src.len(), dst.len()));
    }
    let n = src.len();
    if n < 3 {
        return Err(AlignmentError::TooFewPoints(n));
    }
    let mut state = options.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut draw = move |bound: usize| {
        // xorshift64*: small, deterministic, good enough for sampling indices.
        state ^= state >> 12;
        state ^= state << 25;
        state ^= state >> 27;
        (state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 33) as usize % bound
    };
    let inliers_of = |t: &Similarity| -> Vec<bool> {
        src.iter()
            .zip(dst)
            .map(|(s, d)| (t.apply(s) - d).norm() < options.inlier_threshold)
            .collect()
    };
    let mut best: Option<(usize, Vec<bool>)> = None;
    for _ in 0..options.iterations {
        let (a, b, c) = (draw(n), draw(n), draw(n));
        if a == b || b == c || a == c {
            continue;
        }
        let Ok(t) = umeyama(&[src[a], src[b], src[c]], &[dst[a], dst[b], dst[c]]) else {
            continue;
        };
        let mask = inliers_of(&t);
        let count = mask.iter().filter(|m| **m).count();
        if best.as_ref().is_none_or(|(c, _)| count > *c) {
            best = Some((count, mask));
        }
    }
    let (_, mask) = best.ok_or(AlignmentError::Degenerate)?;
    let pick = |v: &[Vector3<f64>], m: &[bool]| {
        v.iter()
            .zip(m)
            .filter(|(_, k)| **k)
            .map(|(x, _)| *x)
            .collect::<Vec<_>>()
    };
    let refit = umeyama(&pick(src, &mask), &pick(dst, &mask))?;
    let mask = inliers_of(&refit);
    let refit = umeyama(&pick(src, &mask), &pick(dst, &mask))?;
    Ok((refit, mask))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rigid_alignment_recovers_rotation_and_translation_and_keeps_the_scale() {
        let truth = Similarity {
            scale: 1.0,
            rotation: Rotation3::from_euler_angles(0.2, -0.4, 1.1),
            translation: Vector3::new(1.0, -2.0, 0.5),
        };
        let src: Vec<Vector3<f64>> = (0..10)
            .map(|i| {
                let t = f64::from(i);
                Vector3::new(t.cos(), t.sin() * 2.0, 0.3 * t)
            })
            .collect();
        let dst: Vec<Vector3<f64>> = src.iter().map(|p| truth.apply(p)).collect();
        let fit = rigid_alignment(&src, &dst).expect("fit");
        assert_eq!(fit.scale, 1.0);
        assert!((fit.rotation.matrix() - truth.rotation.matrix()).norm() < 1e-12);
        assert!((fit.translation - truth.translation).norm() < 1e-12);
        // Twice as large a trajectory is not shrunk to fit.
        let big: Vec<Vector3<f64>> = src.iter().map(|p| truth.apply(&(p * 2.0))).collect();
        let fit = rigid_alignment(&src, &big).expect("fit");
        let residual: f64 = src
            .iter()
            .zip(&big)
            .map(|(s, d)| (fit.apply(s) - d).norm())
            .sum();
        assert!(residual > 1.0, "{residual}");
        assert!(matches!(
            rigid_alignment(&src[..2], &dst[..2]),
            Err(AlignmentError::TooFewPoints(2))
        ));
    }

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
    fn robust_fit_ignores_thirty_percent_outliers() {
        let truth = Similarity {
            scale: 0.7,
            rotation: Rotation3::from_euler_angles(-0.4, 0.9, 0.2),
            translation: Vector3::new(-3.0, 1.0, 2.0),
        };
        let src: Vec<_> = (0..100)
            .map(|i| {
                let t = i as f64;
                Vector3::new(
                    (1.3 * t).sin() * 4.0,
                    (0.7 * t).cos() * 3.0,
                    5.0 + (0.3 * t).sin() * 2.0,
                )
            })
            .collect();
        let mut dst: Vec<_> = src.iter().map(|p| truth.apply(p)).collect();
        // 30 % gross outliers, and 1 mm noise on the rest.
        for (i, d) in dst.iter_mut().enumerate() {
            if i % 10 < 3 {
                *d += Vector3::new(1.5, -2.0, 0.7 * (i as f64).cos());
            } else {
                *d += Vector3::new(1e-3 * (i as f64).sin(), 1e-3 * (i as f64).cos(), 0.0);
            }
        }
        let plain = umeyama(&src, &dst).expect("fits");
        assert!(
            (plain.scale - 0.7).abs() > 0.01,
            "the outliers do bias a plain fit"
        );
        let options = RobustAlignmentOptions {
            inlier_threshold: 0.02,
            ..RobustAlignmentOptions::default()
        };
        let (robust, mask) = umeyama_ransac(&src, &dst, &options).expect("fits");
        assert!((robust.scale - 0.7).abs() < 1e-3, "scale {}", robust.scale);
        assert!(robust.rotation.angle_to(&truth.rotation) < 1e-3);
        assert!((robust.translation - truth.translation).norm() < 5e-3);
        assert_eq!(mask.iter().filter(|m| !**m).count(), 30);
        // Noiseless: exact.
        let clean: Vec<_> = src.iter().map(|p| truth.apply(p)).collect();
        let (exact, _) = umeyama_ransac(&src, &clean, &options).expect("fits");
        assert!(
            (exact.scale - 0.7).abs() < 1e-12
                && (exact.translation - truth.translation).norm() < 1e-9
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
