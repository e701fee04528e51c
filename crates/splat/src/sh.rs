//! Real spherical harmonics in the basis MVSplat360's rasterizer uses: graphdeco's constants with the e3nn
//! axis permutation (graphdeco evaluated at (z, x, y)), degrees 0..3, including the fork's coefficient-14 quirk.

use candle_core::{Tensor, D};

use crate::error::Result;

pub const C0: f32 = 0.282_094_8;
pub const C1: f32 = 0.488_602_52;
pub const C2: [f32; 5] = [1.092_548_4, -1.092_548_4, 0.315_391_57, -1.092_548_4, 0.546_274_2];
pub const C3: [f32; 7] = [-0.590_043_6, 2.890_611_4, -0.457_045_8, 0.373_176_34, -0.457_045_8, 1.445_305_7, -0.590_043_6];

/// Number of coefficients of degrees `0..=deg`.
pub const fn num_coeffs(deg: usize) -> usize {
    (deg + 1) * (deg + 1)
}

/// Basis values of degrees `0..=deg` (deg ≤ 3) at the unit direction `d`, as the fork's forward evaluates them.
#[inline]
pub fn basis(d: [f32; 3], deg: usize, b: &mut [f32; 16]) {
    let [x, y, z] = d;
    b[0] = C0;
    if deg >= 1 {
        b[1] = -C1 * x;
        b[2] = C1 * y;
        b[3] = -C1 * z;
    }
    if deg >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        b[4] = C2[0] * z * x;
        b[5] = C2[1] * x * y;
        b[6] = C2[2] * (2.0 * yy - zz - xx);
        b[7] = C2[3] * z * y;
        b[8] = C2[4] * (zz - xx);
        if deg >= 3 {
            b[9] = C3[0] * x * (3.0 * zz - xx);
            b[10] = C3[1] * z * x * y;
            b[11] = C3[2] * x * (4.0 * yy - zz - xx);
            b[12] = C3[3] * y * (2.0 * yy - 3.0 * zz - 3.0 * xx);
            b[13] = C3[4] * z * (4.0 * yy - zz - xx);
            // The fork's forward uses z here where the permuted graphdeco basis has y (kept on purpose).
            b[14] = C3[5] * z * (zz - xx);
            b[15] = C3[6] * z * (zz - 3.0 * xx);
        }
    }
}

/// Basis values and their gradients w.r.t. the direction, as used by the backward pass.
/// `official`: coefficient 14 uses y(zz - xx) (the fork's backward); otherwise the true derivative.
#[inline]
pub fn basis_backward(d: [f32; 3], deg: usize, official: bool, b: &mut [f32; 16], g: &mut [[f32; 3]; 16]) {
    basis(d, deg, b);
    let [x, y, z] = d;
    g[0] = [0.0; 3];
    if deg >= 1 {
        g[1] = [-C1, 0.0, 0.0];
        g[2] = [0.0, C1, 0.0];
        g[3] = [0.0, 0.0, -C1];
    }
    if deg >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        g[4] = [C2[0] * z, 0.0, C2[0] * x];
        g[5] = [C2[1] * y, C2[1] * x, 0.0];
        g[6] = [-2.0 * C2[2] * x, 4.0 * C2[2] * y, -2.0 * C2[2] * z];
        g[7] = [0.0, C2[3] * z, C2[3] * y];
        g[8] = [-2.0 * C2[4] * x, 0.0, 2.0 * C2[4] * z];
        if deg >= 3 {
            g[9] = [C3[0] * (3.0 * zz - 3.0 * xx), 0.0, C3[0] * 6.0 * x * z];
            g[10] = [C3[1] * z * y, C3[1] * z * x, C3[1] * x * y];
            g[11] = [C3[2] * (4.0 * yy - zz - 3.0 * xx), C3[2] * 8.0 * x * y, -2.0 * C3[2] * x * z];
            g[12] = [-6.0 * C3[3] * x * y, C3[3] * (6.0 * yy - 3.0 * zz - 3.0 * xx), -6.0 * C3[3] * y * z];
            g[13] = [-2.0 * C3[4] * x * z, 8.0 * C3[4] * y * z, C3[4] * (4.0 * yy - 3.0 * zz - xx)];
            if official {
                b[14] = C3[5] * y * (zz - xx);
                g[14] = [-2.0 * C3[5] * x * y, C3[5] * (zz - xx), 2.0 * C3[5] * y * z];
            } else {
                g[14] = [-2.0 * C3[5] * x * z, 0.0, C3[5] * (3.0 * zz - xx)];
            }
            g[15] = [-6.0 * C3[6] * x * z, 0.0, C3[6] * (3.0 * zz - 3.0 * xx)];
        }
    }
}

/// The original graphdeco 3DGS basis (what .ply viewers evaluate), degrees 0..3, in f64.
pub fn graphdeco_basis(d: [f64; 3]) -> [f64; 16] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let c2: Vec<f64> = C2_F64.to_vec();
    let c3: Vec<f64> = C3_F64.to_vec();
    [
        C0_F64,
        -C1_F64 * y,
        C1_F64 * z,
        -C1_F64 * x,
        c2[0] * x * y,
        c2[1] * y * z,
        c2[2] * (2.0 * zz - xx - yy),
        c2[3] * x * z,
        c2[4] * (xx - yy),
        c3[0] * y * (3.0 * xx - yy),
        c3[1] * x * y * z,
        c3[2] * y * (4.0 * zz - xx - yy),
        c3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        c3[4] * x * (4.0 * zz - xx - yy),
        c3[5] * z * (xx - yy),
        c3[6] * x * (xx - 3.0 * yy),
    ]
}

/// The fork's forward basis in f64 (same formulas as [`basis`]).
pub fn fork_basis(d: [f64; 3]) -> [f64; 16] {
    let [x, y, z] = d;
    // graphdeco evaluated at (z, x, y), except coefficient 14 (see `basis`).
    let mut b = graphdeco_basis([z, x, y]);
    b[14] = C3_F64[5] * z * (z * z - x * x);
    b
}

const C0_F64: f64 = 0.282_094_791_773_878_14;
const C1_F64: f64 = 0.488_602_511_902_919_9;
const C2_F64: [f64; 5] = [1.092_548_430_592_079_2, -1.092_548_430_592_079_2, 0.315_391_565_252_520_05, -1.092_548_430_592_079_2, 0.546_274_215_296_039_6];
const C3_F64: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Deterministic, well-spread unit directions (Fibonacci sphere).
pub fn sphere_directions(n: usize) -> Vec<[f64; 3]> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - y * y).sqrt();
            let th = golden * i as f64;
            [r * th.cos(), y, r * th.sin()]
        })
        .collect()
}

/// Solve the symmetric positive (semi)definite system `(A + ridge I) x = b` by Gaussian elimination (f64).
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<Vec<f64>>, ridge: f64) -> Vec<Vec<f64>> {
    let n = a.len();
    for (i, row) in a.iter_mut().enumerate() {
        row[i] += ridge;
    }
    for col in 0..n {
        let piv = (col..n).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs())).unwrap_or(col);
        a.swap(col, piv);
        b.swap(col, piv);
        let p = a[col][col];
        if p.abs() < 1e-300 {
            continue;
        }
        for r in 0..n {
            if r != col {
                let f = a[r][col] / p;
                if f != 0.0 {
                    for c in col..n {
                        a[r][c] -= f * a[col][c];
                    }
                    for c in 0..b[r].len() {
                        b[r][c] -= f * b[col][c];
                    }
                }
            }
        }
    }
    for r in 0..n {
        let p = a[r][r];
        for v in b[r].iter_mut() {
            *v = if p.abs() < 1e-300 { 0.0 } else { *v / p };
        }
    }
    b
}

/// `X` (16×16) with `fork_k(d) = Σ_j graphdeco_j(d) X[j][k]`, so graphdeco coefficients are `c' = X c`.
/// Exact: every fork function is a polynomial of degree ≤ 3, which lies in the span of degrees 0..3.
pub fn fork_to_graphdeco_matrix() -> [[f64; 16]; 16] {
    let dirs = sphere_directions(256);
    let g: Vec<[f64; 16]> = dirs.iter().map(|&d| graphdeco_basis(d)).collect();
    let f: Vec<[f64; 16]> = dirs.iter().map(|&d| fork_basis(d)).collect();
    let mut gtg = vec![vec![0f64; 16]; 16];
    let mut gtf = vec![vec![0f64; 16]; 16];
    for (gs, fs) in g.iter().zip(&f) {
        for i in 0..16 {
            for j in 0..16 {
                gtg[i][j] += gs[i] * gs[j];
                gtf[i][j] += gs[i] * fs[j];
            }
        }
    }
    let x = solve(gtg, gtf, 0.0);
    let mut out = [[0f64; 16]; 16];
    for i in 0..16 {
        for j in 0..16 {
            let v = x[i][j];
            out[i][j] = if v.abs() < 1e-12 { 0.0 } else { v };
        }
    }
    out
}

/// Minimum-norm inverse of the top-left `k`×`k` block of [`fork_to_graphdeco_matrix`] (k ∈ {1,4,9,16}):
/// fork coefficients from graphdeco ones (zero-padded to 16×16). For k < 16 the block is an exact signed
/// permutation. For k = 16 the fork basis has rank 15 (its coefficient-14 function is a combination of
/// the others), so the one graphdeco component it cannot represent is dropped; files we wrote round-trip.
pub fn graphdeco_to_fork_matrix(k: usize) -> [[f64; 16]; 16] {
    let k = k.clamp(1, 16);
    let x = fork_to_graphdeco_matrix();
    // c = X^T (X X^T + εI)^-1 c'
    let mut xxt = vec![vec![0f64; k]; k];
    for i in 0..k {
        for j in 0..k {
            xxt[i][j] = (0..k).map(|l| x[i][l] * x[j][l]).sum();
        }
    }
    let ident: Vec<Vec<f64>> = (0..k).map(|i| (0..k).map(|j| if i == j { 1.0 } else { 0.0 }).collect()).collect();
    // The ridge keeps the rank-15 case (k = 16) well conditioned; for full-rank blocks it is negligible.
    let inv = solve(xxt, ident, 1e-9);
    let mut out = [[0f64; 16]; 16];
    for i in 0..k {
        for j in 0..k {
            out[i][j] = (0..k).map(|l| x[l][i] * inv[l][j]).sum();
        }
    }
    out
}

/// Differentiable evaluation of feature SH (degree ≤ 2, the fork's basis) + 0.5, no clamp.
/// `sh`: (N,C,K) with K ∈ {1,4,9}; `dirs`: (N,3) unit view directions. Returns (N,C).
pub fn eval_feature_sh(sh: &Tensor, dirs: &Tensor) -> Result<Tensor> {
    let k = sh.dim(D::Minus1)?;
    if sh.dim(1)? == 0 {
        // No channels: candle's CUDA sum divides by the output's size and panics on an empty one.
        return Ok(Tensor::zeros((sh.dim(0)?, 0), sh.dtype(), sh.device())?);
    }
    let x = dirs.narrow(1, 0, 1)?;
    let y = dirs.narrow(1, 1, 1)?;
    let z = dirs.narrow(1, 2, 1)?;
    let ones = x.ones_like()?;
    let mut cols = vec![(ones * C0 as f64)?];
    if k >= 4 {
        cols.push((&x * -(C1 as f64))?);
        cols.push((&y * C1 as f64)?);
        cols.push((&z * -(C1 as f64))?);
    }
    if k >= 9 {
        let (xx, yy, zz) = (x.sqr()?, y.sqr()?, z.sqr()?);
        cols.push(((&z * &x)? * C2[0] as f64)?);
        cols.push(((&x * &y)? * C2[1] as f64)?);
        cols.push((((&yy * 2.0)? - &zz)? - &xx)?.affine(C2[2] as f64, 0.0)?);
        cols.push(((&z * &y)? * C2[3] as f64)?);
        cols.push((&zz - &xx)?.affine(C2[4] as f64, 0.0)?);
    }
    let used = cols.len();
    let basis = Tensor::cat(&cols, 1)?; // (N, used)
    let sh = sh.narrow(D::Minus1, 0, used.min(k))?;
    let out = sh.broadcast_mul(&basis.unsqueeze(1)?)?.sum(D::Minus1)?;
    Ok((out + 0.5)?)
}
