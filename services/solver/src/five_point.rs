//! The five-point minimal solver for the essential matrix on bearings.
//!
//! Stewénius, Engels and Nistér, "Recent developments on direct relative orientation",
//! ISPRS Journal of Photogrammetry and Remote Sensing 60(4), 2006: the five epipolar
//! constraints `b_j^T E b_i = 0` leave a four-dimensional space `E = x X + y Y + z Z + W`;
//! the rank and trace constraints (`det E = 0`, `2 E E^T E - tr(E E^T) E = 0`) are ten
//! cubics in `(x, y, z)`. Their ten cubic monomials are eliminated (Gauss-Jordan), which
//! leaves every cubic as a combination of the ten monomials of degree two or less; the
//! action matrix of multiplication by `x` on those ten has the solutions as eigenvectors.
//! Up to ten essential matrices are returned, one per real eigenvalue.
//!
//! Why own code: it is the minimal solver of the own LO-RANSAC
//! ([`crate::essential_ransac`]), the alternative to OpenCV's USAC that the relative-pose
//! stage can select. ~13 us per sample (release build); the stage's time is the number of
//! samples times that and their scoring (docs/solver.md, "Own five-point RANSAC").

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

type Matrix10 = SMatrix<f64, 10, 10>;
type Vector10 = SVector<f64, 10>;

/// Exponents of the twenty monomials of degree three or less in `(x, y, z)`: the ten
/// cubics (eliminated), then the ten of degree two or less (the action matrix's basis).
const MONOMIALS: [(u8, u8, u8); 20] = [
    (3, 0, 0),
    (0, 3, 0),
    (0, 0, 3),
    (2, 1, 0),
    (2, 0, 1),
    (1, 2, 0),
    (0, 2, 1),
    (1, 0, 2),
    (0, 1, 2),
    (1, 1, 1),
    (2, 0, 0),
    (0, 2, 0),
    (0, 0, 2),
    (1, 1, 0),
    (1, 0, 1),
    (0, 1, 1),
    (1, 0, 0),
    (0, 1, 0),
    (0, 0, 1),
    (0, 0, 0),
];
/// Where the basis monomials `x`, `y`, `z` and `1` sit in the basis (the last ten).
const BASIS_X: usize = 6;
const BASIS_Y: usize = 7;
const BASIS_Z: usize = 8;
const BASIS_ONE: usize = 9;
/// Linear polynomials hold `[x, y, z, 1]`: the basis' last four.
const LINEAR_OFFSET: usize = 16;
/// Quadratic polynomials hold the basis (monomials 10..20).
const QUADRATIC_OFFSET: usize = 10;

const fn monomial_index(e: (u8, u8, u8)) -> usize {
    let mut k = 0;
    while k < MONOMIALS.len() {
        let m = MONOMIALS[k];
        if m.0 == e.0 && m.1 == e.1 && m.2 == e.2 {
            return k;
        }
        k += 1;
    }
    usize::MAX
}

const fn product_table<const A: usize, const B: usize>(
    offset_a: usize,
    offset_b: usize,
) -> [[usize; B]; A] {
    let mut table = [[0; B]; A];
    let mut a = 0;
    while a < A {
        let mut b = 0;
        while b < B {
            let (ea, eb) = (MONOMIALS[offset_a + a], MONOMIALS[offset_b + b]);
            table[a][b] = monomial_index((ea.0 + eb.0, ea.1 + eb.1, ea.2 + eb.2));
            b += 1;
        }
        a += 1;
    }
    table
}

/// Monomial index of a linear term times a linear term, and of a quadratic times a linear.
const LINEAR_TIMES_LINEAR: [[usize; 4]; 4] = product_table::<4, 4>(LINEAR_OFFSET, LINEAR_OFFSET);
const QUADRATIC_TIMES_LINEAR: [[usize; 4]; 10] =
    product_table::<10, 4>(QUADRATIC_OFFSET, LINEAR_OFFSET);
/// The monomial `x * b` for each basis monomial `b`.
const TIMES_X: [usize; 10] = {
    let mut table = [0; 10];
    let mut k = 0;
    while k < 10 {
        let e = MONOMIALS[QUADRATIC_OFFSET + k];
        table[k] = monomial_index((e.0 + 1, e.1, e.2));
        k += 1;
    }
    table
};

type Linear = [f64; 4];
type Quadratic = [f64; 10];
type Cubic = [f64; 20];

fn linear_times_linear(a: &Linear, b: &Linear) -> Quadratic {
    let mut out = [0.0; 10];
    for (i, ai) in a.iter().enumerate() {
        for (j, bj) in b.iter().enumerate() {
            out[LINEAR_TIMES_LINEAR[i][j] - QUADRATIC_OFFSET] += ai * bj;
        }
    }
    out
}

fn quadratic_times_linear(a: &Quadratic, b: &Linear, scale: f64, out: &mut Cubic) {
    for (i, ai) in a.iter().enumerate() {
        for (j, bj) in b.iter().enumerate() {
            out[QUADRATIC_TIMES_LINEAR[i][j]] += scale * ai * bj;
        }
    }
}

fn add_scaled<const N: usize>(out: &mut [f64; N], a: &[f64; N], scale: f64) {
    for (o, v) in out.iter_mut().zip(a) {
        *o += scale * v;
    }
}

/// The four 3x3 matrices spanning the essential matrices that satisfy the five epipolar
/// constraints; `None` when the constraints are degenerate (repeated or collinear bearings).
fn null_space(bi: &[Vector3<f64>; 5], bj: &[Vector3<f64>; 5]) -> Option<[Matrix3<f64>; 4]> {
    // Row m: coefficient of E[(r, c)] (row-major index 3r + c) in b_j^T E b_i is bj[r] bi[c].
    let rows = SMatrix::<f64, 5, 9>::from_fn(|m, k| bj[m][k / 3] * bi[m][k % 3]);
    // [A1 | A2] n = 0 with A1 5x5: n = [-A1^-1 A2; I] spans the null space. The five
    // columns with the largest norms make A1: a cheap guard against a singular A1 built
    // from columns of (near) zeros.
    let mut order: [usize; 9] = [0, 1, 2, 3, 4, 5, 6, 7, 8];
    let norms: [f64; 9] = std::array::from_fn(|k| rows.column(k).norm_squared());
    order.sort_by(|&a, &b| norms[b].total_cmp(&norms[a]));
    let a1 = SMatrix::<f64, 5, 5>::from_fn(|m, k| rows[(m, order[k])]);
    let a2 = SMatrix::<f64, 5, 4>::from_fn(|m, k| rows[(m, order[5 + k])]);
    let solved = a1.lu().solve(&a2)?;
    if !solved.iter().all(|v| v.is_finite()) {
        return None;
    }
    let mut basis = [Matrix3::zeros(); 4];
    for (b, matrix) in basis.iter_mut().enumerate() {
        let mut entries = [0.0; 9];
        for k in 0..5 {
            entries[order[k]] = -solved[(k, b)];
        }
        entries[order[5 + b]] = 1.0;
        *matrix = Matrix3::from_row_slice(&entries);
    }
    Some(basis)
}

/// The ten cubic constraints as rows over [`MONOMIALS`].
fn constraints(basis: &[Matrix3<f64>; 4]) -> SMatrix<f64, 10, 20> {
    let [x, y, z, w] = basis;
    let e: [[Linear; 3]; 3] = std::array::from_fn(|r| {
        std::array::from_fn(|c| [x[(r, c)], y[(r, c)], z[(r, c)], w[(r, c)]])
    });
    let mut rows = SMatrix::<f64, 10, 20>::zeros();
    // det E by the first row's cofactors.
    let mut det = [0.0; 20];
    let minor = |r0: usize, c0: usize, r1: usize, c1: usize| {
        let mut m = linear_times_linear(&e[r0][c0], &e[r1][c1]);
        add_scaled(&mut m, &linear_times_linear(&e[r0][c1], &e[r1][c0]), -1.0);
        m
    };
    quadratic_times_linear(&minor(1, 1, 2, 2), &e[0][0], 1.0, &mut det);
    quadratic_times_linear(&minor(1, 0, 2, 2), &e[0][1], -1.0, &mut det);
    quadratic_times_linear(&minor(1, 0, 2, 1), &e[0][2], 1.0, &mut det);
    rows.row_mut(0).copy_from_slice(&det);
    // E E^T (symmetric) and its trace.
    let mut eet = [[[0.0; 10]; 3]; 3];
    for a in 0..3 {
        for b in a..3 {
            let mut s = [0.0; 10];
            for (ea, eb) in e[a].iter().zip(&e[b]) {
                add_scaled(&mut s, &linear_times_linear(ea, eb), 1.0);
            }
            eet[a][b] = s;
            eet[b][a] = s;
        }
    }
    let mut trace = [0.0; 10];
    for (a, row) in eet.iter().enumerate() {
        add_scaled(&mut trace, &row[a], 1.0);
    }
    // 2 E E^T E - tr(E E^T) E, entry by entry.
    for a in 0..3 {
        for c in 0..3 {
            let mut cubic = [0.0; 20];
            for (b, e_row) in e.iter().enumerate() {
                quadratic_times_linear(&eet[a][b], &e_row[c], 2.0, &mut cubic);
            }
            quadratic_times_linear(&trace, &e[a][c], -1.0, &mut cubic);
            rows.row_mut(1 + 3 * a + c).copy_from_slice(&cubic);
        }
    }
    rows
}

/// Eigenvector of `a` for the real eigenvalue `lambda`, by inverse iteration.
fn eigenvector(a: &Matrix10, lambda: f64) -> Option<Vector10> {
    let shift = lambda + 1e-10 * (1.0 + lambda.abs());
    let lu = (a - Matrix10::identity() * shift).lu();
    let mut v = Vector10::repeat(1.0);
    for _ in 0..3 {
        v = lu.solve(&v)?;
        let norm = v.norm();
        if !norm.is_finite() || norm == 0.0 {
            return None;
        }
        v /= norm;
    }
    Some(v)
}

/// The essential matrices (up to ten) consistent with five bearing pairs, `b_j^T E b_i = 0`
/// for camera i to camera j. Each is scaled to unit Frobenius norm.
pub fn essential_matrices(bi: &[Vector3<f64>; 5], bj: &[Vector3<f64>; 5]) -> Vec<Matrix3<f64>> {
    let Some(basis) = null_space(bi, bj) else {
        return Vec::new();
    };
    let rows = constraints(&basis);
    let cubic_part: Matrix10 = rows.fixed_columns::<10>(0).into_owned();
    let rest: Matrix10 = rows.fixed_columns::<10>(10).into_owned();
    let Some(reduced) = cubic_part.lu().solve(&rest) else {
        return Vec::new();
    };
    // Action of multiplication by x on the basis: a basis monomial times x is either a
    // basis monomial again or an eliminated cubic, which `reduced` expresses in the basis.
    let mut action = Matrix10::zeros();
    for (k, &product) in TIMES_X.iter().enumerate() {
        if product < QUADRATIC_OFFSET {
            action.row_mut(k).copy_from(&(-reduced.row(product)));
        } else {
            action[(k, product - QUADRATIC_OFFSET)] = 1.0;
        }
    }
    if !action.iter().all(|v| v.is_finite()) {
        return Vec::new();
    }
    let eigenvalues = action.complex_eigenvalues();
    let mut solutions = Vec::with_capacity(10);
    for lambda in eigenvalues.iter() {
        if lambda.im.abs() > 1e-8 * (1.0 + lambda.re.abs()) {
            continue;
        }
        // The basis is the monomial vector at a solution, up to scale.
        let Some(v) = eigenvector(&action, lambda.re) else {
            continue;
        };
        if v[BASIS_ONE].abs() < 1e-12 {
            continue;
        }
        let (x, y, z) = (
            v[BASIS_X] / v[BASIS_ONE],
            v[BASIS_Y] / v[BASIS_ONE],
            v[BASIS_Z] / v[BASIS_ONE],
        );
        let e = basis[0] * x + basis[1] * y + basis[2] * z + basis[3];
        let norm = e.norm();
        if norm.is_finite() && norm > 0.0 {
            solutions.push(e / norm);
        }
    }
    solutions
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    fn pairs(r: &Rotation3<f64>, t: &Vector3<f64>) -> ([Vector3<f64>; 5], [Vector3<f64>; 5]) {
        let points = [
            Vector3::new(0.3, -0.2, 4.0),
            Vector3::new(-1.1, 0.4, 6.0),
            Vector3::new(0.8, 0.9, 5.0),
            Vector3::new(-0.5, -0.7, 3.0),
            Vector3::new(1.5, 0.1, 8.0),
        ];
        (
            points.map(|p| p.normalize()),
            points.map(|p| (r * p + t).normalize()),
        )
    }

    #[test]
    fn the_true_essential_matrix_is_among_the_solutions() {
        let r = Rotation3::from_euler_angles(0.05, -0.2, 0.1);
        let t = Vector3::new(0.4, -0.1, 0.2);
        let (bi, bj) = pairs(&r, &t);
        let truth = crate::essential_refinement::skew(&t) * r.matrix();
        let truth = truth / truth.norm();
        let solutions = essential_matrices(&bi, &bj);
        assert!(!solutions.is_empty() && solutions.len() <= 10);
        let best = solutions
            .iter()
            .map(|e| (e - truth).norm().min((e + truth).norm()))
            .fold(f64::INFINITY, f64::min);
        assert!(best < 1e-8, "closest solution {best} from the truth");
        for e in &solutions {
            for (a, b) in bi.iter().zip(&bj) {
                assert!(b.dot(&(e * a)).abs() < 1e-9);
            }
            assert!(e.determinant().abs() < 1e-8);
        }
    }

    #[test]
    fn degenerate_samples_give_no_solution_rather_than_garbage() {
        let b = Vector3::new(0.1, 0.2, 1.0).normalize();
        assert!(essential_matrices(&[b; 5], &[b; 5]).is_empty());
    }
}
