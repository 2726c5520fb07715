//! Translation averaging: camera centres (and points) from known rotations and directions.
//!
//! 1. Convex initialisation in the manner of LUD, Ozyesil and Singer, "Robust Camera Location
//!    Estimation by Convex Programming", CVPR 2015: minimise `sum |B - A - d v|` (unsquared
//!    norm, robust to wrong directions) subject to `d >= 1` (which fixes the scale without a
//!    collapse), solved by iteratively reweighted least squares alternating with `d`.
//! 2. Robust non-linear refinement of the directions, as 1DSfM (Wilson and Snavely,
//!    "Robust Global Translations with 1DSfM", ECCV 2014): minimise
//!    `sum huber(|v - (B - A)/|B - A||^2)` by Gauss-Newton/LM.
//!
//! Constraints are camera-to-camera (from the essential matrices) *and* camera-to-point
//! (a track's bearing rotated to the world), as GLOMAP's global positioning (Pan et al.,
//! ECCV 2024): with points, cameras moving along one line (the egocentric walk, the car) are
//! no longer degenerate, because the points off that line fix the relative scales.

use crate::huber;
pub use crate::refinement_collapse::refinement_rescale;
use crate::schur::{DifferenceEnd, SchurSystem};
use nalgebra::{DMatrix, Matrix3, Vector3};

/// What a direction constrains: `end - start` is parallel to `direction` (world frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Endpoints {
    /// Camera i to camera j.
    Cameras { i: usize, j: usize },
    /// Camera i to point k.
    CameraPoint { i: usize, point: usize },
}

/// One unit direction in the world frame with a weight.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DirectionConstraint {
    pub endpoints: Endpoints,
    pub direction: Vector3<f64>,
    pub weight: f64,
}

/// Options (defaults cited per field).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TranslationAveragingOptions {
    /// Most IRLS iterations of the LUD stage (default 40; the IRLS of Ozyesil-Singer converges
    /// in tens of iterations; stops earlier once positions move by < 1e-6 of the scene size).
    pub lud_iterations: usize,
    /// Smallest residual in the IRLS weight 1/max(|e|, delta) (default 1e-4 of the unit scale).
    pub lud_delta: f64,
    /// Levenberg-Marquardt iterations of the direction refinement (default 15).
    pub refine_iterations: usize,
    /// Huber threshold on the chordal direction error (default 0.1, about 6 deg, as used for
    /// 1DSfM-style refinements in Theia).
    pub huber: f64,
    /// Largest factor by which the refinement may rescale a group of the cameras against
    /// the others (default 30; [`refinement_rescale`] measured at most 10.3 on sound
    /// windows but one, 48.7); beyond it the LUD positions are kept. Low on purpose: a
    /// false alarm costs bundle adjustment a start from the LUD positions (on that window
    /// the same result to 0.1 % of its path), a missed collapse a broken window. The
    /// direction objective is scale-free for every group of cameras with its points, so
    /// nothing but the constraints across the group's border stops it from shrinking:
    /// where its camera-to-camera directions are poor (a few pixels of parallax, 10-50 deg
    /// off) and its points are far compared with its baselines, shrinking costs its
    /// camera-to-point constraints little. On a rendered rolling-shutter walk a
    /// 25-keyframe window's first 20 keyframes shrank a little more with each refinement
    /// iteration, to 0.0007 of their length (window ATE 19 % of its path, 2.5 % from the
    /// LUD positions).
    pub max_refinement_rescale: f64,
}

impl Default for TranslationAveragingOptions {
    fn default() -> Self {
        Self {
            lud_iterations: 40,
            lud_delta: 1e-4,
            refine_iterations: 15,
            huber: 0.1,
            max_refinement_rescale: 30.0,
        }
    }
}

/// Errors of [`average_translations`].
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TranslationAveragingError {
    /// The constraints do not tie every camera to camera 0.
    #[error("camera positions are not determined: the reduced system is singular")]
    Underdetermined,
    /// A constraint names a camera or point out of range.
    #[error("constraint names camera {camera} or point {point} out of range")]
    BadIndex { camera: usize, point: usize },
}

/// Centres and points in a common frame (camera 0 at the origin), up to one global scale.
#[derive(Debug, Clone, PartialEq)]
pub struct TranslationAveragingResult {
    pub centres: Vec<Vector3<f64>>,
    pub points: Vec<Vector3<f64>>,
    /// Angle between each constraint's direction and the estimate, radians.
    pub residuals: Vec<f64>,
}

fn endpoints_of(c: &DirectionConstraint, cams: usize) -> (usize, usize) {
    // Unknowns: cameras 0..cams, then points.
    match c.endpoints {
        Endpoints::Cameras { i, j } => (i, j),
        Endpoints::CameraPoint { i, point } => (i, cams + point),
    }
}

/// Which camera-to-point constraints touch each point, built once per averaging: the IRLS
/// changes weights, not structure, so each solve walks these lists instead of allocating
/// one per point (compressed rows: point k's constraints are `constraint[start[k]..start[k + 1]]`).
struct PointConstraints {
    start: Vec<usize>,
    constraint: Vec<usize>,
}

impl PointConstraints {
    fn new(cams: usize, pts: usize, constraints: &[DirectionConstraint]) -> Self {
        let mut start = vec![0usize; pts + 1];
        for c in constraints {
            if let Endpoints::CameraPoint { point, .. } = c.endpoints {
                start[point + 1] += 1;
            }
        }
        for k in 0..pts {
            start[k + 1] += start[k];
        }
        let mut next = start.clone();
        let mut constraint = vec![0usize; start[pts]];
        for (n, c) in constraints.iter().enumerate() {
            let (_, b) = endpoints_of(c, cams);
            if b >= cams {
                constraint[next[b - cams]] = n;
                next[b - cams] += 1;
            }
        }
        Self { start, constraint }
    }

    fn of(&self, point: usize) -> &[usize] {
        &self.constraint[self.start[point]..self.start[point + 1]]
    }
}

/// One IRLS solve of `min sum w |x_b - x_a - s v|^2` with x_0 = 0, per axis (the system is
/// isotropic), points eliminated (each touches cameras only).
fn weighted_positions(
    cams: usize,
    pts: usize,
    constraints: &[DirectionConstraint],
    by_point: &PointConstraints,
    weights: &[f64],
    scales: &[f64],
) -> Option<Vec<Vector3<f64>>> {
    let m = cams - 1;
    let mut h = DMatrix::<f64>::zeros(m, m);
    let mut rhs = DMatrix::<f64>::zeros(m, 3);
    let target = |n: usize| constraints[n].direction * scales[n] * weights[n];
    for (n, c) in constraints.iter().enumerate() {
        let (a, b) = endpoints_of(c, cams);
        if b >= cams {
            continue; // camera-to-point: below, point by point
        }
        let (w, t) = (weights[n], target(n)); // x_b - x_a should equal s v
        for (u, su) in [(a, -1.0), (b, 1.0)] {
            if u == 0 {
                continue;
            }
            for (v, sv) in [(a, -1.0), (b, 1.0)] {
                if v != 0 {
                    h[(u - 1, v - 1)] += w * su * sv;
                }
            }
            for d in 0..3 {
                rhs[(u - 1, d)] += su * t[d];
            }
        }
    }
    // Each point enters through its constraints x_k - x_a = s v, and is eliminated:
    // x_k = (r_k + sum w x_a) / D_k. `h`'s upper triangle is left incomplete: the Cholesky
    // below reads the lower one only.
    let mut point_diag = vec![0.0; pts];
    let mut point_rhs = vec![Vector3::zeros(); pts];
    // A point's links as (camera, weight, weighted target), gathered once: the pairwise
    // update below reads them L^2 times per point. `h` is column-major m x m.
    let mut links: Vec<(usize, f64, Vector3<f64>)> = Vec::new();
    let hs = h.as_mut_slice();
    for k in 0..pts {
        links.clear();
        links.extend(by_point.of(k).iter().map(|&n| {
            let (a, _) = endpoints_of(&constraints[n], cams);
            (a, weights[n], target(n))
        }));
        let dk: f64 = links.iter().map(|l| l.1).sum();
        let rk: Vector3<f64> = links.iter().map(|l| l.2).sum();
        point_diag[k] = dk;
        point_rhs[k] = rk;
        for &(a, wa, ta) in &links {
            if a == 0 {
                continue;
            }
            hs[(a - 1) * (m + 1)] += wa;
            for d in 0..3 {
                rhs[(a - 1, d)] -= ta[d];
            }
            if dk <= 0.0 {
                continue;
            }
            for d in 0..3 {
                rhs[(a - 1, d)] += wa * rk[d] / dk;
            }
            // Lower triangle only (b <= a): nalgebra's Cholesky reads nothing else.
            for &(b, wb, _) in &links {
                if b != 0 && b <= a {
                    hs[(a - 1) + (b - 1) * m] -= wa * wb / dk;
                }
            }
        }
    }
    // A weak pull towards the origin (1e-6 of the mean diagonal) keeps a camera that no
    // constraint reaches solvable instead of failing the window; constrained cameras are
    // unaffected at this weight.
    let ridge = 1e-6 * (0..m).map(|d| h[(d, d)]).sum::<f64>() / m.max(1) as f64;
    for d in 0..m {
        h[(d, d)] += ridge.max(1e-12);
    }
    let chol = h.cholesky()?;
    let sol = chol.solve(&rhs);
    let mut x = vec![Vector3::zeros(); cams + pts];
    for i in 1..cams {
        x[i] = Vector3::new(sol[(i - 1, 0)], sol[(i - 1, 1)], sol[(i - 1, 2)]);
    }
    for k in 0..pts {
        if point_diag[k] > 0.0 {
            let mut acc = point_rhs[k];
            for &n in by_point.of(k) {
                let (a, _) = endpoints_of(&constraints[n], cams);
                acc += weights[n] * x[a];
            }
            x[cams + k] = acc / point_diag[k];
        }
    }
    x.iter()
        .all(|p| p.iter().all(|v| v.is_finite()))
        .then_some(x)
}

/// LUD by IRLS: alternate `d = max(1, v.(x_b - x_a))`, weights `1/|e|`, weighted solve.
fn lud(
    cams: usize,
    pts: usize,
    constraints: &[DirectionConstraint],
    options: &TranslationAveragingOptions,
) -> Option<Vec<Vector3<f64>>> {
    let mut weights: Vec<f64> = constraints.iter().map(|c| c.weight).collect();
    let mut scales = vec![1.0; constraints.len()];
    let by_point = PointConstraints::new(cams, pts, constraints);
    let mut x = weighted_positions(cams, pts, constraints, &by_point, &weights, &scales)?;
    for _ in 0..options.lud_iterations {
        for (n, c) in constraints.iter().enumerate() {
            let (a, b) = endpoints_of(c, cams);
            let diff = x[b] - x[a];
            scales[n] = c.direction.dot(&diff).max(1.0);
            let e = (diff - scales[n] * c.direction).norm();
            weights[n] = c.weight / e.max(options.lud_delta);
        }
        let next = weighted_positions(cams, pts, constraints, &by_point, &weights, &scales)?;
        // Converged when no position moves by more than 1e-6 of the largest distance.
        let size = next.iter().map(|p| p.norm()).fold(0.0, f64::max).max(1e-12);
        let moved = next
            .iter()
            .zip(&x)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        x = next;
        if moved < 1e-6 * size {
            break;
        }
    }
    Some(x)
}

/// Direction residual `v - u`, `u = (x_b - x_a)/|x_b - x_a|`, and its Jacobian wrt x_b
/// (wrt x_a it is the negative).
fn direction_residual(v: &Vector3<f64>, diff: &Vector3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
    let len = diff.norm().max(1e-12);
    let u = diff / len;
    let jb = -(Matrix3::identity() - u * u.transpose()) / len;
    (v - u, jb)
}

/// 1DSfM-style refinement by Levenberg-Marquardt; positions rescaled to their initial
/// spread after each step (the objective is scale-free).
fn refine(
    cams: usize,
    pts: usize,
    constraints: &[DirectionConstraint],
    x: &mut [Vector3<f64>],
    options: &TranslationAveragingOptions,
) {
    let cost = |x: &[Vector3<f64>]| -> f64 {
        constraints
            .iter()
            .map(|c| {
                let (a, b) = endpoints_of(c, cams);
                let r = direction_residual(&c.direction, &(x[b] - x[a])).0.norm();
                c.weight * huber::cost(r, options.huber)
            })
            .sum()
    };
    let spread = |x: &[Vector3<f64>]| x[..cams].iter().map(|c| c.norm()).sum::<f64>();
    let initial_spread = spread(x);
    let mut lambda = 1e-3;
    let mut current = cost(x);
    let mut sys = SchurSystem::new(3 * (cams - 1), pts);
    // The equations depend on the positions only: after a rejected step or a failed solve
    // they are the same, and only the damping changes.
    let mut built = false;
    for _ in 0..options.refine_iterations {
        if !built {
            sys.reset();
            for c in constraints {
                let (a, b) = endpoints_of(c, cams);
                let (r, jb) = direction_residual(&c.direction, &(x[b] - x[a]));
                let w = c.weight * huber::weight(r.norm(), options.huber);
                // Camera 0 is the fixed origin; the others' centres are the reduced
                // parameters.
                let start = (a != 0).then(|| 3 * (a - 1));
                let end = match b {
                    0 => DifferenceEnd::Fixed,
                    b if b < cams => DifferenceEnd::Reduced(3 * (b - 1)),
                    b => DifferenceEnd::Point(b - cams),
                };
                sys.add_difference(start, end, &jb, &r, w);
            }
            built = true;
        }
        let Some(step) = sys.solve(lambda) else {
            lambda *= 10.0;
            continue;
        };
        let mut trial = x.to_vec();
        for (centre, d) in trial[1..cams]
            .iter_mut()
            .zip(step.reduced.as_slice().chunks_exact(3))
        {
            *centre += Vector3::new(d[0], d[1], d[2]);
        }
        for k in 0..pts {
            trial[cams + k] += step.points[k];
        }
        let s = initial_spread / spread(&trial).max(1e-12);
        for p in &mut trial {
            *p *= s;
        }
        let new_cost = cost(&trial);
        if new_cost < current {
            x.copy_from_slice(&trial);
            built = false;
            let improvement = (current - new_cost) / current.max(1e-18);
            current = new_cost;
            lambda = (lambda * 0.3).max(1e-9);
            if improvement < 1e-8 {
                break;
            }
        } else {
            lambda *= 10.0;
        }
    }
}

/// Translation averaging: LUD initialisation, then direction refinement (module doc).
pub fn average_translations(
    cameras: usize,
    points: usize,
    constraints: &[DirectionConstraint],
    options: &TranslationAveragingOptions,
) -> Result<TranslationAveragingResult, TranslationAveragingError> {
    for c in constraints {
        let (a, b) = endpoints_of(c, cameras);
        let bad = match c.endpoints {
            Endpoints::Cameras { i, j } => i >= cameras || j >= cameras,
            Endpoints::CameraPoint { i, point } => i >= cameras || point >= points,
        };
        if bad {
            return Err(TranslationAveragingError::BadIndex {
                camera: a,
                point: b.saturating_sub(cameras),
            });
        }
    }
    if cameras < 2 {
        return Err(TranslationAveragingError::Underdetermined);
    }
    let initial = lud(cameras, points, constraints, options)
        .ok_or(TranslationAveragingError::Underdetermined)?;
    let mut x = initial.clone();
    refine(cameras, points, constraints, &mut x, options);
    let rescale = refinement_rescale(cameras, constraints, &initial, &x);
    if rescale.is_some_and(|r| r > options.max_refinement_rescale) {
        tracing::debug!(
            rescale,
            "direction refinement rescaled part of the cameras against the rest; LUD kept"
        );
        x = initial;
    }
    let residuals = constraints
        .iter()
        .map(|c| {
            let (a, b) = endpoints_of(c, cameras);
            let u = (x[b] - x[a]).normalize();
            c.direction.dot(&u).clamp(-1.0, 1.0).acos()
        })
        .collect();
    let pts = x.split_off(cameras);
    Ok(TranslationAveragingResult {
        centres: x,
        points: pts,
        residuals,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_geometry::umeyama;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    fn perturb(rng: &mut StdRng, v: Vector3<f64>, sigma: f64) -> Vector3<f64> {
        let n = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        (v + n * sigma).normalize()
    }

    /// Cameras walking straight ahead (z) with a little sway, points in front on both sides.
    fn forward_scene(rng: &mut StdRng) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
        let centres: Vec<_> = (0..20)
            .map(|i| Vector3::new(0.0, 0.0, 0.25 * i as f64))
            .collect();
        let points: Vec<_> = (0..300)
            .map(|_| {
                Vector3::new(
                    rng.random_range(-4.0..4.0),
                    rng.random_range(-2.0..2.0),
                    rng.random_range(6.0..20.0),
                )
            })
            .collect();
        (centres, points)
    }

    #[test]
    fn collinear_forward_motion_is_recovered_with_point_constraints() {
        let mut rng = StdRng::seed_from_u64(3);
        let (centres, points) = forward_scene(&mut rng);
        let n = centres.len();
        let mut constraints = Vec::new();
        for i in 0..n {
            for j in (i + 1)..(i + 4).min(n) {
                constraints.push(DirectionConstraint {
                    endpoints: Endpoints::Cameras { i, j },
                    direction: perturb(&mut rng, (centres[j] - centres[i]).normalize(), 0.01),
                    weight: 1.0,
                });
            }
            for (k, p) in points.iter().enumerate() {
                // Each point seen by a run of consecutive cameras (~1 px of bearing noise).
                if (k + i) % 4 != 0 {
                    constraints.push(DirectionConstraint {
                        endpoints: Endpoints::CameraPoint { i, point: k },
                        direction: perturb(&mut rng, (p - centres[i]).normalize(), 0.002),
                        weight: 1.0,
                    });
                }
            }
        }
        let result = average_translations(
            n,
            points.len(),
            &constraints,
            &TranslationAveragingOptions::default(),
        )
        .expect("solved");
        let sim = umeyama(&result.centres, &centres).expect("aligned");
        let path = 0.25 * (n - 1) as f64;
        let worst = result
            .centres
            .iter()
            .zip(&centres)
            .map(|(e, t)| (sim.apply(e) - t).norm())
            .fold(0.0, f64::max);
        assert!(
            worst < 0.01 * path,
            "worst position error {worst} over a {path} path"
        );
    }

    #[test]
    fn pair_constraints_alone_fix_a_generic_configuration_and_reject_a_wrong_edge() {
        let mut rng = StdRng::seed_from_u64(5);
        let centres: Vec<Vector3<f64>> = (0..8)
            .map(|_| {
                Vector3::new(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                )
            })
            .collect();
        let mut constraints = Vec::new();
        for i in 0..8 {
            for j in (i + 1)..8 {
                constraints.push(DirectionConstraint {
                    endpoints: Endpoints::Cameras { i, j },
                    direction: (centres[j] - centres[i]).normalize(),
                    weight: 1.0,
                });
            }
        }
        constraints[3].direction = -constraints[3].direction; // one flipped edge
        let result =
            average_translations(8, 0, &constraints, &TranslationAveragingOptions::default())
                .expect("solved");
        let sim = umeyama(&result.centres, &centres).expect("aligned");
        for (e, t) in result.centres.iter().zip(&centres) {
            assert!((sim.apply(e) - t).norm() < 1e-3, "{e:?} vs {t:?}");
        }
        assert!(
            result.residuals[3] > 3.0,
            "the flipped edge stays inconsistent"
        );
    }
}
