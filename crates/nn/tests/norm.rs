//! The trainable GroupNorm / InstanceNorm (one CPU op with an analytic backward) against the normalisation
//! written out in f64 candle ops (candle's autograd gives the reference gradients), forward and every gradient.

use candle_core::{DType, Device, Tensor, Var};
use mvsplat360_nn::norm::{group_norm, group_norm_act, instance_norm, Act};

/// GroupNorm(groups) with affine parameters from f64 tensor ops.
fn reference(x: &Tensor, w: &Tensor, b: &Tensor, groups: usize, eps: f64) -> Tensor {
    reference_frames(x, w, b, groups, 1, eps)
}

/// The same with statistics pooled over `frames` consecutive items (a temporal ResBlock's GroupNorm).
fn reference_frames(x: &Tensor, w: &Tensor, b: &Tensor, groups: usize, frames: usize, eps: f64) -> Tensor {
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    let xg = x.reshape((n / frames, frames, groups, ())).unwrap();
    let mean = xg.mean_keepdim(3).unwrap().mean_keepdim(1).unwrap();
    let xc = xg.broadcast_sub(&mean).unwrap();
    let var = xc.sqr().unwrap().mean_keepdim(3).unwrap().mean_keepdim(1).unwrap();
    let xn = xc.broadcast_div(&(var + eps).unwrap().sqrt().unwrap()).unwrap().reshape((n, c, ())).unwrap();
    let y = xn.broadcast_mul(&w.reshape((1, c, 1)).unwrap()).unwrap().broadcast_add(&b.reshape((1, c, 1)).unwrap()).unwrap();
    y.reshape(dims).unwrap()
}

fn rel_err(a: &Tensor, b: &Tensor) -> f64 {
    let a = a.to_dtype(DType::F64).unwrap().flatten_all().unwrap().to_vec1::<f64>().unwrap();
    let b = b.to_dtype(DType::F64).unwrap().flatten_all().unwrap().to_vec1::<f64>().unwrap();
    let scale = b.iter().fold(0f64, |m, v| m.max(v.abs())).max(1e-12);
    a.iter().zip(&b).fold(0f64, |m, (x, y)| m.max((x - y).abs())) / scale
}

/// (ours, reference) outputs and the (x, w, b) gradients of Σ y·r for both; `frames` > 1 goes through the
/// refiner's `group_norm`.
fn compare(x0: &Tensor, groups: usize, instance: bool, silu: bool) {
    compare_frames(x0, groups, 1, instance, silu)
}

fn compare_frames(x0: &Tensor, groups: usize, frames: usize, instance: bool, silu: bool) {
    let d = Device::Cpu;
    let c = x0.dim(1).unwrap();
    let x = Var::from_tensor(x0).unwrap();
    let w = Var::from_tensor(&Tensor::randn(1f32, 0.5, c, &d).unwrap()).unwrap();
    let b = Var::from_tensor(&Tensor::randn(0f32, 0.5, c, &d).unwrap()).unwrap();
    // The refiner's kernels record a backward only in differentiable mode (its training turns it on).
    let _mode = mvsplat360_nn::mode::differentiable();
    let ours = if instance {
        instance_norm(x.as_tensor()).unwrap()
    } else if frames > 1 {
        group_norm(x.as_tensor(), groups, frames, w.as_tensor(), b.as_tensor(), 1e-5, silu).unwrap()
    } else {
        group_norm_act(x.as_tensor(), w.as_tensor(), b.as_tensor(), groups, 1e-5, if silu { Act::Silu } else { Act::None }).unwrap()
    };
    let f64v = |t: &Tensor| Var::from_tensor(&t.to_dtype(DType::F64).unwrap()).unwrap();
    let (xr, wr, br) = (f64v(x.as_tensor()), f64v(w.as_tensor()), f64v(b.as_tensor()));
    let theirs = if instance {
        let (ones, zeros) = (Tensor::ones(c, DType::F64, &d).unwrap(), Tensor::zeros(c, DType::F64, &d).unwrap());
        reference(xr.as_tensor(), &ones, &zeros, c, 1e-5)
    } else {
        let y = reference_frames(xr.as_tensor(), wr.as_tensor(), br.as_tensor(), groups, frames, 1e-5);
        if silu {
            y.silu().unwrap()
        } else {
            y
        }
    };
    assert!(rel_err(&ours, &theirs) < 1e-5, "forward differs by {} (groups {groups}, instance {instance})", rel_err(&ours, &theirs));
    let r = Tensor::randn(0f32, 1.0, ours.dims(), &d).unwrap();
    let g1 = (&ours * &r).unwrap().sum_all().unwrap().backward().unwrap();
    let g2 = (&theirs * &r.to_dtype(DType::F64).unwrap()).unwrap().sum_all().unwrap().backward().unwrap();
    let mut pairs = vec![("input", &x, &xr)];
    if !instance {
        pairs.push(("weight", &w, &wr));
        pairs.push(("bias", &b, &br));
    }
    for (name, v, vr) in pairs {
        let e = rel_err(g1.get(v.as_tensor()).unwrap(), g2.get(vr.as_tensor()).unwrap());
        assert!(e < 1e-4, "{name} gradient differs by {e} relative to its largest entry (groups {groups}, instance {instance}, silu {silu})");
    }
}

#[test]
fn group_norm_matches_the_composed_normalisation_and_its_gradients() {
    let d = Device::Cpu;
    // Inputs away from mean 0 / std 1, so that the statistics matter.
    for &(n, c, h, w, groups, silu) in &[(2usize, 8usize, 5usize, 7usize, 4usize, false), (3, 6, 4, 4, 3, true), (1, 16, 9, 3, 8, false), (2, 4, 6, 5, 1, true)]
    {
        let x = (Tensor::randn(0f32, 2.0, (n, c, h, w), &d).unwrap() + 3.0).unwrap();
        compare(&x, groups, false, silu);
    }
}

#[test]
fn instance_norm_matches_the_composed_normalisation_and_its_gradient() {
    let d = Device::Cpu;
    for &(n, c, h, w) in &[(2usize, 5usize, 6usize, 7usize), (5, 3, 4, 8)] {
        let x = (Tensor::randn(0f32, 1.5, (n, c, h, w), &d).unwrap() - 1.0).unwrap();
        compare(&x, c, true, false);
    }
}

#[test]
fn group_norm_over_frames_matches_the_composed_normalisation_and_its_gradients() {
    let d = Device::Cpu;
    // (items, channels, h, w, groups, frames, silu): one and two videos, statistics pooled over the frames.
    for &(n, c, h, w, groups, frames, silu) in &[(6usize, 8usize, 3usize, 5usize, 4usize, 3usize, true), (4, 6, 4, 4, 2, 4, false), (4, 4, 2, 3, 4, 2, true)] {
        let x = (Tensor::randn(0f32, 1.5, (n, c, h, w), &d).unwrap() + 2.0).unwrap();
        compare_frames(&x, groups, frames, false, silu);
    }
}
