//! Relative pose of two keyframes from their shared tracks.
//!
//! Nistér, "An Efficient Solution to the Five-Point Relative Pose Problem", TPAMI 2004, in
//! OpenCV's USAC (Raguram et al., "USAC: A Universal Framework for Random Sample Consensus",
//! TPAMI 2013; `USAC_FAST`: half the time of plain RANSAC on KITTI windows, same accuracy)
//! on normalised, undistorted coordinates, or (`estimator`) the own five-point solver in
//! LO-RANSAC ([`crate::essential_ransac`]); the essential matrix is decomposed here
//! ([`crate::essential_decomposition`]), which is 50x cheaper than `recoverPose`. The
//! RANSAC fits on 200 matches; rotation and direction can then be refined on every inlier
//! ([`crate::essential_refinement`], off by default).
//! Egocentric video often turns the head without moving it; then the essential matrix is
//! degenerate (its rotation unreliable, its translation noise). Each edge is
//! therefore also fitted with a rotation-only model (Kabsch on bearings, trimmed), and the
//! median residual of that model (the parallax no rotation can explain; model selection in
//! the spirit of Torr's GRIC and ORB-SLAM's homography/fundamental test) decides:
//! - residual >= `min_parallax_px`: the five-point rotation and translation direction are
//!   used, weighted by the inlier count;
//! - below: the rotation-only estimate is used and the edge carries no translation
//!   direction (translation weight 0), as the paper's treatment of low-parallax pairs.

use crate::essential_decomposition::decompose_essential;
use crate::essential_ransac::{
    estimate_essential, homogeneous_pairs, matches_near, EssentialRansacOptions,
};
use crate::essential_refinement::{refine_relative_pose, skew, EssentialRefinementOptions};
use egoslam_geometry::{median, rotation_aligning_trimmed};
use nalgebra::{Matrix3, Rotation3, Vector3};
use opencv::core::{Mat, Point2d, Vector};
use opencv::prelude::*;

/// Options; defaults with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativePoseOptions {
    /// Fewest shared tracks to attempt an edge (default 30: the five-point RANSAC needs a
    /// margin over 5, and fewer matches between keyframes mean the view is mostly lost).
    pub min_matches: usize,
    /// RANSAC inlier threshold, pixels (default 1.0: LK tracks are sub-pixel accurate).
    /// It is the threshold handed to OpenCV and the one the edge's inliers are counted at
    /// (Sampson distance), but OpenCV 4.6's USAC scores its models at half of it: on 200
    /// matches with 1 px noise its inlier mask at 1.0 and 2.0 held exactly the matches
    /// within 0.5 and 1.0 px of Sampson distance (95 and 146). The strict scoring is what
    /// costs the time (~200 iterations at 1 px noise) and what the accuracy rests on:
    /// handing USAC 2.0 while still counting at 1.0 cut the relative-pose stage of KITTI
    /// windows ~100 -> 45 ms, but took the seed-4 walk's windows from 0.26 to 0.42 % of
    /// their path (mean; worst 1.5 -> 5.8 %); 1.4 was in between, 0.7 no better than 1.0.
    /// A 2 px threshold for both had cut the window bench's stage 453 -> 149 ms
    /// (synthetic) and 124 -> 55 ms (KITTI) and broke a walk's scale (docs/solver.md,
    /// "Relative pose refinement").
    pub ransac_threshold_px: f64,
    /// A rotation-only edge counts the matches its rotation explains within this many
    /// pixels, or within 3x its median residual if larger (default 2.0: twice the LK
    /// track noise).
    pub rotation_agreement_px: f64,
    /// Huber threshold of the refinement and the inlier count of a refined edge, pixels
    /// (default 1.0, the RANSAC's; kept apart so a looser RANSAC can be tried).
    pub inlier_threshold_px: f64,
    /// Matches within this many pixels of the model enter the refinement (default 3.0:
    /// three times the track noise, so the gate does not cut the noise's tail on one
    /// side of a slightly wrong model).
    pub refine_gate_px: f64,
    /// RANSAC confidence (default 0.99: a third faster than OpenCV's 0.999 on KITTI windows,
    /// with ATE changes inside run-to-run noise on TUM and KITTI).
    pub ransac_confidence: f64,
    /// Median residual of the best rotation-only fit below which the translation direction
    /// is not trusted, pixels (default 2.0: twice the LK track noise; below it a pure
    /// rotation explains the matches and the five-point translation is noise).
    pub min_parallax_px: f64,
    /// Fewest RANSAC inliers for a usable edge (default 20).
    pub min_inliers: usize,
    /// Matches given to the five-point RANSAC, evenly strided (default 200); inliers are
    /// then counted over all matches.
    pub ransac_points: usize,
    /// Refine rotation and direction on every inlier by the robust Sampson error
    /// ([`crate::essential_refinement`]). Default false: it lowers the median edge
    /// rotation error (rendered walks 0.08-0.12 -> 0.02-0.05 deg, KITTI 0.127 -> 0.106
    /// deg), but windows after bundle adjustment did not follow, and KITTI without motion
    /// prediction went 0.41 -> 0.61 m keyframe ATE (docs/solver.md).
    pub refine: bool,
    /// The five-point RANSAC (default [`EssentialEstimator::OpenCvUsac`]: the own LO-RANSAC
    /// at the same scoring threshold is as accurate per edge and no faster through the
    /// pipeline, and moves single long walks either way; docs/solver.md, "Own five-point
    /// RANSAC").
    pub estimator: EssentialEstimator,
    /// Scoring threshold of [`EssentialEstimator::LoRansac`] on the Sampson distance,
    /// pixels (default 0.5: where OpenCV's USAC scores at our 1 px. At 1 px its windows of
    /// a rendered 1500-frame walk went from 0.23 to 0.39 % of their path (mean; worst 1.2
    /// -> 8.3 %): near-degenerate edges of 2-6 px parallax take a wrong model).
    pub lo_ransac_threshold_px: f64,
    /// Local optimisation of [`EssentialEstimator::LoRansac`]'s best models (default true;
    /// without it its windows and walks score as in docs/solver.md's last column).
    pub lo_ransac_local_optimization: bool,
}

/// Which five-point RANSAC fits an edge's essential matrix.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EssentialEstimator {
    /// OpenCV's `findEssentialMat` with `USAC_FAST`.
    OpenCvUsac,
    /// Own five-point solver in LO-RANSAC ([`crate::essential_ransac`]).
    LoRansac,
}

impl Default for RelativePoseOptions {
    fn default() -> Self {
        Self {
            min_matches: 30,
            ransac_threshold_px: 1.0,
            rotation_agreement_px: 2.0,
            inlier_threshold_px: 1.0,
            refine_gate_px: 3.0,
            ransac_confidence: 0.99,
            min_parallax_px: 2.0,
            min_inliers: 20,
            ransac_points: 200,
            refine: false,
            estimator: EssentialEstimator::OpenCvUsac,
            lo_ransac_threshold_px: 0.5,
            lo_ransac_local_optimization: true,
        }
    }
}

/// A measured edge `x_j = R x_i + t` (camera i to camera j).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativePose {
    pub rotation: Rotation3<f64>,
    /// Unit translation direction in camera j; meaningful only when `has_translation`.
    pub translation: Vector3<f64>,
    pub has_translation: bool,
    pub inliers: usize,
    pub matches: usize,
    /// Median residual of the rotation-only fit, pixels (the parallax).
    pub parallax_px: f64,
}

/// Why an edge was not made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RelativePoseError {
    #[error("only {0} shared tracks")]
    TooFewMatches(usize),
    #[error("only {0} inliers")]
    TooFewInliers(usize),
    #[error("OpenCV: {0}")]
    OpenCv(String),
}

fn angle(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.normalize().dot(&b.normalize()).clamp(-1.0, 1.0).acos()
}

/// Rotation-only fit, trimmed twice to the matches within 3x the median residual, and the
/// median residual (radians) of the matches it kept.
fn rotation_only(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> (Rotation3<f64>, f64) {
    let (r, kept, _) = rotation_aligning_trimmed(pairs, |r, (bi, bj)| angle(&(r * bi), bj), 1e-6);
    let res: Vec<f64> = kept.iter().map(|(bi, bj)| angle(&(r * bi), bj)).collect();
    (r, median(res))
}

/// OpenCV's five-point USAC on the sampled matches.
fn opencv_essential(
    points_i: &[(f64, f64)],
    points_j: &[(f64, f64)],
    threshold: f64,
    options: &RelativePoseOptions,
) -> Result<Matrix3<f64>, RelativePoseError> {
    let cv = |e: opencv::Error| RelativePoseError::OpenCv(e.to_string());
    let p1: Vector<Point2d> = points_i.iter().map(|&(x, y)| Point2d::new(x, y)).collect();
    let p2: Vector<Point2d> = points_j.iter().map(|&(x, y)| Point2d::new(x, y)).collect();
    let k =
        Mat::from_slice_2d(&[[1.0f64, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]).map_err(cv)?;
    let mut mask = Mat::default();
    let e = opencv::calib3d::find_essential_mat(
        &p1,
        &p2,
        &k,
        opencv::calib3d::USAC_FAST,
        options.ransac_confidence,
        threshold,
        1000,
        &mut mask,
    )
    .map_err(cv)?;
    if e.rows() < 3 {
        return Err(RelativePoseError::TooFewInliers(0));
    }
    let essential = Matrix3::from_fn(|r, c| {
        e.at_2d::<f64>(r as i32, c as i32)
            .copied()
            .unwrap_or(f64::NAN)
    });
    if !essential.iter().all(|v| v.is_finite()) {
        return Err(RelativePoseError::OpenCv(
            "findEssentialMat returned no matrix".into(),
        ));
    }
    Ok(essential)
}

/// Estimates the edge from normalised coordinates `(x/z, y/z)` of the shared tracks in
/// keyframes i and j; `focal_px` converts the pixel threshold.
pub fn estimate_relative_pose(
    points_i: &[(f64, f64)],
    points_j: &[(f64, f64)],
    focal_px: f64,
    options: &RelativePoseOptions,
) -> Result<RelativePose, RelativePoseError> {
    let n = points_i.len().min(points_j.len());
    if n < options.min_matches {
        return Err(RelativePoseError::TooFewMatches(n));
    }
    // The rotation-only model first: an edge without parallax is decided by it alone, and
    // the five-point RANSAC (most of a window's solve time) is not run for it. Half of
    // TUM fr1_rpy's edges are such.
    let bearing = |&(x, y): &(f64, f64)| Vector3::new(x, y, 1.0).normalize();
    let all_pairs: Vec<(Vector3<f64>, Vector3<f64>)> = (0..n)
        .map(|m| (bearing(&points_i[m]), bearing(&points_j[m])))
        .collect();
    let (rotation_r, parallax) = rotation_only(&all_pairs);
    let parallax_px = parallax * focal_px;
    // The matches the rotation explains within the agreement threshold.
    let agreeing = || {
        let thr = options.rotation_agreement_px / focal_px;
        all_pairs
            .iter()
            .filter(|(bi, bj)| angle(&(rotation_r * bi), bj) < thr.max(parallax * 3.0))
            .count()
    };
    if parallax_px < options.min_parallax_px {
        let agree = agreeing();
        if agree < options.min_inliers {
            return Err(RelativePoseError::TooFewInliers(agree));
        }
        return Ok(RelativePose {
            rotation: rotation_r,
            translation: Vector3::zeros(),
            has_translation: false,
            inliers: agree,
            matches: n,
            parallax_px,
        });
    }
    // RANSAC on at most `ransac_points` evenly strided matches: the five-point hypotheses
    // are as good, and scoring cost is linear in the points (measured 1.3-5 ms per edge on
    // 300-700 KITTI matches, a third of that on 200).
    let stride = n.div_ceil(options.ransac_points.max(8));
    let sample: Vec<usize> = (0..n).step_by(stride.max(1)).collect();
    let sample_i: Vec<(f64, f64)> = sample.iter().map(|&m| points_i[m]).collect();
    let sample_j: Vec<(f64, f64)> = sample.iter().map(|&m| points_j[m]).collect();
    let threshold = options.ransac_threshold_px / focal_px;
    let essential = match options.estimator {
        EssentialEstimator::OpenCvUsac => {
            opencv_essential(&sample_i, &sample_j, threshold, options)?
        }
        EssentialEstimator::LoRansac => {
            estimate_essential(
                &sample_i,
                &sample_j,
                &EssentialRansacOptions {
                    threshold: options.lo_ransac_threshold_px / focal_px,
                    confidence: options.ransac_confidence,
                    local_optimization: options.lo_ransac_local_optimization,
                    ..Default::default()
                },
            )
            .ok_or(RelativePoseError::TooFewInliers(0))?
            .essential
        }
    };
    let inlier_idx = matches_near(&essential, points_i, points_j, threshold);
    let (rotation_e, t) = decompose_essential(&essential, points_i, points_j, &inlier_idx)
        .ok_or_else(|| {
            RelativePoseError::OpenCv("essential matrix has no valid decomposition".into())
        })?;
    let (rotation_e, t, inliers) = if options.refine {
        let inlier_threshold = options.inlier_threshold_px / focal_px;
        let gate = options.refine_gate_px / focal_px;
        let (mut r, mut t) = (rotation_e, t);
        // Matches are gated around the current model, wider than the noise: gated at the
        // noise level, the set leans toward the model that chose it and the refinement
        // cannot leave it. Twice: the second gate is around the refined model.
        for _ in 0..2 {
            let model = skew(&t) * r.matrix();
            let near = matches_near(&model, points_i, points_j, gate);
            let pairs = homogeneous_pairs(points_i, points_j, &near);
            (r, t) = refine_relative_pose(
                r,
                t,
                &pairs,
                &EssentialRefinementOptions {
                    huber: inlier_threshold,
                    ..Default::default()
                },
            );
        }
        let refined = skew(&t) * r.matrix();
        let inliers = matches_near(&refined, points_i, points_j, inlier_threshold).len();
        (r, t, inliers)
    } else {
        (rotation_e, t, inlier_idx.len())
    };
    if inliers < options.min_inliers {
        // Parallax without a supported essential matrix: no edge.
        return Err(RelativePoseError::TooFewInliers(inliers.max(agreeing())));
    }
    Ok(RelativePose {
        rotation: rotation_e,
        translation: if t.norm() > 0.0 { t.normalize() } else { t },
        has_translation: true,
        inliers,
        matches: n,
        parallax_px,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::noisy_matches;
    use rand::rngs::StdRng;
    use rand::SeedableRng;

    fn scene() -> Vec<Vector3<f64>> {
        (0..200)
            .map(|k| {
                let a = k as f64;
                Vector3::new(
                    (a * 0.37).sin() * 3.0,
                    (a * 0.11).cos() * 2.0,
                    4.0 + (a * 0.53).sin().abs() * 6.0,
                )
            })
            .collect()
    }

    fn normalised(r: &Rotation3<f64>, t: &Vector3<f64>, x: &Vector3<f64>) -> (f64, f64) {
        let p = r * x + t;
        (p.x / p.z, p.y / p.z)
    }

    #[test]
    fn translating_pair_gives_rotation_and_direction() {
        let pts = scene();
        let r = Rotation3::from_euler_angles(0.02, -0.05, 0.01);
        let t = Vector3::new(0.3, 0.0, 0.1);
        let a: Vec<_> = pts.iter().map(|x| (x.x / x.z, x.y / x.z)).collect();
        let b: Vec<_> = pts.iter().map(|x| normalised(&r, &t, x)).collect();
        let e =
            estimate_relative_pose(&a, &b, 500.0, &RelativePoseOptions::default()).expect("edge");
        assert!(e.has_translation, "{e:?}");
        assert!(
            e.rotation.angle_to(&r) < 1e-4,
            "rotation error {} rad",
            e.rotation.angle_to(&r)
        );
        assert!(angle(&e.translation, &t) < 1e-3, "{:?}", e.translation);
        assert!(e.parallax_px > 2.0);
    }

    #[test]
    fn refinement_uses_every_match() {
        // 1 px noise on 1000 matches; the RANSAC fits on 200 of them.
        let r = Rotation3::from_euler_angles(0.01, 0.05, 0.01);
        let t = Vector3::new(0.1, 0.02, 0.3);
        let matches = noisy_matches(&mut StdRng::seed_from_u64(11), 1000, (&r, &t), 1.0, 520.0);
        let (a, b): (Vec<_>, Vec<_>) = matches
            .iter()
            .map(|(x, y)| ((x.x, x.y), (y.x, y.y)))
            .unzip();
        let error = |refine: bool| {
            let options = RelativePoseOptions {
                refine,
                ..Default::default()
            };
            let e = estimate_relative_pose(&a, &b, 520.0, &options).expect("edge");
            (e.rotation.angle_to(&r).to_degrees(), e.inliers)
        };
        let ((plain, plain_inliers), (refined, refined_inliers)) = (error(false), error(true));
        // Measured: 0.48 deg from the RANSAC alone, 0.04 refined.
        assert!(refined < 0.06, "refined rotation {refined} deg off");
        assert!(refined < plain, "{refined} deg refined, {plain} deg not");
        assert!(refined_inliers >= plain_inliers * 9 / 10);
    }

    #[test]
    fn pure_rotation_keeps_rotation_without_direction() {
        let pts = scene();
        let r = Rotation3::from_euler_angles(0.1, 0.05, -0.08);
        let a: Vec<_> = pts.iter().map(|x| (x.x / x.z, x.y / x.z)).collect();
        let b: Vec<_> = pts
            .iter()
            .map(|x| normalised(&r, &Vector3::zeros(), x))
            .collect();
        let e =
            estimate_relative_pose(&a, &b, 500.0, &RelativePoseOptions::default()).expect("edge");
        assert!(!e.has_translation);
        assert!(e.rotation.angle_to(&r) < 1e-6);
        assert!(matches!(
            estimate_relative_pose(&a[..10], &b[..10], 500.0, &RelativePoseOptions::default()),
            Err(RelativePoseError::TooFewMatches(10))
        ));
    }

    #[test]
    fn the_own_ransac_is_as_accurate_as_opencvs_on_noisy_edges() {
        use rand::Rng;
        // 60 edges of 600 matches, 0.7 or 1.5 px noise, one match in seven moved off.
        let errors = |estimator: EssentialEstimator| {
            let mut rng = StdRng::seed_from_u64(5);
            let (mut rotation, mut direction) = (Vec::new(), Vec::new());
            for k in 0..60 {
                let r = Rotation3::from_euler_angles(
                    rng.random_range(-0.1..0.1),
                    rng.random_range(-0.2..0.2),
                    rng.random_range(-0.1..0.1),
                );
                let t = Vector3::new(
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.1..0.1),
                    rng.random_range(-0.3..0.3),
                );
                let noise = if k % 2 == 0 { 0.7 } else { 1.5 };
                let mut matches = noisy_matches(&mut rng, 600, (&r, &t), noise, 500.0);
                for m in (0..600).step_by(7) {
                    matches[m].1.x += rng.random_range(-0.05..0.05);
                }
                let (a, b): (Vec<_>, Vec<_>) = matches
                    .iter()
                    .map(|(x, y)| ((x.x, x.y), (y.x, y.y)))
                    .unzip();
                let options = RelativePoseOptions {
                    estimator,
                    ..Default::default()
                };
                if let Ok(e) = estimate_relative_pose(&a, &b, 500.0, &options) {
                    if e.has_translation {
                        rotation.push(e.rotation.angle_to(&r).to_degrees());
                        direction.push(angle(&e.translation, &t).to_degrees());
                    }
                }
            }
            (median(rotation), median(direction))
        };
        let (own_rotation, own_direction) = errors(EssentialEstimator::LoRansac);
        let (opencv_rotation, opencv_direction) = errors(EssentialEstimator::OpenCvUsac);
        // Measured: rotation 0.25 deg (OpenCV 0.26), direction 3.9 deg (OpenCV 6.4).
        assert!(
            own_rotation < 1.1 * opencv_rotation,
            "{own_rotation} deg, OpenCV {opencv_rotation}"
        );
        assert!(
            own_direction < 1.1 * opencv_direction,
            "{own_direction} deg, OpenCV {opencv_direction}"
        );
    }
}
