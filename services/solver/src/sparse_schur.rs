//! The Schur-complement normal equations with a *sparse* reduced camera system, for bundle
//! adjustments with many cameras (the merger's global refinement): the reduced matrix is
//! block-sparse (two cameras couple only through points both see) and is factored by faer's
//! sparse Cholesky. Same accumulation and step API as [`crate::schur::SchurSystem`], which
//! stays the choice for a window (a dense 114x114 system factors faster than any ordering).
//!
//! Parameters are camera blocks of 6 (`index / 6` is the block); no global parameters.

use crate::schur::{solve_finite, SchurStep};
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMat, Triplet};
use nalgebra::{DVector, Matrix3, Matrix6, Matrix6x3, SMatrix, SVector, Vector3, Vector6};
use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

const BLOCK: usize = 6;

/// Hashes the (camera block, camera block) keys of the reduced system's blocks with one
/// multiply per word (as rustc's FxHash): the elimination looks up ~20 blocks per point
/// (378,000 per solve on the global-BA bench), where an ordered map's comparisons and the
/// default SipHash cost more than the 6x6 update they find. No key comes from outside, so
/// nothing needs SipHash's resistance to chosen collisions. The triplets built from the map
/// do not depend on its order (each position appears once), so the solve is unchanged.
#[derive(Default)]
struct BlockPairHasher(u64);

impl Hasher for BlockPairHasher {
    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.write_u64(u64::from(*b));
        }
    }

    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }

    fn write_usize(&mut self, v: usize) {
        self.write_u64(v as u64);
    }

    fn finish(&self) -> u64 {
        self.0
    }
}

type BlockMap = HashMap<(usize, usize), Matrix6<f64>, BuildHasherDefault<BlockPairHasher>>;

#[derive(Debug, Clone, Default)]
struct PointBlock {
    v: Matrix3<f64>,
    g: Vector3<f64>,
    /// (camera block, W = J_c^T W J_p)
    coupling: Vec<(usize, Matrix6x3<f64>)>,
}

/// The symbolic Cholesky factorization (fill-reducing ordering and elimination tree) of the
/// last reduced system solved, kept between solves: Levenberg-Marquardt solves the same
/// sparsity pattern at every iteration and every damping retry, and on the global-BA bench
/// the ordering and symbolic analysis had been ~12 % of the whole adjustment. It is reused
/// only when the pattern is identical (compared index by index), so a changed active set
/// (outliers removed) simply computes a new one.
#[derive(Default)]
pub struct SymbolicCache {
    pattern: Option<(Vec<usize>, Vec<usize>, SymbolicLlt<usize>)>,
}

impl SymbolicCache {
    /// The symbolic factorization for `matrix`, computed only when its pattern changed.
    fn for_matrix(&mut self, matrix: &SparseColMat<usize, f64>) -> Option<SymbolicLlt<usize>> {
        let symbolic = matrix.symbolic();
        let (col_ptr, row_idx) = (symbolic.col_ptr(), symbolic.row_idx());
        if let Some((c, r, llt)) = &self.pattern {
            if c.as_slice() == col_ptr && r.as_slice() == row_idx {
                return Some(llt.clone());
            }
        }
        let llt = SymbolicLlt::try_new(symbolic, faer::Side::Lower).ok()?;
        self.pattern = Some((col_ptr.to_vec(), row_idx.to_vec(), llt.clone()));
        Some(llt)
    }
}

/// Normal equations with a block-sparse reduced camera system.
#[derive(Debug, Clone)]
pub struct SparseSchurSystem {
    blocks: usize,
    diagonal: Vec<Matrix6<f64>>,
    g: Vec<Vector6<f64>>,
    points: Vec<PointBlock>,
}

impl SparseSchurSystem {
    /// `reduced` parameters (a multiple of 6) and `points` points.
    pub fn new(reduced: usize, points: usize) -> Self {
        let blocks = reduced / BLOCK;
        Self {
            blocks,
            diagonal: vec![Matrix6::zeros(); blocks],
            g: vec![Vector6::zeros(); blocks],
            points: vec![PointBlock::default(); points],
        }
    }

    /// As [`crate::schur::SchurSystem::add`]; every index of `idx` must lie in one camera
    /// block (one observation sees one camera).
    pub fn add<const M: usize>(
        &mut self,
        idx: &[usize],
        jr: &[SVector<f64, M>],
        point: Option<(usize, &SMatrix<f64, M, 3>)>,
        r: &SVector<f64, M>,
        w: f64,
    ) {
        let block = idx.first().map(|i| i / BLOCK);
        let mut jc = SMatrix::<f64, M, 6>::zeros();
        if let Some(b) = block {
            for (col, &i) in jr.iter().zip(idx) {
                debug_assert_eq!(i / BLOCK, b, "one camera block per residual");
                jc.set_column(i - b * BLOCK, col);
            }
            let jct = jc.transpose();
            self.diagonal[b] += jct * jc * w;
            self.g[b] += jct * r * w;
        }
        if let Some((k, jp)) = point {
            let p = &mut self.points[k];
            let jpt = jp.transpose();
            p.v += jpt * jp * w;
            p.g += jpt * r * w;
            if let Some(b) = block {
                let c = jc.transpose() * jp * w;
                match p.coupling.iter_mut().find(|(cb, _)| *cb == b) {
                    Some((_, m)) => *m += c,
                    None => p.coupling.push((b, c)),
                }
            }
        }
    }

    /// Damped solve (as the dense version): points eliminated block by block, the reduced
    /// system assembled as a sparse lower triangle and factored by sparse Cholesky.
    pub fn solve(&self, lambda: f64) -> Option<SchurStep> {
        self.solve_cached(lambda, &mut SymbolicCache::default())
    }

    /// [`Self::solve`], reusing the symbolic factorization in `cache` when the reduced
    /// system's pattern is the one it was made for.
    pub fn solve_cached(&self, lambda: f64, cache: &mut SymbolicCache) -> Option<SchurStep> {
        let n = self.blocks * BLOCK;
        let mut s = BlockMap::default();
        let mut rhs: Vec<Vector6<f64>> = self.g.iter().map(|g| -g).collect();
        for (b, d) in self.diagonal.iter().enumerate() {
            let mut m = *d;
            for i in 0..BLOCK {
                m[(i, i)] += lambda * d[(i, i)].max(1e-12) + 1e-12;
            }
            s.insert((b, b), m);
        }
        let mut v_inv = Vec::with_capacity(self.points.len());
        for p in &self.points {
            let mut v = p.v;
            for d in 0..3 {
                v[(d, d)] += lambda * p.v[(d, d)].max(1e-12) + 1e-12;
            }
            let inv = v.try_inverse().unwrap_or_else(Matrix3::zeros);
            for (a, wa) in &p.coupling {
                let wa_vinv = wa * inv;
                rhs[*a] += wa_vinv * p.g;
                for (b, wb) in &p.coupling {
                    if b >= a {
                        *s.entry((*a, *b)).or_insert_with(Matrix6::zeros) -=
                            wa_vinv * wb.transpose();
                    }
                }
            }
            v_inv.push(inv);
        }
        // Lower triangle: block (b, a) = S_ab^T for a < b; the diagonal blocks' lower half.
        let mut triplets = Vec::with_capacity(s.len() * 36);
        for ((a, b), m) in &s {
            for i in 0..BLOCK {
                for j in 0..BLOCK {
                    let (row, col) = (b * BLOCK + j, a * BLOCK + i);
                    if row >= col {
                        triplets.push(Triplet::new(row, col, m[(i, j)]));
                    }
                }
            }
        }
        let reduced = if n > 0 {
            let matrix = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets).ok()?;
            let symbolic = cache.for_matrix(&matrix)?;
            let llt =
                Llt::try_new_with_symbolic(symbolic, matrix.as_ref(), faer::Side::Lower).ok()?;
            solve_finite(&llt, n, |i| rhs[i / BLOCK][i % BLOCK])?
        } else {
            DVector::zeros(0)
        };
        let points = self
            .points
            .iter()
            .zip(&v_inv)
            .map(|(p, inv)| {
                let mut r = -p.g;
                for (a, wa) in &p.coupling {
                    let xa = Vector6::from_iterator(reduced.rows(a * BLOCK, BLOCK).iter().copied());
                    r -= wa.transpose() * xa;
                }
                inv * r
            })
            .collect();
        Some(SchurStep { reduced, points })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schur::SchurSystem;

    #[test]
    fn matches_the_dense_schur_solve() {
        // Three camera blocks, four points, every point seen by two or three cameras.
        let mut seed = 3u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 33) as f64 / (1u64 << 31) as f64) - 0.5
        };
        let mut dense = SchurSystem::new(18, 4);
        let mut sparse = SparseSchurSystem::new(18, 4);
        for point in 0..4 {
            for cam in 0..3 {
                if point == 3 && cam == 1 {
                    continue;
                }
                for _ in 0..3 {
                    let idx: Vec<usize> = (cam * 6..cam * 6 + 6).collect();
                    let cols: Vec<SVector<f64, 2>> = (0..6)
                        .map(|_| SVector::<f64, 2>::new(next(), next()))
                        .collect();
                    let jp = SMatrix::<f64, 2, 3>::from_fn(|_, _| next());
                    let r = SVector::<f64, 2>::new(next(), next());
                    dense.add(&idx, &cols, Some((point, &jp)), &r, 1.5);
                    sparse.add(&idx, &cols, Some((point, &jp)), &r, 1.5);
                }
            }
        }
        let (a, b) = (
            dense.solve(0.1).expect("dense"),
            sparse.solve(0.1).expect("sparse"),
        );
        assert!((&a.reduced - &b.reduced).norm() < 1e-9 * (1.0 + a.reduced.norm()));
        for (p, q) in a.points.iter().zip(&b.points) {
            assert!((p - q).norm() < 1e-9 * (1.0 + p.norm()));
        }
    }
}
