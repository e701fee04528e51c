//! LPIPS (Zhang et al. 2018), v0.1 linear heads on a VGG16 or AlexNet trunk with ImageNet weights — the
//! `lpips` package's `LPIPS(net=…, version='0.1')` with `normalize=True` (inputs in [0, 1] mapped to [−1, 1],
//! then its ScalingLayer). Weights: the trunk file (`vgg16.safetensors` / `alexnet.safetensors`) and
//! `lpips_v0.1.safetensors` of the weights folder (see [`crate::weights`]).
//!
//! [`Lpips::forward`] is built from candle ops that record a backward, so it can serve as a training loss.

use std::path::Path;

use candle_core::{DType, Device, Result, Tensor, D};

use crate::nets::{alexnet::AlexNet, vgg::Vgg16};
use crate::weights::{self, files, MetricsWeightsError};

/// The trunk network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Net {
    Vgg,
    Alex,
}

impl Net {
    fn key(self) -> &'static str {
        match self {
            Net::Vgg => "vgg",
            Net::Alex => "alex",
        }
    }
}

#[derive(Debug, Clone)]
enum Trunk {
    Vgg(Vgg16),
    Alex(AlexNet),
}

/// Pairs per network pass in [`Lpips::distance`] (bounds memory at large resolutions).
const CHUNK: usize = 4;

/// The LPIPS metric with its pretrained weights.
#[derive(Debug, Clone)]
pub struct Lpips {
    net: Net,
    trunk: Trunk,
    /// (1, C_k, 1, 1) per tapped layer.
    heads: Vec<Tensor>,
    shift: Tensor,
    scale: Tensor,
}

impl Lpips {
    /// Loads the weights located through [`weights::locate`] (`weights_dir` = `--weights-dir`).
    pub fn load(weights_dir: Option<&Path>, net: Net, device: &Device) -> std::result::Result<Self, MetricsWeightsError> {
        let trunk_file = match net {
            Net::Vgg => files::VGG16,
            Net::Alex => files::ALEXNET,
        };
        let tw = weights::load_file(weights_dir, trunk_file, device)?;
        let hw = weights::load_file(weights_dir, files::LPIPS_HEADS, device)?;
        let trunk = match net {
            Net::Vgg => Trunk::Vgg(Vgg16::load(&tw, device)?),
            Net::Alex => Trunk::Alex(AlexNet::load(&tw, device)?),
        };
        let heads = crate::convert::lpips_channels(net == Net::Alex)
            .iter()
            .enumerate()
            .map(|(k, &c)| hw.get(&format!("{}.lin{k}.weight", net.key()), &[1, c, 1, 1]))
            .collect::<std::result::Result<Vec<_>, _>>()?;
        let shift = Tensor::from_slice(&[-0.030f32, -0.088, -0.188], (1, 3, 1, 1), device)?;
        let scale = Tensor::from_slice(&[0.458f32, 0.448, 0.450], (1, 3, 1, 1), device)?;
        Ok(Self { net, trunk, heads, shift, scale })
    }

    pub fn net(&self) -> Net {
        self.net
    }

    /// Per-pair LPIPS (N) of `a`, `b`: (N, 3, H, W) in [0, 1]. Differentiable (gradients reach `a` and `b`).
    pub fn forward(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        let (a, b) = (as_batch(a)?, as_batch(b)?);
        if a.dims() != b.dims() || a.dim(1)? != 3 {
            candle_core::bail!("lpips: inputs {:?} and {:?}, expected two (N, 3, H, W)", a.dims(), b.dims());
        }
        let n = a.dim(0)?;
        let x = Tensor::cat(&[&a, &b], 0)?.to_dtype(DType::F32)?;
        let x = ((x * 2.0)? - 1.0)?.broadcast_sub(&self.shift)?.broadcast_div(&self.scale)?;
        let feats = match &self.trunk {
            Trunk::Vgg(v) => v.features(&x)?,
            Trunk::Alex(a) => a.features(&x)?,
        };
        let mut total: Option<Tensor> = None;
        for (f, head) in feats.iter().zip(&self.heads) {
            let f = normalize(f)?;
            let d = (f.narrow(0, 0, n)? - f.narrow(0, n, n)?)?.sqr()?;
            // 1×1 conv without bias to one channel, then the spatial mean.
            let v = d.broadcast_mul(head)?.sum(1)?.flatten_from(1)?.mean(D::Minus1)?;
            total = Some(match total {
                None => v,
                Some(t) => (t + v)?,
            });
        }
        Ok(total.expect("five layers"))
    }

    /// Per-pair LPIPS of `a`, `b` ((N, 3, H, W) or (3, H, W) in [0, 1]), computed `CHUNK` pairs at a time.
    pub fn distance(&self, a: &Tensor, b: &Tensor) -> Result<Vec<f32>> {
        let (a, b) = (as_batch(a)?, as_batch(b)?);
        let n = a.dim(0)?;
        let mut out = Vec::with_capacity(n);
        for s in (0..n).step_by(CHUNK) {
            let m = CHUNK.min(n - s);
            out.extend(self.forward(&a.narrow(0, s, m)?, &b.narrow(0, s, m)?)?.to_vec1::<f32>()?);
        }
        Ok(out)
    }
}

/// (3, H, W) → (1, 3, H, W); (N, 3, H, W) unchanged.
pub(crate) fn as_batch(x: &Tensor) -> Result<Tensor> {
    match x.rank() {
        3 => x.unsqueeze(0),
        4 => Ok(x.clone()),
        r => candle_core::bail!("expected a (3, H, W) or (N, 3, H, W) image tensor, got rank {r}"),
    }
}

/// x / (‖x‖₂ over channels + 1e-10), as `lpips.normalize_tensor`.
fn normalize(x: &Tensor) -> Result<Tensor> {
    let norm = (x.sqr()?.sum_keepdim(1)?.sqrt()? + 1e-10)?;
    x.broadcast_div(&norm)
}
