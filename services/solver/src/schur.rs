//! Normal equations with point blocks eliminated by the Schur complement.
//!
//! Triggs et al., "Bundle Adjustment — A Modern Synthesis", 2000, section 6.1: in problems
//! with cameras and points, each point's 3x3 block is inverted independently and the system
//! reduces to the (small, dense for a window) camera block, solved here by Cholesky in faer.
//! Used by bundle adjustment and by the direction refinement of translation averaging.

use faer::linalg::solvers::Solve;
use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, SVector, Vector3};

/// One point's block: `V = sum J_p^T W J_p`, `g = sum J_p^T W r`, and its coupling
/// `W_k = sum J_r^T W J_p` to the reduced parameters, stored sparsely by reduced index.
#[derive(Debug, Clone, Default)]
struct PointBlock {
    v: Matrix3<f64>,
    g: Vector3<f64>,
    coupling: Vec<(usize, Vector3<f64>)>,
}

impl PointBlock {
    /// The position of the coupling to reduced parameter `index`, inserted if new; the
    /// list is kept sorted by index, so `SchurSystem::solve` walks the lower triangle in
    /// index order. `hint` is where the previous column's coupling went plus one: a
    /// residual block's columns are consecutive indices (a camera's six parameters), so
    /// the position is almost always the hint, checked in O(1), and a binary search
    /// otherwise. Observations usually arrive in camera order, so insertions are mostly at
    /// the end.
    fn slot(&mut self, index: usize, hint: usize) -> usize {
        let c = &self.coupling;
        if c.get(hint).is_some_and(|(i, _)| *i == index) {
            return hint;
        }
        let after_previous = hint == 0 || c.get(hint - 1).is_some_and(|(i, _)| *i < index);
        let before_next = c.get(hint).is_none_or(|(i, _)| *i > index);
        let p = if after_previous && before_next {
            Err(hint)
        } else {
            c.binary_search_by_key(&index, |(i, _)| *i)
        };
        match p {
            Ok(p) => p,
            Err(p) => {
                self.coupling.insert(p, (index, Vector3::zeros()));
                p
            }
        }
    }
}

/// Accumulates `J^T W J` and `J^T W r` residual block by residual block.
#[derive(Debug, Clone)]
pub struct SchurSystem {
    h: DMatrix<f64>,
    g: DVector<f64>,
    points: Vec<PointBlock>,
}

/// The `x_b` end of a residual given to [`SchurSystem::add_difference`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DifferenceEnd {
    /// Held fixed (no parameters).
    Fixed,
    /// Three reduced parameters starting at this index.
    Reduced(usize),
    /// This point.
    Point(usize),
}

/// The step for reduced parameters and for each point.
#[derive(Debug, Clone)]
pub struct SchurStep {
    pub reduced: DVector<f64>,
    pub points: Vec<Vector3<f64>>,
}

impl SchurSystem {
    /// A system with `reduced` camera-side parameters and `points` 3-D points.
    pub fn new(reduced: usize, points: usize) -> Self {
        Self {
            h: DMatrix::zeros(reduced, reduced),
            g: DVector::zeros(reduced),
            points: vec![PointBlock::default(); points],
        }
    }

    /// Zeroes every sum but keeps each point's list of couplings, so that accumulating
    /// the same structure again (the next Levenberg-Marquardt iteration) finds each
    /// coupling where it was and allocates nothing. A coupling the new accumulation does
    /// not touch stays zero, which changes no result.
    pub fn reset(&mut self) {
        self.h.fill(0.0);
        self.g.fill(0.0);
        for block in &mut self.points {
            block.v = Matrix3::zeros();
            block.g = Vector3::zeros();
            for (_, w) in &mut block.coupling {
                *w = Vector3::zeros();
            }
        }
    }

    /// Adds one residual block of `M` rows: Jacobian columns `jr` on the reduced parameters
    /// `idx` (one column per index), `jp` (M x 3) on `point` if any, residual `r`, scalar
    /// weight `w` (robust loss). Fixed-size and allocation-free: it runs once per
    /// observation and iteration.
    pub fn add<const M: usize>(
        &mut self,
        idx: &[usize],
        jr: &[SVector<f64, M>],
        point: Option<(usize, &SMatrix<f64, M, 3>)>,
        r: &SVector<f64, M>,
        w: f64,
    ) {
        for (ja, &ia) in jr.iter().zip(idx) {
            self.g[ia] += w * ja.dot(r);
            for (jb, &ib) in jr.iter().zip(idx) {
                // Lower triangle only: the Cholesky in `solve` reads nothing else.
                if ib <= ia {
                    self.h[(ia, ib)] += w * ja.dot(jb);
                }
            }
        }
        if let Some((k, jp)) = point {
            let block = &mut self.points[k];
            let jpt = jp.transpose();
            block.v += jpt * jp * w;
            block.g += jpt * r * w;
            let mut hint = 0;
            for (ja, &ia) in jr.iter().zip(idx) {
                let p = block.slot(ia, hint);
                block.coupling[p].1 += jpt * ja * w;
                hint = p + 1;
            }
        }
    }

    /// Adds a residual that depends on `x_b - x_a` only, two 3-vectors (translation
    /// averaging's direction constraints): Jacobian `j` (symmetric) wrt `x_b`, `-j` wrt
    /// `x_a`. Every block is then plus or minus the one `H = w j j`, so it is formed once
    /// instead of per pair of columns as [`SchurSystem::add`] would (that was most of the
    /// direction refinement's assembly). `a` is the first reduced index of `x_a`, `None`
    /// when it is held fixed; likewise `b`, or a point.
    pub fn add_difference(
        &mut self,
        a: Option<usize>,
        b: DifferenceEnd,
        j: &Matrix3<f64>,
        r: &Vector3<f64>,
        w: f64,
    ) {
        let h = j * j * w;
        let gb = j * r * w;
        if let Some(a) = a {
            self.add_diagonal_block(a, &h);
            for d in 0..3 {
                self.g[a + d] -= gb[d];
            }
        }
        match b {
            DifferenceEnd::Fixed => {}
            DifferenceEnd::Reduced(b) => {
                self.add_diagonal_block(b, &h);
                for d in 0..3 {
                    self.g[b + d] += gb[d];
                }
                if let Some(a) = a {
                    // Lower triangle: the block at (max, min) of the two, minus H (which is
                    // symmetric, so its transpose is itself).
                    let (row, col) = if b > a { (b, a) } else { (a, b) };
                    for c in 0..3 {
                        for r in 0..3 {
                            self.h[(row + r, col + c)] -= h[(r, c)];
                        }
                    }
                }
            }
            DifferenceEnd::Point(k) => {
                let block = &mut self.points[k];
                block.v += h;
                block.g += gb;
                if let Some(a) = a {
                    let mut hint = 0;
                    for d in 0..3 {
                        let p = block.slot(a + d, hint);
                        block.coupling[p].1 -= h.column(d);
                        hint = p + 1;
                    }
                }
            }
        }
    }

    /// `h` into the lower triangle of the diagonal block starting at `at`.
    fn add_diagonal_block(&mut self, at: usize, h: &Matrix3<f64>) {
        for c in 0..3 {
            for r in c..3 {
                self.h[(at + r, at + c)] += h[(r, c)];
            }
        }
    }

    /// Solves `(H + lambda diag(H)) dx = -g` (Levenberg-Marquardt damping, Marquardt's scaled
    /// form) with the points eliminated. The reduced matrix is symmetric and its Cholesky
    /// factorisation reads the lower triangle only, so only that is accumulated (half the
    /// work of the elimination, which is most of a window's bundle adjustment). `None` when the reduced system is not positive
    /// definite (the caller raises lambda).
    pub fn solve(&self, lambda: f64) -> Option<SchurStep> {
        let n = self.g.len();
        let mut s = self.h.clone();
        for d in 0..n {
            s[(d, d)] += lambda * self.h[(d, d)].max(1e-12) + 1e-12;
        }
        let mut rhs = -self.g.clone();
        let mut v_inv = Vec::with_capacity(self.points.len());
        // Each point's couplings are sorted by index (`PointBlock::slot`), so its part of
        // the lower triangle (a >= b) is walked column b by column b of the column-major
        // matrix with no per-entry test (that test and the bounds checks had been most of
        // this loop). Copied out as x / y / z columns, with the end of each run of
        // consecutive indices (a camera's six parameters) marked, each run's update is a
        // contiguous slice, which vectorises.
        let (mut wx, mut wy, mut wz) = (Vec::new(), Vec::new(), Vec::new());
        let mut run_end: Vec<usize> = Vec::new();
        let lower = s.as_mut_slice();
        for block in &self.points {
            let mut v = block.v;
            for d in 0..3 {
                v[(d, d)] += lambda * block.v[(d, d)].max(1e-12) + 1e-12;
            }
            let inv = v.try_inverse().unwrap_or_else(Matrix3::zeros);
            let inv_g = inv * block.g;
            let k = block.coupling.len();
            wx.clear();
            wy.clear();
            wz.clear();
            for (_, w) in &block.coupling {
                wx.push(w.x);
                wy.push(w.y);
                wz.push(w.z);
            }
            run_end.clear();
            run_end.resize(k, k);
            for p in (0..k.saturating_sub(1)).rev() {
                run_end[p] = if block.coupling[p + 1].0 == block.coupling[p].0 + 1 {
                    run_end[p + 1]
                } else {
                    p + 1
                };
            }
            for (b, (ib, wb)) in block.coupling.iter().enumerate() {
                rhs[*ib] += wb.dot(&inv_g);
                let yb = inv * wb;
                let column = &mut lower[ib * n..(ib + 1) * n];
                let mut p = b;
                while p < k {
                    let e = run_end[p];
                    let first = block.coupling[p].0;
                    let dst = &mut column[first..first + (e - p)];
                    for (((d, x), y), z) in
                        dst.iter_mut().zip(&wx[p..e]).zip(&wy[p..e]).zip(&wz[p..e])
                    {
                        *d -= x * yb.x + y * yb.y + z * yb.z;
                    }
                    p = e;
                }
            }
            v_inv.push(inv);
        }
        let reduced = if n > 0 {
            let a = faer::Mat::<f64>::from_fn(n, n, |i, j| s[(i, j)]);
            let llt = a.llt(faer::Side::Lower).ok()?;
            solve_finite(&llt, n, |i| rhs[i])?
        } else {
            DVector::zeros(0)
        };
        let points = self
            .points
            .iter()
            .zip(&v_inv)
            .map(|(block, inv)| {
                let mut rhs_p = -block.g;
                for (ia, wa) in &block.coupling {
                    rhs_p -= wa * reduced[*ia];
                }
                inv * rhs_p
            })
            .collect();
        Some(SchurStep { reduced, points })
    }
}

/// Solves with a factorisation for the right-hand side `rhs(i)`, `None` if not finite.
pub(crate) fn solve_finite(
    solver: &impl Solve<f64>,
    n: usize,
    rhs: impl Fn(usize) -> f64,
) -> Option<DVector<f64>> {
    let mut x = faer::Mat::<f64>::from_fn(n, 1, |i, _| rhs(i));
    solver.solve_in_place(x.as_mut());
    let out = DVector::from_fn(n, |i, _| x[(i, 0)]);
    out.iter().all(|v| v.is_finite()).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values in [-0.5, 0.5) (a linear congruential generator).
    fn pseudo_random(mut seed: u64) -> impl FnMut() -> f64 {
        move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 33) as f64 / (1u64 << 31) as f64) - 0.5
        }
    }

    #[test]
    fn matches_a_dense_solve() {
        // Two reduced parameters, two points, a few random-ish rows.
        let mut sys = SchurSystem::new(2, 2);
        let mut dense_h = DMatrix::<f64>::zeros(8, 8);
        let mut dense_g = DVector::<f64>::zeros(8);
        // Six rows per point (deterministic pseudo-random), so the full system has rank 8.
        let mut next = pseudo_random(7);
        let rows: Vec<(usize, [f64; 2], [f64; 3], f64)> = (0..12)
            .map(|n| (n / 6, [next(), next()], [next(), next(), next()], next()))
            .collect();
        for (k, jr, jp, r) in rows {
            let cols = [SVector::<f64, 1>::new(jr[0]), SVector::<f64, 1>::new(jr[1])];
            let jp_m = SMatrix::<f64, 1, 3>::new(jp[0], jp[1], jp[2]);
            sys.add(
                &[0, 1],
                &cols,
                Some((k, &jp_m)),
                &SVector::<f64, 1>::new(r),
                2.0,
            );
            let mut full = DVector::<f64>::zeros(8);
            full[0] = jr[0];
            full[1] = jr[1];
            for d in 0..3 {
                full[2 + 3 * k + d] = jp[d];
            }
            dense_h += &full * full.transpose() * 2.0;
            dense_g += &full * (r * 2.0);
        }
        let step = sys.solve(0.0).expect("solvable");
        let dense = dense_h.cholesky().expect("spd").solve(&(-dense_g));
        assert!((step.reduced[0] - dense[0]).abs() < 1e-9);
        assert!((step.reduced[1] - dense[1]).abs() < 1e-9);
        for k in 0..2 {
            for d in 0..3 {
                assert!((step.points[k][d] - dense[2 + 3 * k + d]).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn add_difference_matches_the_general_accumulation() {
        // Cameras 1 and 2 reduced (indices 0..6), camera 0 fixed, one point: every kind of
        // end, with a symmetric Jacobian as translation averaging's direction residual has.
        let mut next = pseudo_random(11);
        let (mut fast, mut general) = (SchurSystem::new(6, 1), SchurSystem::new(6, 1));
        let ends = [
            (Some(0), DifferenceEnd::Reduced(3)),
            (Some(3), DifferenceEnd::Reduced(0)),
            (None, DifferenceEnd::Reduced(0)),
            (Some(3), DifferenceEnd::Fixed),
            (Some(0), DifferenceEnd::Point(0)),
            (Some(3), DifferenceEnd::Point(0)),
            (None, DifferenceEnd::Point(0)),
        ];
        for (a, b) in ends {
            let m = Matrix3::from_fn(|_, _| next());
            let j = m + m.transpose() + Matrix3::identity() * 2.0;
            let r = Vector3::new(next(), next(), next());
            let w = 1.0 + next();
            fast.add_difference(a, b, &j, &r, w);
            let (mut idx, mut cols) = (Vec::new(), Vec::new());
            if let Some(a) = a {
                idx.extend(a..a + 3);
                cols.extend((0..3).map(|d| -j.column(d).into_owned()));
            }
            if let DifferenceEnd::Reduced(b) = b {
                idx.extend(b..b + 3);
                cols.extend((0..3).map(|d| j.column(d).into_owned()));
            }
            let point = match b {
                DifferenceEnd::Point(k) => Some((k, &j)),
                _ => None,
            };
            general.add(&idx, &cols, point, &r, w);
        }
        let (x, y) = (
            fast.solve(0.1).expect("solvable"),
            general.solve(0.1).expect("solvable"),
        );
        assert!((x.reduced - y.reduced).norm() < 1e-12);
        assert!((x.points[0] - y.points[0]).norm() < 1e-12);
    }
}
