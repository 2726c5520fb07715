//! Bundle adjustment's normal equations, dense or sparse by problem size: a window's 20
//! cameras factor fastest as one dense reduced matrix (`schur.rs`), the merger's hundreds
//! of keyframes as a sparse one (`sparse_schur.rs`), since they couple only through the
//! points they share.

use crate::schur::{SchurStep, SchurSystem};
use crate::sparse_schur::{SparseSchurSystem, SymbolicCache};
use nalgebra::{SMatrix, SVector};

/// Cameras above which the reduced system is kept sparse (a window's 20 cameras factor
/// faster dense; the merger's hundreds of keyframes couple only through shared points).
const SPARSE_ABOVE_CAMERAS: usize = 60;

/// Dense or sparse normal equations, chosen by size.
pub(crate) enum NormalEquations {
    Dense(SchurSystem),
    Sparse(SparseSchurSystem),
}

impl NormalEquations {
    /// Empty equations for `reduced` camera-side parameters (`globals` of them shared by
    /// every camera: intrinsics, which keep the system dense) and `points` points.
    pub(crate) fn new(reduced: usize, globals: usize, points: usize) -> Self {
        if globals == 0 && reduced > 6 * SPARSE_ABOVE_CAMERAS {
            Self::Sparse(SparseSchurSystem::new(reduced, points))
        } else {
            Self::Dense(SchurSystem::new(reduced, points))
        }
    }

    /// Ready for the next iteration's accumulation (`SchurSystem::reset`; the sparse
    /// system is rebuilt).
    pub(crate) fn reset(&mut self, reduced: usize, points: usize) {
        match self {
            Self::Dense(s) => s.reset(),
            Self::Sparse(s) => *s = SparseSchurSystem::new(reduced, points),
        }
    }

    /// One residual block of `M` rows (`SchurSystem::add`): an observation's two, or a
    /// prior's three.
    pub(crate) fn add<const M: usize>(
        &mut self,
        idx: &[usize],
        jr: &[SVector<f64, M>],
        point: Option<(usize, &SMatrix<f64, M, 3>)>,
        r: &SVector<f64, M>,
        w: f64,
    ) {
        match self {
            Self::Dense(s) => s.add(idx, jr, point, r, w),
            Self::Sparse(s) => s.add(idx, jr, point, r, w),
        }
    }

    /// The damped step (`SchurSystem::solve`; the sparse one reuses `cache`'s symbolic
    /// factorisation while the pattern is unchanged).
    pub(crate) fn solve(&self, lambda: f64, cache: &mut SymbolicCache) -> Option<SchurStep> {
        match self {
            Self::Dense(s) => s.solve(lambda),
            Self::Sparse(s) => s.solve_cached(lambda, cache),
        }
    }
}
