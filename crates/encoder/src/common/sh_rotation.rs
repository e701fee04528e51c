//! Rotation of real spherical harmonics (`misc/sh_rotation.py`), reproducing e3nn 0.6.0: angles from
//! `matrix_to_angles` (computed in f32 like the official f32 run), then
//! `D_l(α,β,γ) = exp(α·X_y) · exp(β·X_x) · exp(γ·X_y)` with e3nn's real-basis SO(3) generators (in f64).

use candle_core::{Device, Result, Tensor};

#[derive(Debug, Clone, Copy, Default)]
struct C64 {
    re: f64,
    im: f64,
}

impl C64 {
    fn new(re: f64, im: f64) -> Self {
        Self { re, im }
    }
    fn mul(self, o: Self) -> Self {
        Self::new(self.re * o.re - self.im * o.im, self.re * o.im + self.im * o.re)
    }
    fn add(self, o: Self) -> Self {
        Self::new(self.re + o.re, self.im + o.im)
    }
    fn conj(self) -> Self {
        Self::new(self.re, -self.im)
    }
}

type CMat = Vec<C64>;

fn cmatmul(a: &CMat, b: &CMat, n: usize) -> CMat {
    let mut c = vec![C64::default(); n * n];
    for i in 0..n {
        for k in 0..n {
            let aik = a[i * n + k];
            for j in 0..n {
                c[i * n + j] = c[i * n + j].add(aik.mul(b[k * n + j]));
            }
        }
    }
    c
}

/// e3nn `so3_generators(l)`: the real generators `[X_x, X_y(“z” of SU(2)), X_3]` of size (2l+1)², row-major.
pub fn so3_generators(l: usize) -> [Vec<f64>; 3] {
    let n = 2 * l + 1;
    let j = l as f64;
    let mut raising = vec![C64::default(); n * n];
    let mut lowering = vec![C64::default(); n * n];
    for i in 0..n - 1 {
        let m = -j + i as f64;
        raising[(i + 1) * n + i] = C64::new(-(j * (j + 1.0) - m * (m + 1.0)).sqrt(), 0.0);
        let m = -j + 1.0 + i as f64;
        lowering[i * n + i + 1] = C64::new((j * (j + 1.0) - m * (m - 1.0)).sqrt(), 0.0);
    }
    let mut su2 = [vec![C64::default(); n * n], vec![C64::default(); n * n], vec![C64::default(); n * n]];
    for e in 0..n * n {
        let (r, lo) = (raising[e], lowering[e]);
        su2[0][e] = C64::new(0.5 * (r.re + lo.re), 0.5 * (r.im + lo.im));
        // −0.5i·(raising − lowering)
        let d = C64::new(r.re - lo.re, r.im - lo.im);
        su2[2][e] = C64::new(0.5 * d.im, -0.5 * d.re);
    }
    for i in 0..n {
        su2[1][i * n + i] = C64::new(0.0, -j + i as f64);
    }
    // change_basis_real_to_complex (its global factor (−i)^l cancels in Q^H·X·Q).
    let s = 1.0 / 2f64.sqrt();
    let mut q = vec![C64::default(); n * n];
    for mm in 1..=l {
        // m = −mm
        q[(l - mm) * n + l + mm] = C64::new(s, 0.0);
        q[(l - mm) * n + l - mm] = C64::new(0.0, -s);
    }
    q[l * n + l] = C64::new(1.0, 0.0);
    for m in 1..=l {
        let sign = if m % 2 == 0 { 1.0 } else { -1.0 };
        q[(l + m) * n + l + m] = C64::new(sign * s, 0.0);
        q[(l + m) * n + l - m] = C64::new(0.0, sign * s);
    }
    let mut qh = vec![C64::default(); n * n];
    for r in 0..n {
        for c in 0..n {
            qh[r * n + c] = q[c * n + r].conj();
        }
    }
    let real = |x: &CMat| -> Vec<f64> { cmatmul(&cmatmul(&qh, x, n), &q, n).iter().map(|z| z.re).collect() };
    [real(&su2[0]), real(&su2[1]), real(&su2[2])]
}

fn matmul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let mut c = vec![0.0; n * n];
    for i in 0..n {
        for k in 0..n {
            let aik = a[i * n + k];
            if aik != 0.0 {
                for j in 0..n {
                    c[i * n + j] += aik * b[k * n + j];
                }
            }
        }
    }
    c
}

/// Matrix exponential (scaling and squaring + Taylor), accurate to f64 rounding for the small matrices here.
fn expm(a: &[f64], n: usize) -> Vec<f64> {
    let norm = a.iter().map(|x| x.abs()).sum::<f64>();
    let mut s = 0;
    while norm / f64::from(1u32 << s.min(30)) > 0.25 && s < 30 {
        s += 1;
    }
    let scaled: Vec<f64> = a.iter().map(|x| x / f64::from(1u32 << s)).collect();
    let mut result = vec![0.0; n * n];
    let mut term = vec![0.0; n * n];
    for i in 0..n {
        result[i * n + i] = 1.0;
        term[i * n + i] = 1.0;
    }
    for k in 1..30 {
        term = matmul(&term, &scaled, n).into_iter().map(|x| x / k as f64).collect();
        for (r, t) in result.iter_mut().zip(&term) {
            *r += t;
        }
    }
    for _ in 0..s {
        result = matmul(&result, &result, n);
    }
    result
}

/// e3nn `wigner_D(l, α, β, γ)` (row-major (2l+1)²). Angles are reduced mod 2π in f32 first, as e3nn does
/// on f32 tensors.
pub fn wigner_d(l: usize, alpha: f32, beta: f32, gamma: f32) -> Vec<f64> {
    let n = 2 * l + 1;
    let two_pi = std::f32::consts::TAU;
    let md = |a: f32| -> f64 { (a - (a / two_pi).floor() * two_pi) as f64 };
    let x = so3_generators(l);
    let e = |ang: f64, g: &[f64]| expm(&g.iter().map(|v| v * ang).collect::<Vec<_>>(), n);
    matmul(&matmul(&e(md(alpha), &x[1]), &e(md(beta), &x[0]), n), &e(md(gamma), &x[1]), n)
}

fn mat3_mul(a: &[[f32; 3]; 3], b: &[[f32; 3]; 3]) -> [[f32; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j]))
}

/// e3nn `matrix_to_angles(R)` in f32: (α, β) of R·ŷ, then γ from the remaining rotation about y.
pub fn matrix_to_angles(r: &[[f32; 3]; 3]) -> (f32, f32, f32) {
    let x = [r[0][1], r[1][1], r[2][1]];
    let norm = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt().max(1e-12);
    let x = x.map(|v| (v / norm).clamp(-1.0, 1.0));
    let beta = x[1].acos();
    let alpha = x[0].atan2(x[2]);
    let (ca, sa) = (alpha.cos(), alpha.sin());
    let (cb, sb) = (beta.cos(), beta.sin());
    let my = [[ca, 0.0, sa], [0.0, 1.0, 0.0], [-sa, 0.0, ca]];
    let mx = [[1.0, 0.0, 0.0], [0.0, cb, -sb], [0.0, sb, cb]];
    let m = mat3_mul(&my, &mx);
    let mt: [[f32; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]));
    let r2 = mat3_mul(&mt, r);
    (alpha, beta, r2[0][2].atan2(r2[0][0]))
}

/// Block-diagonal SH rotation `[..., n_sh, n_sh]` (blocks D_0..D_L, f32 as the official `.type(dtype)`) for each
/// rotation `rotations [..., 3, 3]` (c2w).
pub fn sh_rotation_matrices(rotations: &Tensor, degree: usize) -> Result<Tensor> {
    let dims = rotations.dims().to_vec();
    if dims.len() < 2 || dims[dims.len() - 1] != 3 || dims[dims.len() - 2] != 3 {
        candle_core::bail!("sh rotation: expected [..., 3, 3] rotations, got {dims:?}");
    }
    let r = rotations.to_dtype(candle_core::DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let count = r.len() / 9;
    let n_sh = (degree + 1) * (degree + 1);
    let mut out = vec![0f32; count * n_sh * n_sh];
    for i in 0..count {
        let m: [[f32; 3]; 3] = std::array::from_fn(|a| std::array::from_fn(|b| r[i * 9 + a * 3 + b]));
        let (al, be, ga) = matrix_to_angles(&m);
        for l in 0..=degree {
            let d = wigner_d(l, al, be, ga);
            let n = 2 * l + 1;
            let o = l * l;
            for a in 0..n {
                for b in 0..n {
                    out[i * n_sh * n_sh + (o + a) * n_sh + o + b] = d[a * n + b] as f32;
                }
            }
        }
    }
    let mut shape = dims[..dims.len() - 2].to_vec();
    shape.extend_from_slice(&[n_sh, n_sh]);
    Tensor::from_vec(out, shape, &Device::Cpu)?.to_device(rotations.device())
}

/// `rotate_sh`: `sh [B, V, ..., n_sh]` rotated by the per-view `rot [B, V, n_sh, n_sh]` (`sh · Dᵀ`).
pub fn rotate_sh(sh: &Tensor, rot: &Tensor) -> Result<Tensor> {
    let dims = sh.dims().to_vec();
    let (b, v, n, _) = rot.dims4()?;
    if dims.len() < 3 || dims[0] != b || dims[1] != v || dims[dims.len() - 1] != n {
        candle_core::bail!("rotate_sh: sh {dims:?} does not match per-view rotations {:?}", rot.dims());
    }
    let rows = sh.elem_count() / (b * v * n).max(1);
    let rt = rot.reshape((b * v, n, n))?.transpose(1, 2)?.contiguous()?;
    sh.contiguous()?.reshape((b * v, rows, n))?.matmul(&rt)?.reshape(dims)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rot(ax: [f64; 3], ang: f64) -> [[f32; 3]; 3] {
        let n = (ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2]).sqrt();
        let (x, y, z) = (ax[0] / n, ax[1] / n, ax[2] / n);
        let (c, s) = (ang.cos(), ang.sin());
        let t = 1.0 - c;
        let m = [
            [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
            [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
            [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
        ];
        m.map(|r| r.map(|v| v as f32))
    }

    #[test]
    fn wigner_d_is_orthogonal_and_a_homomorphism() {
        let r1 = rot([0.3, -1.0, 0.5], 1.1);
        let r2 = rot([1.0, 0.2, -0.4], -2.3);
        let r12 = mat3_mul(&r1, &r2);
        for l in 0..=4 {
            let n = 2 * l + 1;
            let d = |r: &[[f32; 3]; 3]| {
                let (a, b, g) = matrix_to_angles(r);
                wigner_d(l, a, b, g)
            };
            let (d1, d2, d12) = (d(&r1), d(&r2), d(&r12));
            let mut dt = vec![0.0; n * n];
            for i in 0..n {
                for j in 0..n {
                    dt[i * n + j] = d1[j * n + i];
                }
            }
            let id = matmul(&d1, &dt, n);
            let prod = matmul(&d1, &d2, n);
            for i in 0..n {
                for j in 0..n {
                    let e = if i == j { 1.0 } else { 0.0 };
                    assert!((id[i * n + j] - e).abs() < 1e-9, "l={l}: D·Dᵀ ≠ I");
                    assert!((prod[i * n + j] - d12[i * n + j]).abs() < 1e-5, "l={l}: D(R1)D(R2) ≠ D(R1R2)");
                }
            }
        }
    }

    #[test]
    fn angles_reproduce_the_matrix() {
        let r = rot([0.2, 0.9, -0.3], 0.8);
        let (a, b, g) = matrix_to_angles(&r);
        let my = |t: f32| [[t.cos(), 0.0, t.sin()], [0.0, 1.0, 0.0], [-t.sin(), 0.0, t.cos()]];
        let mx = |t: f32| [[1.0, 0.0, 0.0], [0.0, t.cos(), -t.sin()], [0.0, t.sin(), t.cos()]];
        let back = mat3_mul(&mat3_mul(&my(a), &mx(b)), &my(g));
        for i in 0..3 {
            for j in 0..3 {
                assert!((back[i][j] - r[i][j]).abs() < 1e-5);
            }
        }
    }
}
