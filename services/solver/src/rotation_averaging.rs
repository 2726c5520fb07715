//! Robust rotation averaging on SO(3).
//!
//! Chatterjee and Govindu, "Efficient and Robust Large-Scale Rotation Averaging", ICCV 2013,
//! and "Robust Relative Rotation Averaging", TPAMI 40(4), 2018: a spanning-tree
//! initialisation, then an L1 stage and an IRLS stage, each relinearising in the tangent space
//! of the current estimate and solving a weighted least-squares problem on the view graph.
//!
//! Convention: `rotations[i]` is camera_from_world; an edge measures
//! `R_ij ≈ R_j R_i^T` (camera i to camera j), as OpenCV's `recoverPose(E, x_i, x_j)` returns.

use nalgebra::{DMatrix, DVector, Rotation3, Vector3};
use std::collections::VecDeque;

/// A relative rotation measurement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativeRotation {
    pub i: usize,
    pub j: usize,
    /// `R_j R_i^T`.
    pub rotation: Rotation3<f64>,
    /// Confidence (e.g. RANSAC inliers); the spanning tree prefers heavy edges.
    pub weight: f64,
}

/// Options; defaults from Chatterjee and Govindu 2018 where they give one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotationAveragingOptions {
    /// L1 iterations (paper: a handful suffice to reach the basin of the IRLS stage; 10).
    pub l1_iterations: usize,
    /// IRLS iterations after the L1 stage (default 30; stops earlier on convergence).
    pub irls_iterations: usize,
    /// Scale of the robust IRLS weight, radians (default 5 deg: paper's Geman-McClure
    /// sigma; 3 deg edge noise sits inside, wrong edges far outside).
    pub robust_scale: f64,
    /// Stop when the largest update is below this, radians (default 1e-7).
    pub tolerance: f64,
}

impl Default for RotationAveragingOptions {
    fn default() -> Self {
        Self {
            l1_iterations: 10,
            irls_iterations: 30,
            robust_scale: 5f64.to_radians(),
            tolerance: 1e-7,
        }
    }
}

/// Errors of [`average_rotations`].
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RotationAveragingError {
    /// Some cameras are not connected to camera 0 by any edge.
    #[error(
        "view graph is disconnected: {unreached} of {cameras} cameras unreachable from camera 0"
    )]
    Disconnected { unreached: usize, cameras: usize },
    /// An edge names a camera index out of range, is a self loop, or is not finite.
    #[error("edge ({i}, {j}) invalid for {cameras} cameras")]
    BadEdge { i: usize, j: usize, cameras: usize },
}

/// Result with per-edge residuals so callers can drop inconsistent edges.
#[derive(Debug, Clone, PartialEq)]
pub struct RotationAveragingResult {
    /// camera_from_world, camera 0 = identity.
    pub rotations: Vec<Rotation3<f64>>,
    /// Angle between each edge's measurement and the estimate, radians.
    pub edge_residuals: Vec<f64>,
}

/// Breadth-first spanning tree over the heaviest edges first (a maximum spanning tree would
/// be marginally better; BFS from camera 0 visiting heavy edges first is what GLOMAP's
/// initialiser does in spirit and is deterministic).
fn spanning_tree_init(
    n: usize,
    edges: &[RelativeRotation],
) -> Result<Vec<Rotation3<f64>>, RotationAveragingError> {
    let mut adjacency: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (e, edge) in edges.iter().enumerate() {
        adjacency[edge.i].push(e);
        adjacency[edge.j].push(e);
    }
    for list in &mut adjacency {
        list.sort_by(|&a, &b| edges[b].weight.total_cmp(&edges[a].weight));
    }
    let mut rotations: Vec<Option<Rotation3<f64>>> = vec![None; n];
    rotations[0] = Some(Rotation3::identity());
    let mut queue = VecDeque::from([0usize]);
    while let Some(k) = queue.pop_front() {
        let rk = rotations[k].unwrap_or_else(Rotation3::identity);
        for &e in &adjacency[k] {
            let edge = &edges[e];
            let (other, r) = if edge.i == k {
                (edge.j, edge.rotation * rk)
            } else {
                (edge.i, edge.rotation.inverse() * rk)
            };
            if rotations[other].is_none() {
                rotations[other] = Some(r);
                queue.push_back(other);
            }
        }
    }
    let unreached = rotations.iter().filter(|r| r.is_none()).count();
    if unreached > 0 {
        return Err(RotationAveragingError::Disconnected {
            unreached,
            cameras: n,
        });
    }
    Ok(rotations
        .into_iter()
        .map(|r| r.unwrap_or_else(Rotation3::identity))
        .collect())
}

/// Residual of an edge in the tangent space: `log(R_j^T R_ij R_i)`.
fn edge_residual(edge: &RelativeRotation, rotations: &[Rotation3<f64>]) -> Vector3<f64> {
    (rotations[edge.j].inverse() * edge.rotation * rotations[edge.i]).scaled_axis()
}

/// One relinearised weighted least-squares step: solves for tangent updates `w` (camera 0
/// fixed) minimising `sum_e weight_e |r_e - (w_j - w_i)|^2`, applies `R_k <- R_k exp(w_k)`,
/// returns the largest update.
fn weighted_step(
    rotations: &mut [Rotation3<f64>],
    edges: &[RelativeRotation],
    weights: &[f64],
) -> f64 {
    let n = rotations.len();
    let m = n - 1; // camera 0 is the gauge
    let mut h = DMatrix::<f64>::zeros(m, m);
    let mut b = [
        DVector::<f64>::zeros(m),
        DVector::<f64>::zeros(m),
        DVector::<f64>::zeros(m),
    ];
    for (edge, &w) in edges.iter().zip(weights) {
        let r = edge_residual(edge, rotations);
        // Row: +1 at j, -1 at i.
        let (i, j) = (edge.i, edge.j);
        for (a, sa) in [(j, 1.0), (i, -1.0)] {
            if a == 0 {
                continue;
            }
            for (c, sc) in [(j, 1.0), (i, -1.0)] {
                if c == 0 {
                    continue;
                }
                h[(a - 1, c - 1)] += w * sa * sc;
            }
            for (axis, rhs) in b.iter_mut().enumerate() {
                rhs[a - 1] += w * sa * r[axis];
            }
        }
    }
    // Tiny damping keeps cameras whose every edge was down-weighted solvable.
    for d in 0..m {
        h[(d, d)] += 1e-9;
    }
    let Some(chol) = h.cholesky() else { return 0.0 };
    let solutions: Vec<DVector<f64>> = b.iter().map(|rhs| chol.solve(rhs)).collect();
    if solutions.iter().any(|s| s.iter().any(|v| !v.is_finite())) {
        return 0.0;
    }
    let mut largest: f64 = 0.0;
    for k in 1..n {
        let w = Vector3::new(
            solutions[0][k - 1],
            solutions[1][k - 1],
            solutions[2][k - 1],
        );
        largest = largest.max(w.norm());
        rotations[k] *= Rotation3::new(w);
    }
    largest
}

/// Robust rotation averaging; see the module doc.
pub fn average_rotations(
    cameras: usize,
    edges: &[RelativeRotation],
    options: &RotationAveragingOptions,
) -> Result<RotationAveragingResult, RotationAveragingError> {
    for e in edges {
        if e.i >= cameras
            || e.j >= cameras
            || e.i == e.j
            || !e.rotation.matrix().iter().all(|v| v.is_finite())
        {
            return Err(RotationAveragingError::BadEdge {
                i: e.i,
                j: e.j,
                cameras,
            });
        }
    }
    let mut rotations = spanning_tree_init(cameras, edges)?;
    if cameras > 1 {
        // L1 stage: IRLS weights 1/|r| minimise sum |r| (Chatterjee-Govindu 2013, eq. 8).
        for _ in 0..options.l1_iterations {
            let weights: Vec<f64> = edges
                .iter()
                .map(|e| 1.0 / edge_residual(e, &rotations).norm().max(1e-4))
                .collect();
            if weighted_step(&mut rotations, edges, &weights) < options.tolerance {
                break;
            }
        }
        // IRLS stage with the Geman-McClure weight sigma^2 / (sigma^2 + r^2)^2 (2018, eq. 12).
        let s2 = options.robust_scale * options.robust_scale;
        for _ in 0..options.irls_iterations {
            let weights: Vec<f64> = edges
                .iter()
                .map(|e| {
                    let r2 = edge_residual(e, &rotations).norm_squared();
                    s2 / ((s2 + r2) * (s2 + r2))
                })
                .collect();
            if weighted_step(&mut rotations, edges, &weights) < options.tolerance {
                break;
            }
        }
    }
    // Re-anchor so camera 0 is exactly the identity.
    let anchor = rotations[0].inverse();
    for r in &mut rotations {
        *r *= anchor;
    }
    let edge_residuals = edges
        .iter()
        .map(|e| edge_residual(e, &rotations).norm())
        .collect();
    Ok(RotationAveragingResult {
        rotations,
        edge_residuals,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    fn random_rotation(rng: &mut StdRng, max_angle: f64) -> Rotation3<f64> {
        let axis = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        Rotation3::new(axis * rng.random_range(0.0..max_angle))
    }

    /// Noise of exactly `angle` about a random axis.
    fn noise(rng: &mut StdRng, angle: f64) -> Rotation3<f64> {
        let axis = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        Rotation3::new(axis * angle)
    }

    #[test]
    fn thirty_cameras_three_degree_noise_twenty_percent_outliers() {
        let mut rng = StdRng::seed_from_u64(42);
        let n = 30;
        let truth: Vec<Rotation3<f64>> = (0..n)
            .map(|_| random_rotation(&mut rng, std::f64::consts::PI))
            .collect();
        // Each camera sees the next 8: a window-like banded graph.
        let mut edges = Vec::new();
        for i in 0..n {
            for j in (i + 1)..(i + 9).min(n) {
                let angle = rng.random_range(0.0..6f64.to_radians());
                edges.push(RelativeRotation {
                    i,
                    j,
                    rotation: noise(&mut rng, angle) * truth[j] * truth[i].inverse(),
                    weight: 1.0,
                });
            }
        }
        // Mean noise 3 deg; now 20 % of the edges become random rotations.
        let outliers = edges.len() / 5;
        let mut picked = 0;
        while picked < outliers {
            let e = rng.random_range(0..edges.len());
            if edges[e].weight == 1.0 {
                edges[e].rotation = random_rotation(&mut rng, std::f64::consts::PI);
                edges[e].weight = 0.999;
                picked += 1;
            }
        }
        let result =
            average_rotations(n, &edges, &RotationAveragingOptions::default()).expect("connected");
        // Compare up to the global gauge: align camera 0.
        let g = truth[0].inverse();
        let errors: Vec<f64> = (0..n)
            .map(|k| {
                (result.rotations[k].inverse() * truth[k] * g)
                    .angle()
                    .to_degrees()
            })
            .collect();
        let mean = errors.iter().sum::<f64>() / n as f64;
        assert!(mean < 1.0, "mean rotation error {mean} deg");
        // The outliers stand out in the residuals.
        let flagged = edges
            .iter()
            .zip(&result.edge_residuals)
            .filter(|(e, r)| e.weight < 1.0 && **r > 15f64.to_radians())
            .count();
        assert!(
            flagged as f64 > 0.9 * outliers as f64,
            "{flagged} of {outliers} outliers flagged"
        );
    }

    #[test]
    fn disconnected_graph_is_an_error() {
        let e = RelativeRotation {
            i: 0,
            j: 1,
            rotation: Rotation3::identity(),
            weight: 1.0,
        };
        assert_eq!(
            average_rotations(3, &[e], &RotationAveragingOptions::default()),
            Err(RotationAveragingError::Disconnected {
                unreached: 1,
                cameras: 3
            })
        );
    }
}
