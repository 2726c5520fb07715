//! Window bundle adjustment: Levenberg-Marquardt over camera rotations, centres and points,
//! points eliminated by the Schur complement, Huber loss, camera 0 fixed (gauge), optional
//! refinement of a focal scale and one radial term (the paper's 7-parameter camera plus
//! distortion, section 4; through a fisheye on its raw image, `projection.rs`).
//!
//! Triggs et al., "Bundle Adjustment — A Modern Synthesis", 2000; Lourakis and Argyros, SBA,
//! 2009 (the damped Schur-complement scheme); Huber, "Robust Estimation of a Location
//! Parameter", 1964. After convergence, observations whose error exceeds a threshold are
//! removed, reported, and the problem is solved again without them.
//!
//! With a rolling-shutter readout (`readout_s > 0`) each camera also has an angular
//! velocity during its readout: the turn the frontend's first-order correction of the
//! tracks got wrong (it predicts the image's motion from the two frames before, so at the
//! onset of a sharp head turn it lags by tens of pixels per frame). Row `y` is seen at
//! `readout_s * (y - h/2) / h` after the middle row, by the camera turned by that velocity
//! for that time (the first-order model of Hedborg et al., "Rolling Shutter Bundle
//! Adjustment", CVPR 2012; Albl et al., "R6P", CVPR 2015), with a weak prior towards no
//! turn for cameras whose rows cannot tell it.

mod projection;

use crate::huber;
use crate::normal_equations::NormalEquations;
use crate::sparse_schur::SymbolicCache;
use crate::triangulation::CameraPose;
use egoslam_geometry::PinholeRadtan;
use nalgebra::{Matrix3, Point2, Rotation3, Vector2, Vector3};
use projection::Projection;

/// One observation of point `point` in camera `camera` at an undistorted pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    pub camera: usize,
    pub point: usize,
    pub pixel: Point2<f64>,
}

/// Options; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BundleAdjustmentOptions {
    /// LM iterations per solve (default 30; a window converges in 5-15 from averaging).
    pub max_iterations: usize,
    /// Huber threshold, pixels (default 2: about 2 sigma of LK tracks, so inliers are
    /// treated quadratically).
    pub huber_px: f64,
    /// Observations above this error after the first solve are outliers (default 4 px,
    /// COLMAP's `max_reproj_error`).
    pub outlier_px: f64,
    /// Refine a focal scale and a radial term k (default false: calibration is given).
    pub refine_intrinsics: bool,
    /// With `refine_intrinsics`, hold the focal scale at 1 and refine the radial term
    /// alone (default false). Under forward motion the focal length trades off against
    /// the translation (a shorter focal explains the flow's expansion as well), while a
    /// radial term is pinned by where in the image the points are: on kitti_odometry_00's
    /// windows the two free together came back at focal 0.96-0.98 with k about 0, which
    /// the ground-truth poses contradict (they fit the tracks best at the calibrated
    /// focal with k 0.02-0.03; `focal_calibration`).
    pub hold_focal: bool,
    /// Stop when the relative cost decrease falls below this (default 1e-4: from an
    /// averaging start, 1e-6 took twice the iterations for ATE changes below 1 mm on the
    /// KITTI and TUM windows).
    pub tolerance: f64,
    /// After the first solve, a point nearer to an observing camera than this fraction of
    /// the median observation depth is removed with all its observations (default 0.02).
    /// With the centimetre baselines of a head turning in place (TUM fr1_rpy), the first
    /// solve pulled weakly seen points of a window onto the camera cluster (depth 1/1000
    /// of the median; 152 observations in one window, none before the solve), where they
    /// bent the poses of the last keyframes and made the merger's scale between windows
    /// 35x wrong. Real near structure (a hand at 0.3 m in a 3 m room) is 10x nearer, not 50x.
    pub min_depth_fraction: f64,
    /// Leading cameras held fixed (default 1: camera 0 fixes rotation and translation; the
    /// merger fixes the keyframes it shares with the settled map, which also fixes scale).
    pub fixed_cameras: usize,
    /// Rolling-shutter readout, seconds, first row to last (default 0: a global shutter,
    /// no turn is estimated). Only whether it is on matters to the poses: the estimated
    /// angular velocity absorbs the value, which sets the units of the prior below.
    pub readout_s: f64,
    /// Standard deviation of the prior on each camera's readout turn, rad/s (default
    /// 1.0: a weak pull, worth 1 px^2 per rad/s, where a camera's ~1000 observations
    /// over the rows pin it to ~0.01 rad/s; it only keeps the turn of a camera whose
    /// observations span few rows from wandering).
    pub turn_prior_rad_s: f64,
    /// Standard deviation of the prior on the cameras' mean turn, rad/s (default 0.01:
    /// held). A turn about the camera's x axis shared by every camera stretches all images
    /// vertically, which a vertical stretch of the scene explains as well when the
    /// cameras' rows are parallel, as a walking head's are (Albl et al., "Degeneracies in
    /// Rolling Shutter SfM", ECCV 2016): on synthetic windows it came back 0.9 rad/s off
    /// with the reprojection error at the noise. The frontend's correction gets the
    /// readout right on average, so only each camera's departure from it is estimated.
    pub mean_turn_prior_rad_s: f64,
}

impl Default for BundleAdjustmentOptions {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            huber_px: 2.0,
            outlier_px: 4.0,
            refine_intrinsics: false,
            hold_focal: false,
            tolerance: 1e-4,
            min_depth_fraction: 0.02,
            fixed_cameras: 1,
            readout_s: 0.0,
            turn_prior_rad_s: 1.0,
            mean_turn_prior_rad_s: 0.01,
        }
    }
}

/// Errors of [`bundle_adjust`]; invalid input only: numerical trouble ends the iterations
/// and hands back the best state reached (see [`BundleAdjustmentResult::converged`]).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BundleAdjustmentError {
    /// An observation names a camera or point that does not exist.
    #[error("observation {index} names camera {camera} / point {point} out of range")]
    BadObservation {
        index: usize,
        camera: usize,
        point: usize,
    },
    /// Nothing to adjust.
    #[error("need at least two cameras and one observation")]
    Empty,
}

/// The adjusted problem.
#[derive(Debug, Clone, PartialEq)]
pub struct BundleAdjustmentResult {
    pub poses: Vec<CameraPose>,
    pub points: Vec<Vector3<f64>>,
    /// Focal scale (1 = as calibrated) and radial k on normalised coordinates.
    pub focal_scale: f64,
    pub radial_k: f64,
    /// Each camera's angular velocity during the readout, rad/s, in its own frame (zeros
    /// without a readout).
    pub turns: Vec<Vector3<f64>>,
    /// Indices of observations removed as outliers.
    pub outliers: Vec<usize>,
    /// sqrt(mean squared per-axis error) over inlier observations, pixels.
    pub rmse_px: f64,
    /// Whether the last solve met the tolerance before the iteration limit.
    pub converged: bool,
    pub iterations: usize,
}

impl BundleAdjustmentResult {
    /// Inlier observations of each of `cameras` cameras, of the `observations` adjusted.
    pub fn inliers_per_camera(&self, observations: &[Observation], cameras: usize) -> Vec<usize> {
        let mut seen = vec![0usize; cameras];
        for o in observations {
            seen[o.camera] += 1;
        }
        for &n in &self.outliers {
            seen[observations[n].camera] -= 1;
        }
        seen
    }
}

struct State {
    poses: Vec<CameraPose>,
    points: Vec<Vector3<f64>>,
    focal_scale: f64,
    radial_k: f64,
    turns: Vec<Vector3<f64>>,
}

impl State {
    /// Observation `o`'s point in its camera at the moment its row was read: the camera
    /// turned by its readout turn for the row's time after the middle row (`tau`).
    fn seen(&self, camera: &PinholeRadtan, readout_s: f64, o: &Observation) -> SeenPoint {
        let pc = self.poses[o.camera].to_camera(&self.points[o.point]);
        if readout_s == 0.0 {
            return SeenPoint {
                pc,
                tau: 0.0,
                turned: pc,
            };
        }
        let tau = readout_s * camera.row_offset(o.pixel.y);
        let turn = self.turns[o.camera];
        SeenPoint {
            pc,
            tau,
            turned: pc + tau * turn.cross(&pc),
        }
    }
}

/// A point in its camera's frame, before and after the readout turn of its row.
struct SeenPoint {
    pc: Vector3<f64>,
    /// The row's time after the middle row, seconds.
    tau: f64,
    turned: Vector3<f64>,
}

/// The observations with what each is compared with ([`Projection::target`]).
struct Problem<'a> {
    camera: &'a PinholeRadtan,
    projection: Projection<'a>,
    observations: &'a [Observation],
    targets: Vec<Vector2<f64>>,
}

impl Problem<'_> {
    fn measured(&self) -> impl Iterator<Item = (&Observation, Vector2<f64>)> {
        self.observations.iter().zip(self.targets.iter().copied())
    }
}

/// Robust cost; observations behind a camera count as a large constant.
fn cost(problem: &Problem, st: &State, active: &[bool], options: &BundleAdjustmentOptions) -> f64 {
    let delta = options.huber_px;
    let observations: f64 = problem
        .measured()
        .zip(active)
        .filter(|(_, a)| **a)
        .map(|((o, target), _)| {
            let seen = st.seen(problem.camera, options.readout_s, o);
            match problem
                .projection
                .project(st.focal_scale, st.radial_k, &seen.turned)
            {
                Some((p, _, _)) => huber::cost((p - target).norm(), delta),
                None => huber::cost(1e3, delta),
            }
        })
        .sum();
    let prior: f64 = st
        .turns
        .iter()
        .map(|w| 0.5 * (w / options.turn_prior_rad_s).norm_squared())
        .sum();
    observations + prior + mean_turn_prior(&st.turns, options).1
}

/// The prior on the cameras' mean turn as one residual per axis, `sqrt(n) mean / sigma`:
/// its weight per camera's turn (`sqrt(n) / (n sigma)`) and its cost.
fn mean_turn_prior(turns: &[Vector3<f64>], options: &BundleAdjustmentOptions) -> (f64, f64) {
    if turns.is_empty() {
        return (0.0, 0.0);
    }
    let n = turns.len() as f64;
    let scale = n.sqrt() / options.mean_turn_prior_rad_s;
    let mean = turns.iter().sum::<Vector3<f64>>() / n;
    (scale / n, 0.5 * (mean * scale).norm_squared())
}

/// LM iterations; returns (converged, iterations).
fn levenberg_marquardt(
    problem: &Problem,
    st: &mut State,
    active: &[bool],
    options: &BundleAdjustmentOptions,
) -> (bool, usize) {
    let cams = st.poses.len();
    // The refined intrinsics' columns of `project`'s d(pixel)/d(focal_scale, k).
    let intrinsics: &[usize] = match (options.refine_intrinsics, options.hold_focal) {
        (false, _) => &[],
        (true, false) => &[0, 1],
        (true, true) => &[1],
    };
    let globals = intrinsics.len();
    let fixed = options.fixed_cameras.clamp(1, cams);
    let turns_on = options.readout_s > 0.0;
    // A free camera's block: rotation, centre and, with a readout, its turn (consecutive,
    // so the Schur couplings stay runs); fixed cameras keep only their turns, after them.
    let block = if turns_on { 9 } else { 6 };
    let g0 = block * (cams - fixed) + if turns_on { 3 * fixed } else { 0 };
    let reduced = g0 + globals;
    let turn_index = |c: usize| {
        if c >= fixed {
            block * (c - fixed) + 6
        } else {
            block * (cams - fixed) + 3 * c
        }
    };
    let prior_sqrt = 1.0 / options.turn_prior_rad_s;
    let mut lambda = 1e-4;
    let mut symbolic = SymbolicCache::default();
    let mut current = cost(problem, st, active, options);
    let mut sys = NormalEquations::new(reduced, globals, st.points.len());
    let mut idx = Vec::with_capacity(8);
    let mut cols: Vec<Vector2<f64>> = Vec::with_capacity(8);
    for iteration in 0..options.max_iterations {
        if iteration > 0 {
            sys.reset(reduced, st.points.len());
        }
        for ((o, target), _) in problem.measured().zip(active).filter(|(_, a)| **a) {
            let seen = st.seen(problem.camera, options.readout_s, o);
            let Some((p, j_turned, j_intr)) =
                problem
                    .projection
                    .project(st.focal_scale, st.radial_k, &seen.turned)
            else {
                continue;
            };
            let r = p - target;
            let w = huber::weight(r.norm(), options.huber_px);
            let r_mat = st.poses[o.camera].rotation.matrix();
            // turned = (I + tau [turn]x) pc; d pc / d rotation (left perturbation): -[pc]x;
            // d pc / d centre: -R; d pc / d X: R; d turned / d turn: -tau [pc]x.
            let j_pc = if turns_on {
                j_turned * (Matrix3::identity() + seen.tau * st.turns[o.camera].cross_matrix())
            } else {
                j_turned
            };
            let j_rot = j_pc * -seen.pc.cross_matrix();
            let j_c = j_pc * -r_mat;
            let j_x = j_pc * r_mat;
            idx.clear();
            cols.clear();
            if o.camera >= fixed {
                let base = block * (o.camera - fixed);
                for d in 0..3 {
                    idx.push(base + d);
                    cols.push(j_rot.column(d).into_owned());
                }
                for d in 0..3 {
                    idx.push(base + 3 + d);
                    cols.push(j_c.column(d).into_owned());
                }
            }
            if turns_on {
                let j_turn = j_turned * (-seen.tau * seen.pc.cross_matrix());
                let base = turn_index(o.camera);
                for d in 0..3 {
                    idx.push(base + d);
                    cols.push(j_turn.column(d).into_owned());
                }
            }
            for (d, &column) in intrinsics.iter().enumerate() {
                idx.push(g0 + d);
                cols.push(j_intr.column(column).into_owned());
            }
            sys.add(&idx, &cols, Some((o.point, &j_x)), &r, w);
        }
        if turns_on {
            for (c, turn) in st.turns.iter().enumerate() {
                let base = turn_index(c);
                let unit = |d: usize| Vector3::ith(d, prior_sqrt);
                sys.add(
                    &[base, base + 1, base + 2],
                    &[unit(0), unit(1), unit(2)],
                    None,
                    &(turn * prior_sqrt),
                    1.0,
                );
            }
            let (per_turn, _) = mean_turn_prior(&st.turns, options);
            let mean = st.turns.iter().sum::<Vector3<f64>>() * per_turn;
            for d in 0..3 {
                idx.clear();
                idx.extend((0..cams).map(|c| turn_index(c) + d));
                let cols = vec![nalgebra::Vector1::new(per_turn); cams];
                sys.add(&idx, &cols, None, &nalgebra::Vector1::new(mean[d]), 1.0);
            }
        }
        let mut accepted = false;
        for _ in 0..8 {
            let Some(step) = sys.solve(lambda, &mut symbolic) else {
                lambda *= 10.0;
                continue;
            };
            let mut trial = State {
                poses: st.poses.clone(),
                points: st.points.clone(),
                focal_scale: st.focal_scale,
                radial_k: st.radial_k,
                turns: st.turns.clone(),
            };
            if turns_on {
                for (c, turn) in trial.turns.iter_mut().enumerate() {
                    let b = turn_index(c);
                    *turn +=
                        Vector3::new(step.reduced[b], step.reduced[b + 1], step.reduced[b + 2]);
                }
            }
            for c in fixed..cams {
                let b = block * (c - fixed);
                let dr = Vector3::new(step.reduced[b], step.reduced[b + 1], step.reduced[b + 2]);
                let dc = Vector3::new(
                    step.reduced[b + 3],
                    step.reduced[b + 4],
                    step.reduced[b + 5],
                );
                trial.poses[c].rotation = Rotation3::new(dr) * trial.poses[c].rotation;
                trial.poses[c].centre += dc;
            }
            for (d, &column) in intrinsics.iter().enumerate() {
                match column {
                    0 => trial.focal_scale += step.reduced[g0 + d],
                    _ => trial.radial_k += step.reduced[g0 + d],
                }
            }
            for (x, dx) in trial.points.iter_mut().zip(&step.points) {
                *x += dx;
            }
            let new_cost = cost(problem, &trial, active, options);
            if new_cost < current {
                let decrease = (current - new_cost) / current.max(1e-18);
                *st = trial;
                current = new_cost;
                lambda = (lambda / 3.0).max(1e-12);
                accepted = true;
                if decrease < options.tolerance {
                    return (true, iteration + 1);
                }
                break;
            }
            lambda *= 4.0;
        }
        if !accepted {
            // No decreasing step even with heavy damping: at a minimum (or stuck).
            return (true, iteration + 1);
        }
    }
    (false, options.max_iterations)
}

/// Points nearer to an observing camera than `fraction` of the median observation depth;
/// `in_camera[n]` is observation `n`'s point in its camera's frame.
fn collapsed_points(
    points: usize,
    observations: &[Observation],
    in_camera: &[Vector3<f64>],
    fraction: f64,
) -> Vec<bool> {
    let mut collapsed = vec![false; points];
    let depths: Vec<f64> = in_camera.iter().map(|pc| pc.z).collect();
    let mut sorted: Vec<f64> = depths.iter().copied().filter(|d| d.is_finite()).collect();
    if sorted.is_empty() || fraction <= 0.0 {
        return collapsed;
    }
    let mid = sorted.len() / 2;
    let median = *sorted.select_nth_unstable_by(mid, f64::total_cmp).1;
    for (o, d) in observations.iter().zip(&depths) {
        if *d < fraction * median {
            collapsed[o.point] = true;
        }
    }
    collapsed
}

/// Bundle adjustment with outlier removal; see the module doc. The first
/// `options.fixed_cameras` poses stay fixed.
pub fn bundle_adjust(
    camera: &PinholeRadtan,
    poses: &[CameraPose],
    points: &[Vector3<f64>],
    observations: &[Observation],
    options: &BundleAdjustmentOptions,
) -> Result<BundleAdjustmentResult, BundleAdjustmentError> {
    if poses.len() < 2 || observations.is_empty() {
        return Err(BundleAdjustmentError::Empty);
    }
    for (index, o) in observations.iter().enumerate() {
        if o.camera >= poses.len() || o.point >= points.len() {
            return Err(BundleAdjustmentError::BadObservation {
                index,
                camera: o.camera,
                point: o.point,
            });
        }
    }
    let mut st = State {
        poses: poses.to_vec(),
        points: points.to_vec(),
        focal_scale: 1.0,
        radial_k: 0.0,
        turns: vec![Vector3::zeros(); poses.len()],
    };
    let projection = Projection::new(camera, options.refine_intrinsics);
    // An observation the lens has no image of cannot be measured: an outlier from the start.
    let mut outliers = Vec::new();
    let targets: Vec<Vector2<f64>> = observations
        .iter()
        .enumerate()
        .map(|(n, o)| {
            projection.target(o).unwrap_or_else(|| {
                outliers.push(n);
                o.pixel.coords
            })
        })
        .collect();
    let problem = Problem {
        camera,
        projection,
        observations,
        targets,
    };
    let mut active = vec![true; observations.len()];
    for &n in &outliers {
        active[n] = false;
    }
    let unmeasured = outliers.len();
    let (_, first_iterations) = levenberg_marquardt(&problem, &mut st, &active, options);
    let in_camera: Vec<Vector3<f64>> = observations
        .iter()
        .map(|o| st.seen(camera, options.readout_s, o).turned)
        .collect();
    let fraction = options.min_depth_fraction;
    let collapsed = collapsed_points(st.points.len(), observations, &in_camera, fraction);
    for (n, ((o, target), pc)) in problem.measured().zip(&in_camera).enumerate() {
        let bad = collapsed[o.point]
            || problem
                .projection
                .project(st.focal_scale, st.radial_k, pc)
                .is_none_or(|(p, _, _)| (p - target).norm() > options.outlier_px);
        if bad && active[n] {
            active[n] = false;
            outliers.push(n);
        }
    }
    outliers.sort_unstable();
    // Solved again however few observations went: the Huber loss bounds an outlier's pull
    // but does not remove it. Skipping this solve when under 1 % went (0.3 % on KITTI's
    // windows, a quarter of the window's adjustment time) moved the dumped windows of the
    // rendered walker_1500_seed4 from 0.26 to 0.44 % of their path in the mean (worst
    // window 1.5 -> 6.5 %) and KITTI's from 0.23 to 0.32 % (docs/benchmarks.md,
    // "Window-level accuracy").
    let (converged, iterations) = if outliers.len() == unmeasured {
        (true, 0)
    } else {
        levenberg_marquardt(&problem, &mut st, &active, options)
    };
    let (mut sum, mut count) = (0.0, 0usize);
    for ((o, target), _) in problem.measured().zip(&active).filter(|(_, a)| **a) {
        let pc = st.seen(camera, options.readout_s, o).turned;
        if let Some((p, _, _)) = problem.projection.project(st.focal_scale, st.radial_k, &pc) {
            sum += (p - target).norm_squared();
            count += 1;
        }
    }
    Ok(BundleAdjustmentResult {
        poses: st.poses,
        points: st.points,
        focal_scale: st.focal_scale,
        radial_k: st.radial_k,
        turns: st.turns,
        outliers,
        rmse_px: (sum / (2.0 * count.max(1) as f64)).sqrt(),
        converged,
        iterations: first_iterations + iterations,
    })
}

#[cfg(test)]
mod tests;
