//! grid_sample and upsampling custom ops: forward against a plain f64 reference of PyTorch's formulas, backward
//! against central finite differences of that reference.

use candle_core::{Device, Tensor, Var};
use mvsplat360_nn::grid_sample::grid_sample;
use mvsplat360_nn::upsample::{upsample_bilinear, upsample_nearest};

struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64) / ((1u64 << 53) as f64)
    }
    fn vec(&mut self, n: usize, lo: f64, hi: f64) -> Vec<f64> {
        (0..n).map(|_| lo + (hi - lo) * self.next()).collect()
    }
}

/// PyTorch grid_sample (bilinear, zeros, align_corners=True), written from the formula in f64.
fn grid_sample_ref(x: &[f64], g: &[f64], n: usize, c: usize, hi: usize, wi: usize, ho: usize, wo: usize) -> Vec<f64> {
    let mut out = vec![0.0; n * c * ho * wo];
    for ni in 0..n {
        for p in 0..ho * wo {
            let ix = (g[(ni * ho * wo + p) * 2] + 1.0) / 2.0 * (wi as f64 - 1.0);
            let iy = (g[(ni * ho * wo + p) * 2 + 1] + 1.0) / 2.0 * (hi as f64 - 1.0);
            let (x0, y0) = (ix.floor(), iy.floor());
            for ci in 0..c {
                let mut acc = 0.0;
                for (dx, dy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
                    let (xx, yy) = (x0 + dx, y0 + dy);
                    let w = (1.0 - (ix - xx).abs()) * (1.0 - (iy - yy).abs());
                    if xx >= 0.0 && yy >= 0.0 && xx < wi as f64 && yy < hi as f64 {
                        acc += w * x[((ni * c + ci) * hi + yy as usize) * wi + xx as usize];
                    }
                }
                out[(ni * c + ci) * ho * wo + p] = acc;
            }
        }
    }
    out
}

fn to_f32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

fn flat(t: &Tensor) -> Vec<f64> {
    t.flatten_all().unwrap().to_dtype(candle_core::DType::F64).unwrap().to_vec1().unwrap()
}

fn max_err(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}

#[test]
fn grid_sample_forward_matches_reference_and_identity() {
    let (n, c, hi, wi, ho, wo) = (2, 3, 5, 7, 4, 6);
    let mut r = Lcg(1);
    let x = r.vec(n * c * hi * wi, -1.0, 1.0);
    // Grid reaching outside [-1,1] exercises zero padding and partially outside taps.
    let g = r.vec(n * ho * wo * 2, -1.3, 1.3);
    let xt = Tensor::from_vec(to_f32(&x), (n, c, hi, wi), &Device::Cpu).unwrap();
    let gt = Tensor::from_vec(to_f32(&g), (n, ho, wo, 2), &Device::Cpu).unwrap();
    let out = grid_sample(&xt, &gt).unwrap();
    assert_eq!(out.dims(), &[n, c, ho, wo]);
    let e = max_err(&flat(&out), &grid_sample_ref(&flat(&xt), &flat(&gt), n, c, hi, wi, ho, wo));
    assert!(e < 1e-5, "forward error {e:.3e}");

    // An align_corners identity grid returns the input.
    let mut id = Vec::new();
    for _ in 0..n {
        for y in 0..hi {
            for xx in 0..wi {
                id.push(2.0 * xx as f32 / (wi - 1) as f32 - 1.0);
                id.push(2.0 * y as f32 / (hi - 1) as f32 - 1.0);
            }
        }
    }
    let idt = Tensor::from_vec(id, (n, hi, wi, 2), &Device::Cpu).unwrap();
    let e = max_err(&flat(&grid_sample(&xt, &idt).unwrap()), &flat(&xt));
    assert!(e < 1e-6, "identity grid error {e:.3e}");
}

#[test]
fn grid_sample_backward_matches_finite_differences() {
    let (n, c, hi, wi, ho, wo) = (2, 3, 4, 5, 3, 4);
    let mut r = Lcg(7);
    let x = r.vec(n * c * hi * wi, -1.0, 1.0);
    let mut g = r.vec(n * ho * wo * 2, -1.2, 1.2);
    // Keep sample points away from cell borders, where the function has kinks.
    for (i, v) in g.iter_mut().enumerate() {
        let size = if i % 2 == 0 { wi } else { hi } as f64 - 1.0;
        let p = (*v + 1.0) / 2.0 * size;
        let frac = p - p.floor();
        if !(0.05..=0.95).contains(&frac) {
            *v = ((p.floor() + 0.5) / size) * 2.0 - 1.0;
        }
    }
    let wgt = r.vec(n * c * ho * wo, -1.0, 1.0);
    let loss = |x: &[f64], g: &[f64]| -> f64 { grid_sample_ref(x, g, n, c, hi, wi, ho, wo).iter().zip(&wgt).map(|(a, b)| a * b).sum() };

    let xv = Var::from_vec(to_f32(&x), (n, c, hi, wi), &Device::Cpu).unwrap();
    let gv = Var::from_vec(to_f32(&g), (n, ho, wo, 2), &Device::Cpu).unwrap();
    let wt = Tensor::from_vec(to_f32(&wgt), (n, c, ho, wo), &Device::Cpu).unwrap();
    let l = grid_sample(xv.as_tensor(), gv.as_tensor()).unwrap().mul(&wt).unwrap().sum_all().unwrap();
    let grads = l.backward().unwrap();
    let gx = flat(grads.get(xv.as_tensor()).expect("input grad"));
    let gg = flat(grads.get(gv.as_tensor()).expect("grid grad"));

    // Use the f32-rounded values as the expansion point so both sides see the same inputs.
    let x = flat(xv.as_tensor());
    let g = flat(gv.as_tensor());
    let h = 1e-6;
    let mut ex = 0.0f64;
    for i in 0..x.len() {
        let (mut a, mut b) = (x.clone(), x.clone());
        a[i] += h;
        b[i] -= h;
        ex = ex.max(((loss(&a, &g) - loss(&b, &g)) / (2.0 * h) - gx[i]).abs());
    }
    let mut eg = 0.0f64;
    let mut gmax = 0.0f64;
    for i in 0..g.len() {
        let (mut a, mut b) = (g.clone(), g.clone());
        a[i] += h;
        b[i] -= h;
        let fd = (loss(&x, &a) - loss(&x, &b)) / (2.0 * h);
        gmax = gmax.max(fd.abs());
        eg = eg.max((fd - gg[i]).abs());
    }
    eprintln!("grid_sample grads: input max err {ex:.3e}, grid max err {eg:.3e} (max |grad| {gmax:.3e})");
    assert!(ex < 1e-5, "input gradient error {ex:.3e}");
    assert!(eg < 1e-4 * gmax.max(1.0), "grid gradient error {eg:.3e}");
    assert!(gmax > 1e-2, "degenerate grid-gradient test");
}

fn upsample_ref(x: &[f64], n: usize, c: usize, hi: usize, wi: usize, ho: usize, wo: usize) -> Vec<f64> {
    let mut out = vec![0.0; n * c * ho * wo];
    let sy = if ho > 1 { (hi as f64 - 1.0) / (ho as f64 - 1.0) } else { 0.0 };
    let sx = if wo > 1 { (wi as f64 - 1.0) / (wo as f64 - 1.0) } else { 0.0 };
    for nc in 0..n * c {
        for yo in 0..ho {
            let y = yo as f64 * sy;
            let y0 = y.floor() as usize;
            let y1 = (y0 + 1).min(hi - 1);
            let fy = y - y0 as f64;
            for xo in 0..wo {
                let xx = xo as f64 * sx;
                let x0 = xx.floor() as usize;
                let x1 = (x0 + 1).min(wi - 1);
                let fx = xx - x0 as f64;
                let p = |yy: usize, xx: usize| x[(nc * hi + yy) * wi + xx];
                out[(nc * ho + yo) * wo + xo] = (1.0 - fy) * ((1.0 - fx) * p(y0, x0) + fx * p(y0, x1)) + fy * ((1.0 - fx) * p(y1, x0) + fx * p(y1, x1));
            }
        }
    }
    out
}

#[test]
fn upsample_bilinear_forward_and_backward() {
    let mut r = Lcg(3);
    for &(n, c, hi, wi, ho, wo) in &[(2usize, 3usize, 4usize, 5usize, 16usize, 20usize), (1, 2, 3, 3, 7, 5), (1, 1, 1, 4, 3, 9)] {
        let x = r.vec(n * c * hi * wi, -1.0, 1.0);
        let xv = Var::from_vec(to_f32(&x), (n, c, hi, wi), &Device::Cpu).unwrap();
        let out = upsample_bilinear(xv.as_tensor(), (ho, wo)).unwrap();
        let x = flat(xv.as_tensor());
        let e = max_err(&flat(&out), &upsample_ref(&x, n, c, hi, wi, ho, wo));
        assert!(e < 1e-6, "upsample forward error {e:.3e} for {:?}", (hi, wi, ho, wo));

        let wgt = r.vec(n * c * ho * wo, -1.0, 1.0);
        let wt = Tensor::from_vec(to_f32(&wgt), (n, c, ho, wo), &Device::Cpu).unwrap();
        let grads = out.mul(&wt).unwrap().sum_all().unwrap().backward().unwrap();
        let gx = flat(grads.get(xv.as_tensor()).expect("input grad"));
        let wgt = flat(&wt);
        let loss = |x: &[f64]| -> f64 { upsample_ref(x, n, c, hi, wi, ho, wo).iter().zip(&wgt).map(|(a, b)| a * b).sum() };
        let h = 1e-5;
        let mut e = 0.0f64;
        for i in 0..x.len() {
            let (mut a, mut b) = (x.clone(), x.clone());
            a[i] += h;
            b[i] -= h;
            e = e.max(((loss(&a) - loss(&b)) / (2.0 * h) - gx[i]).abs());
        }
        assert!(e < 2e-5, "upsample backward error {e:.3e}");
    }
}

#[test]
fn upsample_nearest_repeats_and_has_backward() {
    let x = Var::from_vec((0..12).map(|v| v as f32).collect::<Vec<_>>(), (1, 1, 3, 4), &Device::Cpu).unwrap();
    let y = upsample_nearest(x.as_tensor(), (12, 16)).unwrap();
    let yv: Vec<Vec<f32>> = y.squeeze(0).unwrap().squeeze(0).unwrap().to_vec2().unwrap();
    for (yy, row) in yv.iter().enumerate() {
        for (xx, &v) in row.iter().enumerate() {
            assert_eq!(v, ((yy / 4) * 4 + xx / 4) as f32);
        }
    }
    let g = y.sum_all().unwrap().backward().unwrap();
    let gx = flat(g.get(x.as_tensor()).expect("grad"));
    assert!(gx.iter().all(|&v| (v - 16.0).abs() < 1e-6), "each input feeds 16 outputs: {gx:?}");
}

/// The fused warp+correlation equals grid_sample followed by the channel dot product, values and gradients.
#[test]
fn warp_correlation_matches_grid_sample_composition() {
    use mvsplat360_nn::warp_correlation::warp_correlation;
    let (n, c, h, w, d) = (2, 4, 3, 5, 3);
    let mut r = Lcg(11);
    let dev = Device::Cpu;
    let grid: Vec<f32> = to_f32(&r.vec(n * d * h * w * 2, -1.3, 1.3));
    let a = Var::from_vec(to_f32(&r.vec(n * c * h * w, -1.0, 1.0)), (n, c, h, w), &dev).unwrap();
    let b = Var::from_vec(to_f32(&r.vec(n * c * h * w, -1.0, 1.0)), (n, c, h, w), &dev).unwrap();
    let wgt = Tensor::from_vec(to_f32(&r.vec(n * d * h * w, -1.0, 1.0)), (n, d, h, w), &dev).unwrap();

    let fused = warp_correlation(a.as_tensor(), b.as_tensor(), &grid, d).unwrap();
    let g = Tensor::from_vec(grid.clone(), (n, d * h, w, 2), &dev).unwrap();
    let warped = grid_sample(b.as_tensor(), &g).unwrap().reshape((n, c, d, h, w)).unwrap();
    let composed = warped.broadcast_mul(&a.as_tensor().unsqueeze(2).unwrap()).unwrap().sum(1).unwrap();
    let e = max_err(&flat(&fused), &flat(&composed));
    assert!(e < 1e-5, "forward error {e:.3e}");

    let gf = fused.mul(&wgt).unwrap().sum_all().unwrap().backward().unwrap();
    let gc = composed.mul(&wgt).unwrap().sum_all().unwrap().backward().unwrap();
    for (name, v) in [("reference", &a), ("source", &b)] {
        let x = flat(gf.get(v.as_tensor()).expect("fused grad"));
        let y = flat(gc.get(v.as_tensor()).expect("composed grad"));
        let e = max_err(&x, &y);
        assert!(e < 1e-5, "{name} gradient error {e:.3e}");
        assert!(y.iter().any(|v| v.abs() > 1e-3), "{name}: degenerate gradient");
    }
}
