//! Window bundle adjustment: Levenberg-Marquardt over camera rotations, centres and points,
//! points eliminated by the Schur complement, Huber loss, camera 0 fixed (gauge), optional
//! refinement of a focal scale and one radial term (the paper's 7-parameter camera plus
//! distortion, section 4).
//!
//! Triggs et al., "Bundle Adjustment — A Modern Synthesis", 2000; Lourakis and Argyros, SBA,
//! 2009 (the damped Schur-complement scheme); Huber, "Robust Estimation of a Location
//! Parameter", 1964. After convergence, observations whose error exceeds a threshold are
//! removed, reported, and the problem is solved again without them.

use crate::huber;
use crate::normal_equations::NormalEquations;
use crate::sparse_schur::SymbolicCache;
use crate::triangulation::CameraPose;
use egoslam_geometry::PinholeRadtan;
use nalgebra::{Matrix2x3, Point2, Rotation3, Vector2, Vector3};

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
}

impl Default for BundleAdjustmentOptions {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            huber_px: 2.0,
            outlier_px: 4.0,
            refine_intrinsics: false,
            tolerance: 1e-4,
            min_depth_fraction: 0.02,
            fixed_cameras: 1,
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
    /// Indices of observations removed as outliers.
    pub outliers: Vec<usize>,
    /// sqrt(mean squared per-axis error) over inlier observations, pixels.
    pub rmse_px: f64,
    /// Whether the last solve met the tolerance before the iteration limit.
    pub converged: bool,
    pub iterations: usize,
}

struct State {
    poses: Vec<CameraPose>,
    points: Vec<Vector3<f64>>,
    focal_scale: f64,
    radial_k: f64,
}

/// Projection with the refinable intrinsics; also returns d(pixel)/d(camera point) and
/// d(pixel)/d(focal_scale, k).
fn project(
    camera: &PinholeRadtan,
    s: f64,
    k: f64,
    pc: &Vector3<f64>,
) -> Option<(Vector2<f64>, Matrix2x3<f64>, nalgebra::Matrix2<f64>)> {
    if pc.z <= 1e-9 {
        return None;
    }
    let (xn, yn) = (pc.x / pc.z, pc.y / pc.z);
    let r2 = xn * xn + yn * yn;
    let d = 1.0 + k * r2;
    let (fx, fy) = (camera.fx * s, camera.fy * s);
    let pixel = Vector2::new(fx * d * xn + camera.cx, fy * d * yn + camera.cy);
    // d pixel / d (xn, yn)
    let j_n = nalgebra::Matrix2::new(
        fx * (d + 2.0 * k * xn * xn),
        fx * 2.0 * k * xn * yn,
        fy * 2.0 * k * xn * yn,
        fy * (d + 2.0 * k * yn * yn),
    );
    let iz = 1.0 / pc.z;
    let j_pc = Matrix2x3::new(iz, 0.0, -xn * iz, 0.0, iz, -yn * iz);
    let j_intr = nalgebra::Matrix2::new(
        camera.fx * d * xn,
        fx * r2 * xn,
        camera.fy * d * yn,
        fy * r2 * yn,
    );
    Some((pixel, j_n * j_pc, j_intr))
}

/// Robust cost; observations behind a camera count as a large constant.
fn cost(
    camera: &PinholeRadtan,
    st: &State,
    obs: &[Observation],
    active: &[bool],
    delta: f64,
) -> f64 {
    obs.iter()
        .zip(active)
        .filter(|(_, a)| **a)
        .map(|(o, _)| {
            let pc = st.poses[o.camera].to_camera(&st.points[o.point]);
            match project(camera, st.focal_scale, st.radial_k, &pc) {
                Some((p, _, _)) => huber::cost((p - o.pixel.coords).norm(), delta),
                None => huber::cost(1e3, delta),
            }
        })
        .sum()
}

/// LM iterations; returns (converged, iterations).
fn levenberg_marquardt(
    camera: &PinholeRadtan,
    st: &mut State,
    obs: &[Observation],
    active: &[bool],
    options: &BundleAdjustmentOptions,
) -> (bool, usize) {
    let cams = st.poses.len();
    let globals = if options.refine_intrinsics { 2 } else { 0 };
    let fixed = options.fixed_cameras.clamp(1, cams);
    let reduced = 6 * (cams - fixed) + globals;
    let g0 = 6 * (cams - fixed);
    let mut lambda = 1e-4;
    let mut symbolic = SymbolicCache::default();
    let mut current = cost(camera, st, obs, active, options.huber_px);
    let mut sys = NormalEquations::new(reduced, globals, st.points.len());
    let mut idx = Vec::with_capacity(8);
    let mut cols: Vec<Vector2<f64>> = Vec::with_capacity(8);
    for iteration in 0..options.max_iterations {
        if iteration > 0 {
            sys.reset(reduced, st.points.len());
        }
        for (o, _) in obs.iter().zip(active).filter(|(_, a)| **a) {
            let pose = &st.poses[o.camera];
            let pc = pose.to_camera(&st.points[o.point]);
            let Some((p, j_pc, j_intr)) = project(camera, st.focal_scale, st.radial_k, &pc) else {
                continue;
            };
            let r = p - o.pixel.coords;
            let w = huber::weight(r.norm(), options.huber_px);
            let r_mat = pose.rotation.matrix();
            // d pc / d rotation (left perturbation): -[pc]x ; d pc / d centre: -R ; d pc / d X: R
            let j_rot = j_pc * -pc.cross_matrix();
            let j_c = j_pc * -r_mat;
            let j_x = j_pc * r_mat;
            idx.clear();
            cols.clear();
            if o.camera >= fixed {
                let base = 6 * (o.camera - fixed);
                for d in 0..3 {
                    idx.push(base + d);
                    cols.push(j_rot.column(d).into_owned());
                }
                for d in 0..3 {
                    idx.push(base + 3 + d);
                    cols.push(j_c.column(d).into_owned());
                }
            }
            for d in 0..globals {
                idx.push(g0 + d);
                cols.push(j_intr.column(d).into_owned());
            }
            sys.add(&idx, &cols, Some((o.point, &j_x)), &r, w);
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
            };
            for c in fixed..cams {
                let b = 6 * (c - fixed);
                let dr = Vector3::new(step.reduced[b], step.reduced[b + 1], step.reduced[b + 2]);
                let dc = Vector3::new(
                    step.reduced[b + 3],
                    step.reduced[b + 4],
                    step.reduced[b + 5],
                );
                trial.poses[c].rotation = Rotation3::new(dr) * trial.poses[c].rotation;
                trial.poses[c].centre += dc;
            }
            if globals == 2 {
                trial.focal_scale += step.reduced[g0];
                trial.radial_k += step.reduced[g0 + 1];
            }
            for (x, dx) in trial.points.iter_mut().zip(&step.points) {
                *x += dx;
            }
            let new_cost = cost(camera, &trial, obs, active, options.huber_px);
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
    };
    let mut active = vec![true; observations.len()];
    let (_, first_iterations) =
        levenberg_marquardt(camera, &mut st, observations, &active, options);
    let mut outliers = Vec::new();
    let in_camera: Vec<Vector3<f64>> = observations
        .iter()
        .map(|o| st.poses[o.camera].to_camera(&st.points[o.point]))
        .collect();
    let fraction = options.min_depth_fraction;
    let collapsed = collapsed_points(st.points.len(), observations, &in_camera, fraction);
    for (n, (o, pc)) in observations.iter().zip(&in_camera).enumerate() {
        let bad = collapsed[o.point]
            || project(camera, st.focal_scale, st.radial_k, pc)
                .is_none_or(|(p, _, _)| (p - o.pixel.coords).norm() > options.outlier_px);
        if bad {
            active[n] = false;
            outliers.push(n);
        }
    }
    let (converged, iterations) = if outliers.is_empty() {
        (true, 0)
    } else {
        levenberg_marquardt(camera, &mut st, observations, &active, options)
    };
    let (mut sum, mut count) = (0.0, 0usize);
    for (o, _) in observations.iter().zip(&active).filter(|(_, a)| **a) {
        let pc = st.poses[o.camera].to_camera(&st.points[o.point]);
        if let Some((p, _, _)) = project(camera, st.focal_scale, st.radial_k, &pc) {
            sum += (p - o.pixel.coords).norm_squared();
            count += 1;
        }
    }
    Ok(BundleAdjustmentResult {
        poses: st.poses,
        points: st.points,
        focal_scale: st.focal_scale,
        radial_k: st.radial_k,
        outliers,
        rmse_px: (sum / (2.0 * count.max(1) as f64)).sqrt(),
        converged,
        iterations: first_iterations + iterations,
    })
}

#[cfg(test)]
#[path = "bundle_adjustment_tests.rs"]
mod tests;
