//! Focal-length self-calibration from the first windows of a recording.
//!
//! The paper's window bundle adjustment may refine a focal scale and one radial term (its
//! 7-parameter camera, section 4), as COLMAP and GLOMAP refine the focal length by default.
//! The pipeline keeps one calibration for every process, so instead of letting each window
//! drift to its own focal length, the first windows of a recording are solved with the
//! intrinsics free and their focal scales pooled: the median, applied only when it differs
//! from the calibration clearly (by `min_correction` and by `min_significance` standard
//! errors of the median) and plausibly (within `max_correction`).
//!
//! The same windows, solved with the focal held and the radial term free, measure a
//! radial distortion the calibration leaves ([`estimate_radial_term`]; rectified KITTI
//! images keep a pincushion of k ~0.01-0.03 that the ground-truth poses confirm).
//!
//! Why: a focal length a few percent off bends a monocular map into a scale drift that no
//! later stage undoes. Measured on kitti_odometry_00 (every window of the run, solved
//! with the intrinsics free): focal scales 0.962-0.982 in all six windows; the pipeline's
//! keyframe ATE with the calibration scaled by 0.97 / 0.98 / 1.0 / 1.02 was 0.29 / 0.32 /
//! 0.48 / 0.68 m. On a rendered walk with its exact focal the six windows gave
//! 0.991-1.012 (nothing to correct); told a focal 3 % too long, 0.963-0.983 (the truth:
//! 0.971).

use crate::view_graph::{EdgeCache, KeyframeObservations};
use crate::window_solver::{solve_window, WindowSolution, WindowSolverOptions, WindowStatus};
use crate::windowing::{WindowBuilder, WindowOptions, WindowOptionsError};
use egoslam_geometry::PinholeRadtan;

/// The frames of a recording whose keyframes the estimates are made from (300: 10 s at
/// 30 fps, 30 s of KITTI's 10 fps; enough keyframes for the 3-8 windows pooled on every
/// sequence here).
pub const FIRST_FRAMES: usize = 300;

/// Options; defaults with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FocalCalibrationOptions {
    /// Keyframes per window (default 20, the solver's: the estimate is of the windows the
    /// run will solve).
    pub window: usize,
    /// Keyframes consecutive windows share (default 5, the solver's).
    pub overlap: usize,
    /// Most windows solved (default 8: bounds the pre-pass, 1.8-3.4 s in all in the dev
    /// build on six inputs; the spread of six KITTI windows was already 0.003 about their
    /// median).
    pub max_windows: usize,
    /// Fewest windows solved with translation whose scales are pooled (default 3: a
    /// median of fewer is one window's word). Rotation-only windows carry no focal
    /// information the bundle adjustment uses.
    pub min_windows: usize,
    /// Smallest correction applied, as a fraction (default 0.01: windows of a rendered walk
    /// with the exact focal scatter 0.99-1.01, and under 1 % the map hardly moves).
    pub min_correction: f64,
    /// The correction must exceed this many standard errors of the median (1.4826 x MAD /
    /// sqrt(n)) (default 2).
    pub min_significance: f64,
    /// Largest correction believed, as a fraction (default 0.2): a calibration that far off
    /// is the wrong file or the wrong resolution, which a focal scale should not hide.
    pub max_correction: f64,
    /// Smallest radial term applied ([`estimate_radial_term`]; default 0.005: at the corner
    /// of a 65 deg view, r^2 = 0.64, it moves a point 0.3 % of its distance from the
    /// centre, ~1 px at VGA; on rendered walks, which have no distortion, the windows'
    /// medians came within 0.0012 of 0, single windows up to 0.019).
    pub min_radial_correction: f64,
    /// Largest radial term believed (default 0.1: 6 % at such a corner, a lens the
    /// calibration did not describe at all, which a residual term should not hide).
    pub max_radial_correction: f64,
    /// The radial term must exceed this many standard errors of the median (default 3,
    /// stricter than the focal's 2: `egoslam run` estimates it by default for a
    /// calibration without distortion terms, and a term applied wrongly bends every map of
    /// that camera: tum_fr1_rpy's five windows gave -0.0076 at 1.97 standard errors, and
    /// applied it took that sequence from 1.97 to 3.02 cm, while kitti_odometry_00's six
    /// gave 0.0135 at 3.4, which took it from 0.479 to 0.246 m).
    pub min_radial_significance: f64,
}

impl Default for FocalCalibrationOptions {
    fn default() -> Self {
        Self {
            window: 20,
            overlap: 5,
            max_windows: 8,
            min_windows: 3,
            min_correction: 0.01,
            min_significance: 2.0,
            max_correction: 0.2,
            min_radial_correction: 0.005,
            max_radial_correction: 0.1,
            min_radial_significance: 3.0,
        }
    }
}

/// What the windows said.
#[derive(Debug, Clone, PartialEq)]
pub struct FocalEstimate {
    /// Median focal scale (focal length over the calibrated one).
    pub scale: f64,
    /// Each window's scale, in order (windows solved with translation only).
    pub per_window: Vec<f64>,
    /// Standard error of the median, 1.4826 x MAD / sqrt(n).
    pub standard_error: f64,
    /// Whether the correction is clear enough to apply (`min_correction`,
    /// `min_significance`).
    pub significant: bool,
}

impl FocalEstimate {
    /// The scale to apply: the estimate when significant, else 1.
    pub fn applied(&self) -> f64 {
        if self.significant {
            self.scale
        } else {
            1.0
        }
    }
}

/// What the first windows said about a radial distortion the calibration leaves
/// ([`estimate_radial_term`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RadialEstimate {
    /// Median radial term, `k` of `(1 + k r^2)` on the calibration's undistorted
    /// normalized coordinates (to first order, what adds to the calibration's `k1`).
    pub k: f64,
    /// Each window's term, in order (windows solved with translation only).
    pub per_window: Vec<f64>,
    /// Standard error of the median, 1.4826 x MAD / sqrt(n).
    pub standard_error: f64,
    /// Whether the term is clear enough to apply (`min_radial_correction`,
    /// `min_radial_significance`).
    pub significant: bool,
}

impl RadialEstimate {
    /// The term to apply: the estimate when significant, else 0.
    pub fn applied(&self) -> f64 {
        if self.significant {
            self.k
        } else {
            0.0
        }
    }
}

/// Why no focal (or radial) estimate was made.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum FocalCalibrationError {
    /// Too few windows had translation (a still or rotating start, or a short input).
    #[error("only {solved} windows solved with translation (need {needed})")]
    TooFewWindows { solved: usize, needed: usize },
    /// The windows agree on a focal length too far from the calibration's to be believed.
    #[error("the windows put the focal length at {scale:.3}x the calibration's: check the calibration file and the image size")]
    Implausible { scale: f64 },
    /// The windows agree on a radial distortion too strong to be a residual of the
    /// calibration.
    #[error("the windows find a radial distortion k = {k:.3} the calibration does not describe: check the calibration's distortion")]
    ImplausibleRadial { k: f64 },
    /// The window size and overlap do not make windows (`WindowBuilder::new`).
    #[error(transparent)]
    Windows(#[from] WindowOptionsError),
}

/// Solves the first windows of `keyframes` with the focal length and a radial term free
/// and pools their focal scales (module doc).
pub fn estimate_focal_scale(
    camera: &PinholeRadtan,
    keyframes: &[KeyframeObservations],
    options: &FocalCalibrationOptions,
    solver: &WindowSolverOptions,
) -> Result<FocalEstimate, FocalCalibrationError> {
    let _span = tracing::debug_span!("focal_calibration", keyframes = keyframes.len()).entered();
    let terms = first_window_terms(Intrinsic::Focal, camera, keyframes, options, solver)?;
    pool_focal_scales(terms, options)
}

/// The focal estimate of the windows' scales (`per_window`, in order).
pub fn pool_focal_scales(
    per_window: Vec<f64>,
    options: &FocalCalibrationOptions,
) -> Result<FocalEstimate, FocalCalibrationError> {
    let (scale, standard_error) = pooled(&per_window, options)?;
    if scale.ln().abs() > (1.0 + options.max_correction).ln() {
        return Err(FocalCalibrationError::Implausible { scale });
    }
    let correction = (scale - 1.0).abs();
    let significant = correction >= options.min_correction
        && correction >= options.min_significance * standard_error;
    Ok(FocalEstimate {
        scale,
        per_window,
        standard_error,
        significant,
    })
}

/// Solves the first windows of `keyframes` with the focal length held and a radial term
/// free (`BundleAdjustmentOptions::hold_focal`: under forward motion a free focal trades
/// off against the translation) and pools their terms: a lens distortion the calibration
/// leaves, as the paper's 7-parameter camera refines one radial term.
pub fn estimate_radial_term(
    camera: &PinholeRadtan,
    keyframes: &[KeyframeObservations],
    options: &FocalCalibrationOptions,
    solver: &WindowSolverOptions,
) -> Result<RadialEstimate, FocalCalibrationError> {
    let _span = tracing::debug_span!("radial_calibration", keyframes = keyframes.len()).entered();
    let terms = first_window_terms(Intrinsic::Radial, camera, keyframes, options, solver)?;
    pool_radial_terms(terms, options)
}

/// The radial estimate of the windows' terms (`per_window`, in order).
pub fn pool_radial_terms(
    per_window: Vec<f64>,
    options: &FocalCalibrationOptions,
) -> Result<RadialEstimate, FocalCalibrationError> {
    let (k, standard_error) = pooled(&per_window, options)?;
    if k.abs() > options.max_radial_correction {
        return Err(FocalCalibrationError::ImplausibleRadial { k });
    }
    let significant = k.abs() >= options.min_radial_correction
        && k.abs() >= options.min_radial_significance * standard_error;
    Ok(RadialEstimate {
        k,
        per_window,
        standard_error,
        significant,
    })
}

/// What a window solved with the intrinsics free measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Intrinsic {
    /// The focal scale (the focal length and a radial term free).
    Focal,
    /// A radial term (the focal length held).
    Radial,
}

impl Intrinsic {
    /// `solver` with the intrinsics free as this estimate frees them.
    pub fn solver(self, solver: &WindowSolverOptions) -> WindowSolverOptions {
        let mut solver = *solver;
        solver.bundle_adjustment.refine_intrinsics = true;
        solver.bundle_adjustment.hold_focal = self == Intrinsic::Radial;
        solver
    }

    /// The window's value of this intrinsic, when it is usable.
    pub fn term(self, solution: &WindowSolution) -> Option<f64> {
        match self {
            Intrinsic::Focal => Some(solution.focal_scale).filter(|s| s.is_finite() && *s > 0.0),
            Intrinsic::Radial => Some(solution.radial_k).filter(|k| k.is_finite()),
        }
    }
}

/// The run's first windows (without its adaptive ends, at most `max_windows`), as the
/// keyframes come: each window a run of consecutive keyframe indices.
pub struct FirstWindows {
    builder: WindowBuilder<usize>,
    made: usize,
    max_windows: usize,
    next: usize,
}

impl FirstWindows {
    pub fn new(options: &FocalCalibrationOptions) -> Result<Self, FocalCalibrationError> {
        let builder = WindowBuilder::new(WindowOptions {
            size: options.window,
            overlap: options.overlap,
            ..WindowOptions::default()
        })?;
        Ok(Self {
            builder,
            made: 0,
            max_windows: options.max_windows,
            next: 0,
        })
    }

    /// Whether every window to solve has been made.
    pub fn complete(&self) -> bool {
        self.made == self.max_windows
    }

    /// Takes the next keyframe; the window it completes, as the range of keyframe indices.
    pub fn push(&mut self) -> Option<std::ops::RangeInclusive<usize>> {
        if self.complete() {
            return None;
        }
        let index = self.next;
        self.next += 1;
        let window = self.builder.push(index)?;
        self.range(window.keyframes)
    }

    /// After the last keyframe: the last window, if one is left to make.
    pub fn finish(mut self) -> Option<std::ops::RangeInclusive<usize>> {
        if self.complete() {
            return None;
        }
        let window = self.builder.finish()?;
        self.range(window.keyframes)
    }

    fn range(&mut self, indices: Vec<usize>) -> Option<std::ops::RangeInclusive<usize>> {
        self.made += 1;
        Some(*indices.first()?..=*indices.last()?)
    }
}

/// Solves one of the first windows with `solver` (an [`Intrinsic::solver`]); `None` when it
/// is not solved with translation. `cache` is shared by the windows of one estimate.
pub fn solve_first_window(
    camera: &PinholeRadtan,
    window: &[KeyframeObservations],
    solver: &WindowSolverOptions,
    cache: &mut EdgeCache,
) -> Option<WindowSolution> {
    let s = solve_window(camera, window, solver, cache);
    tracing::debug!(keyframes = window.len(), status = ?s.status, focal_scale = s.focal_scale, radial_k = s.radial_k, "window");
    (s.status == WindowStatus::Solved).then_some(s)
}

/// The value of `what` in each of the run's first windows of `keyframes` solved with it
/// free (those solved with translation, in order).
fn first_window_terms(
    what: Intrinsic,
    camera: &PinholeRadtan,
    keyframes: &[KeyframeObservations],
    options: &FocalCalibrationOptions,
    solver: &WindowSolverOptions,
) -> Result<Vec<f64>, FocalCalibrationError> {
    let solver = what.solver(solver);
    let mut windows = FirstWindows::new(options)?;
    let mut ranges: Vec<_> = keyframes.iter().filter_map(|_| windows.push()).collect();
    ranges.extend(windows.finish());
    let mut cache = EdgeCache::new();
    Ok(ranges
        .into_iter()
        .filter_map(|r| solve_first_window(camera, &keyframes[r], &solver, &mut cache))
        .filter_map(|s| what.term(&s))
        .collect())
}

/// Median of the windows' values and its standard error (1.4826 x MAD / sqrt(n)); an
/// error with fewer than `min_windows`.
fn pooled(
    per_window: &[f64],
    options: &FocalCalibrationOptions,
) -> Result<(f64, f64), FocalCalibrationError> {
    if per_window.len() < options.min_windows.max(1) {
        return Err(FocalCalibrationError::TooFewWindows {
            solved: per_window.len(),
            needed: options.min_windows.max(1),
        });
    }
    let centre = median(per_window);
    let deviations: Vec<f64> = per_window.iter().map(|v| (v - centre).abs()).collect();
    let standard_error = 1.4826 * median(&deviations) / (per_window.len() as f64).sqrt();
    Ok((centre, standard_error))
}

/// Median of a non-empty slice (the mean of the middle two for an even count).
fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{observe, random_points};
    use crate::triangulation::CameraPose;
    use nalgebra::{Rotation3, Vector3};
    use rand::rngs::StdRng;
    use rand::SeedableRng;

    /// A head walking forward and looking around for `n` keyframes (as
    /// `test_support::head_poses`, longer).
    fn walk(n: usize) -> Vec<CameraPose> {
        (0..n)
            .map(|i| {
                let t = i as f64;
                CameraPose {
                    rotation: Rotation3::from_euler_angles(
                        0.03 * (0.7 * t).sin(),
                        0.15 * (0.3 * t).sin(),
                        0.02 * t.cos(),
                    ),
                    centre: Vector3::new(0.05 * (0.5 * t).sin(), 0.01 * t.cos(), 0.08 * t),
                }
            })
            .collect()
    }

    /// Tracks rendered with the test camera's 520 px focal length, 0.5 px noise.
    fn keyframes(seed: u64) -> Vec<KeyframeObservations> {
        let mut rng = StdRng::seed_from_u64(seed);
        let poses = walk(50);
        // Points along the whole walk (it goes 4 m forward).
        let mut points = random_points(&mut rng, 2500);
        for (k, p) in points.iter_mut().enumerate() {
            p.z += 4.0 * (k % 5) as f64 / 5.0;
        }
        observe(&poses, &points, 0.5, &mut rng)
    }

    fn camera_with_focal(f: f64) -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [f, f, 320.0, 240.0], [0.0; 5]).expect("camera")
    }

    #[test]
    fn a_focal_length_told_four_percent_long_is_found_and_the_right_one_left_alone() {
        let kf = keyframes(5);
        let options = FocalCalibrationOptions::default();
        let solver = WindowSolverOptions::default();
        let told_long = estimate_focal_scale(&camera_with_focal(540.0), &kf, &options, &solver)
            .expect("estimate");
        let truth = 520.0 / 540.0;
        assert!(told_long.per_window.len() >= 3, "{told_long:?}");
        assert!(
            (told_long.scale - truth).abs() < 0.005,
            "scale {} against {truth} ({:?})",
            told_long.scale,
            told_long.per_window
        );
        assert!(told_long.significant, "{told_long:?}");
        assert!((told_long.applied() - told_long.scale).abs() < 1e-12);
        let right = estimate_focal_scale(&camera_with_focal(520.0), &kf, &options, &solver)
            .expect("estimate");
        assert!((right.scale - 1.0).abs() < 0.005, "{right:?}");
        assert!(!right.significant, "{right:?}");
        assert_eq!(right.applied(), 1.0);
    }

    #[test]
    fn too_few_windows_and_an_implausible_focal_are_refused() {
        let kf = keyframes(6);
        let options = FocalCalibrationOptions::default();
        let solver = WindowSolverOptions::default();
        // 20 keyframes are one window.
        assert_eq!(
            estimate_focal_scale(&camera_with_focal(520.0), &kf[..20], &options, &solver),
            Err(FocalCalibrationError::TooFewWindows {
                solved: 1,
                needed: 3
            })
        );
        // Beyond the bound believed (2 % here, 20 % by default: the wrong calibration
        // file) a focal length is refused, not "corrected".
        let strict = FocalCalibrationOptions {
            max_correction: 0.02,
            ..options
        };
        let r = estimate_focal_scale(&camera_with_focal(540.0), &kf, &strict, &solver);
        assert!(
            matches!(r, Err(FocalCalibrationError::Implausible { scale }) if scale < 0.98),
            "{r:?}"
        );
    }

    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
    }

    /// `keyframes` seen through a lens with radial distortion `k` the calibration
    /// (`camera_with_focal(520.0)`) does not describe.
    fn distorted(keyframes: &[KeyframeObservations], k: f64) -> Vec<KeyframeObservations> {
        let c = camera_with_focal(520.0);
        keyframes
            .iter()
            .map(|kf| KeyframeObservations {
                tracks: kf
                    .tracks
                    .iter()
                    .map(|(id, p)| {
                        let (x, y) = ((p.x - c.cx) / c.fx, (p.y - c.cy) / c.fy);
                        let d = 1.0 + k * (x * x + y * y);
                        (
                            *id,
                            nalgebra::Point2::new(c.cx + c.fx * d * x, c.cy + c.fy * d * y),
                        )
                    })
                    .collect(),
                ..kf.clone()
            })
            .collect()
    }

    #[test]
    fn a_radial_distortion_the_calibration_leaves_is_found_and_none_is_left_alone() {
        let kf = keyframes(5);
        let options = FocalCalibrationOptions::default();
        let solver = WindowSolverOptions::default();
        let camera = camera_with_focal(520.0);
        let pincushion = estimate_radial_term(&camera, &distorted(&kf, 0.03), &options, &solver)
            .expect("estimate");
        assert!(pincushion.per_window.len() >= 3, "{pincushion:?}");
        assert!((pincushion.k - 0.03).abs() < 0.005, "{pincushion:?}");
        assert!(pincushion.significant, "{pincushion:?}");
        assert_eq!(pincushion.applied(), pincushion.k);
        let none = estimate_radial_term(&camera, &kf, &options, &solver).expect("estimate");
        assert!(none.k.abs() < 0.003, "{none:?}");
        assert!(!none.significant, "{none:?}");
        assert_eq!(none.applied(), 0.0);
    }

    /// `poses` in a corridor (walls 2 m either side, floor and ceiling 1.5 m off, an end
    /// wall 12 m ahead) seen through `lens` with 0.5 px of noise on the raw image, and
    /// undistorted with `told`, as the tracker undistorts with the calibration it is given.
    fn through_lens(
        poses: &[CameraPose],
        lens: &PinholeRadtan,
        told: &PinholeRadtan,
        seed: u64,
    ) -> Vec<KeyframeObservations> {
        use crate::test_support::gaussian;
        use rand::Rng;
        let mut rng = StdRng::seed_from_u64(seed);
        let points: Vec<Vector3<f64>> = (0..4000)
            .map(|n| {
                let (a, b) = (rng.random_range(-1.0..1.0), rng.random_range(0.0..1.0));
                match n % 5 {
                    0 => Vector3::new(-2.0, 1.5 * a, -2.0 + 14.0 * b),
                    1 => Vector3::new(2.0, 1.5 * a, -2.0 + 14.0 * b),
                    2 => Vector3::new(2.0 * a, -1.5, -2.0 + 14.0 * b),
                    3 => Vector3::new(2.0 * a, 1.5, -2.0 + 14.0 * b),
                    _ => Vector3::new(2.0 * a, 1.5 * (2.0 * b - 1.0), 12.0),
                }
            })
            .collect();
        poses
            .iter()
            .enumerate()
            .map(|(k, pose)| {
                let tracks = points
                    .iter()
                    .enumerate()
                    .filter_map(|(id, x)| {
                        let raw = lens.project_raw(&pose.to_camera(x))?;
                        let noisy = nalgebra::Point2::new(
                            raw.x + 0.5 * gaussian(&mut rng),
                            raw.y + 0.5 * gaussian(&mut rng),
                        );
                        let inside =
                            (0.0..640.0).contains(&noisy.x) && (0.0..480.0).contains(&noisy.y);
                        inside
                            .then(|| told.undistort_pixel(noisy))
                            .flatten()
                            .map(|p| (id as u64, p))
                    })
                    .collect();
                KeyframeObservations {
                    id: k as u64,
                    timestamp: k as f64 * 0.2,
                    tracks,
                }
            })
            .collect()
    }

    fn fisheye(f: f64, k1: f64) -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [f, f, 320.0, 240.0], [k1, 0.0, 0.0, 0.0, 0.0])
            .and_then(|c| c.with_lens(egoslam_geometry::LensModel::Equidistant))
            .expect("camera")
    }

    #[test]
    fn a_fisheyes_focal_and_first_term_are_found_on_its_own_image() {
        let options = FocalCalibrationOptions::default();
        let solver = WindowSolverOptions::default();
        let lens = fisheye(260.0, 0.02);
        let poses = walk(50);
        // Told a focal 4 % long (the first term right): the scale that makes it 260.
        let told_long = fisheye(270.0, 0.02);
        let kf = through_lens(&poses, &lens, &told_long, 3);
        let focal = estimate_focal_scale(&told_long, &kf, &options, &solver).expect("estimate");
        let truth = 260.0 / 270.0;
        assert!(focal.per_window.len() >= 3, "{focal:?}");
        assert!(
            (focal.scale - truth).abs() < 0.004,
            "scale {} against {truth}: {focal:?}",
            focal.scale
        );
        assert!(focal.significant, "{focal:?}");
        // Told a nominal lens without its first term: the term it leaves.
        let nominal = fisheye(260.0, 0.0);
        let kf = through_lens(&poses, &lens, &nominal, 4);
        let radial = estimate_radial_term(&nominal, &kf, &options, &solver).expect("estimate");
        assert!((radial.k - 0.02).abs() < 0.004, "{radial:?}");
        assert!(radial.significant, "{radial:?}");
        // Told the lens as it is: nothing to correct.
        let kf = through_lens(&poses, &lens, &lens, 5);
        let right = estimate_focal_scale(&lens, &kf, &options, &solver).expect("estimate");
        assert!(
            (right.scale - 1.0).abs() < 0.004 && !right.significant,
            "{right:?}"
        );
        let none = estimate_radial_term(&lens, &kf, &options, &solver).expect("estimate");
        assert!(none.k.abs() < 0.003 && !none.significant, "{none:?}");
    }
}
