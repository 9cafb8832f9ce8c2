//! The bundle adjustment's normal equations in block form and their solution with the board
//! poses eliminated (docs/design.md §8, (35)–(38)).
//!
//! Takes JᵀWJ and JᵀW·e split into the device parameters (every lens, device pose, the side
//! transform and the bend: `m` columns, a dense block U) and one 6×6 block V_k per board
//! pose, coupled to the device parameters it shares observations with by W_k; gives damped
//! Levenberg–Marquardt steps from the reduced camera system S = U − Σ W_k·V_k⁻¹·W_kᵀ (dense
//! Cholesky of an m × m matrix, however many board poses) and the covariance of any set of
//! parameters from S⁻¹ and the per-pose blocks, without inverting the whole state.
//!
//! Every column is scaled to a unit diagonal first (Jacobi), so Marquardt's damping
//! λ·diag(JᵀWJ) becomes λ·I and the Cholesky factors see condition numbers of the geometry,
//! not of the units (pixels of focal length against radians of rotation). All sums run in a
//! fixed order: the result does not depend on the thread count.

use nalgebra::{DMatrix, DVector, Matrix6, Vector6};
use rayon::prelude::*;

/// One board pose's part of the normal equations.
#[derive(Clone, Debug)]
pub struct PoseBlock {
    /// The device-parameter columns this pose's observations touch, ascending.
    pub cols: Vec<usize>,
    /// W_k: coupling of those columns (rows) with the pose's increment (columns).
    pub w: DMatrix<f64>,
    /// V_k: the pose's own 6×6 block.
    pub v: Matrix6<f64>,
    /// The pose's part of JᵀW·e.
    pub g: Vector6<f64>,
}

/// Normal equations JᵀWJ·δ = JᵀW·e in block form.
#[derive(Clone, Debug)]
pub struct BlockSystem {
    /// U: the device parameters' block (m × m, symmetric, both triangles filled).
    pub u: DMatrix<f64>,
    /// The device parameters' part of JᵀW·e.
    pub g: DVector<f64>,
    /// One block per board pose.
    pub poses: Vec<PoseBlock>,
}

/// A solved step, in the parameters' own units.
pub struct Step {
    /// Increment of the device parameters.
    pub devices: DVector<f64>,
    /// Increment of each board pose.
    pub poses: Vec<Vector6<f64>>,
    /// Cost decrease the linear model predicts: δᵀ·g + λ·|δ|² in scaled units.
    pub predicted: f64,
}

/// A [`BlockSystem`] scaled to a unit diagonal; parameters without information (zero
/// diagonal) are held: their scale is zero, their scaled diagonal one.
pub struct Scaled {
    sys: BlockSystem,
    scale_u: DVector<f64>,
    scale_v: Vec<Vector6<f64>>,
}

/// 1/√d for an informative diagonal entry d, else 0 (held).
fn inv_sqrt(d: f64) -> f64 {
    if d > 0.0 {
        1.0 / d.sqrt()
    } else {
        0.0
    }
}

impl BlockSystem {
    /// Scale every column to a unit diagonal.
    pub fn scaled(mut self) -> Scaled {
        let m = self.u.nrows();
        let scale_u = DVector::from_fn(m, |i, _| inv_sqrt(self.u[(i, i)]));
        for j in 0..m {
            for i in 0..m {
                self.u[(i, j)] *= scale_u[i] * scale_u[j];
            }
            if scale_u[j] == 0.0 {
                self.u[(j, j)] = 1.0;
            }
        }
        self.g.component_mul_assign(&scale_u);
        let mut scale_v = Vec::with_capacity(self.poses.len());
        for b in &mut self.poses {
            let s = Vector6::from_fn(|i, _| inv_sqrt(b.v[(i, i)]));
            for j in 0..6 {
                for i in 0..6 {
                    b.v[(i, j)] *= s[i] * s[j];
                }
                if s[j] == 0.0 {
                    b.v[(j, j)] = 1.0;
                }
                for (r, &c) in b.cols.iter().enumerate() {
                    b.w[(r, j)] *= scale_u[c] * s[j];
                }
            }
            b.g.component_mul_assign(&s);
            scale_v.push(s);
        }
        Scaled {
            sys: self,
            scale_u,
            scale_v,
        }
    }
}

/// A block's local index of each of `m` device columns, given its columns `cols` in local
/// order (`u32::MAX`: not one of its columns).
pub(crate) fn local_index(cols: &[usize], m: usize) -> Vec<u32> {
    let mut at = vec![u32::MAX; m];
    for (i, &c) in cols.iter().enumerate() {
        at[c] = i as u32;
    }
    at
}

/// S −= W_k·V_k⁻¹·W_kᵀ for the poses of `chunk` (their products `xw` at the pose's
/// columns), each column of S by one thread and each entry in pose order: the same sums as
/// one thread's, for any thread count.
fn subtract_in_order(
    s: &mut DMatrix<f64>,
    chunk: &[PoseBlock],
    products: &[(DMatrix<f64>, Vector6<f64>, DMatrix<f64>)],
) {
    let m = s.nrows();
    let local: Vec<Vec<u32>> = chunk.iter().map(|b| local_index(&b.cols, m)).collect();
    s.as_mut_slice()
        .par_chunks_mut(m)
        .enumerate()
        .for_each(|(cc, column)| {
            for ((b, (_, _, xw)), at) in chunk.iter().zip(products).zip(&local) {
                let c = at[cc];
                if c == u32::MAX {
                    continue;
                }
                let from = xw.column(c as usize);
                for (a, &ca) in b.cols.iter().enumerate() {
                    column[ca] -= from[a];
                }
            }
        });
}

impl Scaled {
    /// Held parameters: the device columns, then 6 per board pose.
    pub fn held(&self) -> (Vec<bool>, Vec<[bool; 6]>) {
        (
            self.scale_u.iter().map(|s| *s == 0.0).collect(),
            self.scale_v
                .iter()
                .map(|s| std::array::from_fn(|i| s[i] == 0.0))
                .collect(),
        )
    }

    /// The reduced system S = U + λI − Σ W_k·(V_k + λI)⁻¹·W_kᵀ and its right-hand side
    /// g_U − Σ W_k·(V_k + λI)⁻¹·g_k (36), with each pose's (V_k + λI)⁻¹·[W_kᵀ g_k].
    /// `None` when a V_k + λI is not positive definite.
    #[allow(clippy::type_complexity)]
    fn reduce(
        &self,
        lambda: f64,
    ) -> Option<(
        DMatrix<f64>,
        DVector<f64>,
        Vec<(DMatrix<f64>, Vector6<f64>)>,
    )> {
        let m = self.sys.u.nrows();
        let mut s = self.sys.u.clone();
        for i in 0..m {
            s[(i, i)] += lambda;
        }
        let mut rhs = self.sys.g.clone();
        let mut solved = Vec::with_capacity(self.sys.poses.len());
        // Each pose's products in parallel, a few poses per thread at a time (bounded
        // memory), subtracted in pose order: the same sums for any thread count.
        let batch = 8 * rayon::current_num_threads().max(1);
        for chunk in self.sys.poses.chunks(batch) {
            let products = chunk
                .par_iter()
                .map(|b| {
                    let chol = (b.v + Matrix6::identity() * lambda).cholesky()?;
                    // X = W·V⁻¹ (rows: the pose's columns), y = V⁻¹·g.
                    let x = chol.solve(&b.w.transpose()).transpose();
                    let y = chol.solve(&b.g);
                    let xw = &x * b.w.transpose();
                    Some((x, y, xw))
                })
                .collect::<Option<Vec<_>>>()?;
            subtract_in_order(&mut s, chunk, &products);
            for (b, (x, y, _)) in chunk.iter().zip(products) {
                for (a, &ca) in b.cols.iter().enumerate() {
                    rhs[ca] -= x.row(a).transpose().dot(&b.g);
                }
                solved.push((x, y));
            }
        }
        Some((s, rhs, solved))
    }

    /// The damped step (JᵀWJ + λ·diag(JᵀWJ))·δ = JᵀW·e (32) by the Schur complement (36)
    /// and back-substitution (37); `None` when the reduced system is not positive definite.
    pub fn solve(&self, lambda: f64) -> Option<Step> {
        let (s, rhs, solved) = self.reduce(lambda)?;
        let du = s.cholesky()?.solve(&rhs);
        let mut predicted = du.dot(&self.sys.g) + lambda * du.norm_squared();
        // δ_k = (V_k + λI)⁻¹·(g_k − W_kᵀ·δ_U) = y_k − X_kᵀ·δ_U.
        let mut poses = Vec::with_capacity(solved.len());
        for ((b, (x, y)), s) in self.sys.poses.iter().zip(&solved).zip(&self.scale_v) {
            let mut dv = *y;
            for (a, &c) in b.cols.iter().enumerate() {
                dv -= x.row(a).transpose() * du[c];
            }
            predicted += dv.dot(&b.g) + lambda * dv.norm_squared();
            poses.push(dv.component_mul(s));
        }
        Some(Step {
            devices: du.component_mul(&self.scale_u),
            poses,
            predicted,
        })
    }

    /// The device-parameter columns the data do not determine: those with a weight above
    /// 0.1 in an eigenvector of the reduced system S (36, undamped, scaled to a unit
    /// diagonal) whose eigenvalue is below `tol` of that diagonal, ascending
    /// (docs/design.md §8, "Observability"). `None` when a board pose's own block is
    /// singular (that pose is not determined).
    pub fn null_columns(&self, tol: f64) -> Option<Vec<usize>> {
        let (s, _, _) = self.reduce(0.0)?;
        let eigen = s.symmetric_eigen();
        let mut cols = Vec::new();
        for (j, _) in eigen
            .eigenvalues
            .iter()
            .enumerate()
            .filter(|(_, v)| **v < tol)
        {
            let v = eigen.eigenvectors.column(j);
            cols.extend((0..v.len()).filter(|&i| v[i].abs() > 0.1));
        }
        cols.sort_unstable();
        cols.dedup();
        Some(cols)
    }

    /// The covariance of the parameters up to the factor σ² (38): S⁻¹ for the device
    /// parameters, with each pose's blocks kept to give any other entry. `None` when the
    /// normal equations are singular.
    pub fn covariance(&self) -> Option<Covariance> {
        let (s, _, solved) = self.reduce(0.0)?;
        let devices = s.cholesky()?.inverse();
        let poses = self
            .sys
            .poses
            .iter()
            .zip(solved)
            .map(|(b, (x, _))| {
                let vinv = b.v.cholesky().map(|c| c.inverse())?;
                Some(PoseCovariance {
                    cols: b.cols.clone(),
                    x,
                    vinv,
                })
            })
            .collect::<Option<Vec<_>>>()?;
        Some(Covariance {
            devices,
            poses,
            scale_u: self.scale_u.clone(),
            scale_v: self.scale_v.clone(),
            factor: 1.0,
        })
    }
}

/// A board pose's share of the covariance: X_k = W_k·V_k⁻¹ and V_k⁻¹ (scaled units).
#[derive(Clone, Debug)]
struct PoseCovariance {
    cols: Vec<usize>,
    x: DMatrix<f64>,
    vinv: Matrix6<f64>,
}

/// The parameters' covariance σ²·(JᵀWJ)⁻¹ in block form (38): with Σ = S⁻¹,
/// Cov(U) = Σ, Cov(U, b_k) = −Σ·X_k, Cov(b_k, b_l) = δ_kl·V_k⁻¹ + X_kᵀ·Σ·X_l. Indices are
/// those of the state: the device parameters, then 6 per board pose; held parameters have
/// zero rows and columns.
#[derive(Clone, Debug)]
pub struct Covariance {
    devices: DMatrix<f64>,
    poses: Vec<PoseCovariance>,
    scale_u: DVector<f64>,
    scale_v: Vec<Vector6<f64>>,
    factor: f64,
}

impl Covariance {
    /// The same covariance times `factor` (σ̂²).
    pub fn times(mut self, factor: f64) -> Covariance {
        self.factor *= factor;
        self
    }

    /// Parameters in the state.
    pub fn len(&self) -> usize {
        self.devices.nrows() + 6 * self.poses.len()
    }

    /// Whether there is no parameter.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    #[allow(clippy::type_complexity)]
    /// State index `i` as a combination of the reduced system's unknowns (a column of
    /// [−X_k; I] or a unit vector), its scale and, for a pose entry, (pose, component).
    fn column(&self, i: usize) -> (Vec<(usize, f64)>, f64, Option<(usize, usize)>) {
        let m = self.devices.nrows();
        if i < m {
            return (vec![(i, 1.0)], self.scale_u[i], None);
        }
        let (k, t) = ((i - m) / 6, (i - m) % 6);
        let pc = &self.poses[k];
        let a = pc
            .cols
            .iter()
            .enumerate()
            .map(|(r, &c)| (c, -pc.x[(r, t)]))
            .collect();
        (a, self.scale_v[k][t], Some((k, t)))
    }

    /// The covariance of the parameters `idx` (state indices), as a dense matrix.
    pub fn block(&self, idx: &[usize]) -> DMatrix<f64> {
        let cols: Vec<_> = idx.iter().map(|&i| self.column(i)).collect();
        // Σ·a_j for every column, then a_iᵀ·(Σ·a_j).
        let sa: Vec<DVector<f64>> = cols
            .iter()
            .map(|(a, _, _)| {
                let mut v = DVector::zeros(self.devices.nrows());
                for &(c, w) in a {
                    v.axpy(w, &self.devices.column(c), 1.0);
                }
                v
            })
            .collect();
        DMatrix::from_fn(idx.len(), idx.len(), |r, c| {
            let (a, sr, pr) = &cols[r];
            let (_, sc, pc) = &cols[c];
            let mut v: f64 = a.iter().map(|&(i, w)| w * sa[c][i]).sum();
            if let (Some((k, t)), Some((l, u))) = (pr, pc) {
                if k == l {
                    v += self.poses[*k].vinv[(*t, *u)];
                }
            }
            self.factor * sr * sc * v
        })
    }

    /// The variance of parameter `i`.
    pub fn variance(&self, i: usize) -> f64 {
        self.block(&[i])[(0, 0)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A random sparse-structured system: 7 device columns (one held), 3 poses.
    fn system() -> (BlockSystem, DMatrix<f64>, DVector<f64>) {
        let (m, k) = (7, 3);
        let n = m + 6 * k;
        // J with rows touching a few device columns and one pose each; column 2 untouched.
        let mut rows = Vec::new();
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        for pose in 0..k {
            for r in 0..20 {
                let mut row = DVector::zeros(n);
                for c in [0, 1, 3, 4, 5, 6] {
                    if (r + c + pose) % 3 != 0 {
                        row[c] = rnd() * 10f64.powi(c as i32 - 3);
                    }
                }
                for t in 0..6 {
                    row[m + 6 * pose + t] = rnd() * 100.0;
                }
                rows.push((row, rnd()));
            }
        }
        let mut a = DMatrix::zeros(n, n);
        let mut g = DVector::zeros(n);
        for (row, e) in &rows {
            a += row * row.transpose();
            g += row * *e;
        }
        let poses = (0..k)
            .map(|p| {
                let at = m + 6 * p;
                let cols: Vec<usize> = vec![0, 1, 3, 4, 5, 6];
                PoseBlock {
                    w: DMatrix::from_fn(cols.len(), 6, |r, t| a[(cols[r], at + t)]),
                    cols,
                    v: Matrix6::from_fn(|i, j| a[(at + i, at + j)]),
                    g: Vector6::from_fn(|i, _| g[at + i]),
                }
            })
            .collect();
        let sys = BlockSystem {
            u: a.view((0, 0), (m, m)).into_owned(),
            g: g.rows(0, m).into_owned(),
            poses,
        };
        (sys, a, g)
    }

    #[test]
    fn schur_steps_and_covariance_equal_the_dense_solution() {
        let (sys, a, g) = system();
        let m = sys.u.nrows();
        let n = a.nrows();
        let scaled = sys.scaled();
        assert_eq!(scaled.held().0, (0..m).map(|i| i == 2).collect::<Vec<_>>());
        // The dense damped solve with column 2 held.
        let keep: Vec<usize> = (0..n).filter(|&i| i != 2).collect();
        let sub = DMatrix::from_fn(keep.len(), keep.len(), |r, c| a[(keep[r], keep[c])]);
        for lambda in [0.0, 1e-3, 0.5] {
            let mut damped = sub.clone();
            for i in 0..keep.len() {
                damped[(i, i)] *= 1.0 + lambda;
            }
            let rhs = DVector::from_fn(keep.len(), |r, _| g[keep[r]]);
            let dense = damped.clone().cholesky().unwrap().solve(&rhs);
            let step = scaled.solve(lambda).unwrap();
            let mut full = DVector::zeros(n);
            full.rows_mut(0, m).copy_from(&step.devices);
            for (k, d) in step.poses.iter().enumerate() {
                full.fixed_rows_mut::<6>(m + 6 * k).copy_from(d);
            }
            assert_eq!(full[2], 0.0);
            for (r, &i) in keep.iter().enumerate() {
                assert!(
                    (full[i] - dense[r]).abs() < 1e-9 * (1.0 + dense[r].abs()),
                    "λ {lambda}, parameter {i}: {} vs {}",
                    full[i],
                    dense[r]
                );
            }
            // Predicted decrease δᵀg + λ·δᵀDδ.
            let d_diag: f64 = (0..keep.len())
                .map(|r| sub[(r, r)] * dense[r] * dense[r])
                .sum();
            let predicted = dense.dot(&rhs) + lambda * d_diag;
            assert!((step.predicted - predicted).abs() < 1e-9 * predicted.abs());
        }
        let cov = scaled.covariance().unwrap();
        let inverse = sub.cholesky().unwrap().inverse();
        let idx: Vec<usize> = (0..n).collect();
        let block = cov.times(4.0).block(&idx);
        for (r, &i) in keep.iter().enumerate() {
            for (c, &j) in keep.iter().enumerate() {
                let want = 4.0 * inverse[(r, c)];
                assert!(
                    (block[(i, j)] - want).abs()
                        < 1e-8 * (inverse[(r, r)] * inverse[(c, c)]).sqrt(),
                    "({i}, {j}): {} vs {want}",
                    block[(i, j)]
                );
            }
            assert_eq!(block[(i, 2)], 0.0);
        }
    }
}
