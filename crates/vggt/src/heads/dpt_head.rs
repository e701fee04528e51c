//! `DPTHead` (Ranftl et al., "Vision Transformers for Dense Prediction") on four of the aggregator's layers:
//! per layer LayerNorm, a 1×1 projection, the UV positional embedding, a resize to 4×, 2×, 1× and ½× the
//! patch grid; RefineNet-style fusion from coarse to fine; a 3×3 conv; bilinear (align_corners) to the image
//! size; the embedding again; a 3×3 conv, ReLU, 1×1 conv to the outputs. Runs in f32 whatever the trunk's
//! dtype (upstream disables autocast for the heads), except with the CPU's packed bf16 trunk, where
//! [`DptHead::pack_bf16`] puts the products in bf16 too (activations, transforms and sums stay f32).

use std::collections::BTreeMap;

use std::sync::Arc;

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use mvsplat360_nn::bf16::Bf16Weights;
use mvsplat360_nn::conv::bf16::{conv2d_fused_bf16, Bf16ConvWeights};
use mvsplat360_nn::conv::{Winograd3x3, WinogradEpilogue};
use mvsplat360_nn::{conv2d, Conv2dConfig, ConvEpilogue};

use super::head_act::{activate_head, Activation};
use super::utils::position_embed_uv;
use crate::config::DptConfig;
use crate::layers::{LayerNorm, PackedBf16, TORCH_LN_EPS};

/// A conv weight packed for `nn`'s bf16 convolution (shared by clones).
#[derive(Clone)]
pub struct PackedConvBf16(pub Arc<Bf16ConvWeights>);

impl std::fmt::Debug for PackedConvBf16 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PackedConvBf16{:?}", self.0.dims())
    }
}

/// Whether a packed bf16 product applies to `x`: a CPU f32 input at inference (else the f32 weights).
fn bf16_applies(x: &Tensor) -> bool {
    x.device().is_cpu() && x.dtype() == candle_core::DType::F32 && !mvsplat360_nn::mode::is_differentiable() && !x.track_op()
}

#[derive(Debug, Clone)]
pub struct Conv {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
    pub cfg: Conv2dConfig,
    /// 3×3, stride 1, padding 1 with CPU f32 weights: the Winograd F(2×2, 3×3) kernel, weights transformed
    /// here once (16/9 of the weight's memory; ≈ 2× faster than the shifted gemms on 2 Zen 4 cores, issue 69).
    /// Its forward falls back to `conv2d` itself where it does not apply (another device or dtype, autograd).
    pub winograd: Option<Winograd3x3>,
    /// The weight packed for `nn`'s bf16 convolution ([`Conv::pack_bf16`], convs without a Winograd kernel).
    pub packed: Option<PackedConvBf16>,
}

impl Conv {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, k: usize, stride: usize, padding: usize, bias: bool) -> Result<Self> {
        let weight = vb.get((c_out, c_in, k, k), "weight")?;
        let bias = if bias { Some(vb.get(c_out, "bias")?) } else { None };
        let winograd =
            if k == 3 && stride == 1 && padding == 1 { Some(Winograd3x3::new(&weight, bias.as_ref())?).filter(|w| w.is_transformed()) } else { None };
        Ok(Self { weight, bias, cfg: Conv2dConfig { padding, stride, dilation: 1 }, winograd, packed: None })
    }

    /// Products in bf16 (issue 73): the Winograd kernel's transformed weights held in bf16 only
    /// ([`Winograd3x3::new_bf16`]), any other conv packed for `conv2d_fused_bf16`. Storage only where the
    /// calling thread's `nn::bf16::path` lacks AVX512-BF16 (the bf16 weights widened, f32 arithmetic).
    pub fn pack_bf16(&mut self) -> Result<()> {
        if self.winograd.is_some() {
            self.winograd = Some(Winograd3x3::new_bf16(&self.weight, self.bias.as_ref())?);
        } else if self.packed.is_none() {
            self.packed = Some(PackedConvBf16(Arc::new(Bf16ConvWeights::from_conv(&self.weight)?)));
        }
        Ok(())
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match (&self.winograd, &self.packed) {
            (Some(w), _) => w.forward(x),
            (None, Some(p)) if bf16_applies(x) => conv2d_fused_bf16(x, &p.0, self.bias.as_ref(), self.cfg, ConvEpilogue::default()),
            _ => conv2d(x, &self.weight, self.bias.as_ref(), self.cfg),
        }
    }
}

/// `nn.ConvTranspose2d` with kernel = stride, no padding: patches do not overlap, so each input pixel's
/// `k × k` output block is one row of a gemm with the weight `(C_in, C_out·k·k)`.
#[derive(Debug, Clone)]
pub struct ConvTransposePatch {
    /// `(C_out·k·k, C_in)`: the transposed-convolution weight `(C_in, C_out, k, k)` as a linear layer.
    pub weight: Tensor,
    /// The bias repeated over each output channel's `k × k` block: `(C_out·k·k)`, the linear layer's bias.
    pub bias: Tensor,
    pub k: usize,
    pub c_out: usize,
    /// The weight packed for `nn`'s bf16 product ([`ConvTransposePatch::pack_bf16`]).
    pub packed: Option<PackedBf16>,
}

impl ConvTransposePatch {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, k: usize) -> Result<Self> {
        let w = vb.get((c_in, c_out, k, k), "weight")?;
        let bias = vb.get(c_out, "bias")?.reshape((c_out, 1))?.broadcast_as((c_out, k * k))?.contiguous()?.reshape(c_out * k * k)?;
        Ok(Self { weight: w.reshape((c_in, c_out * k * k))?.t()?.contiguous()?, bias, k, c_out, packed: None })
    }

    /// The gemm in bf16 (`linear_fused_bf16`; storage only without AVX512-BF16).
    pub fn pack_bf16(&mut self) -> Result<()> {
        self.packed = Some(PackedBf16(Arc::new(Bf16Weights::from_linear(&self.weight)?)));
        Ok(())
    }

    /// `rows (n·h·w, C_in)`: the input pixels row-major (the tokens' layout) → `(n, C_out, h·k, w·k)`.
    pub fn forward_rows(&self, rows: &Tensor, n: usize, h: usize, w: usize) -> Result<Tensor> {
        let k = self.k;
        let y = match &self.packed {
            Some(p) if bf16_applies(rows) => mvsplat360_nn::linear::linear_fused_bf16(rows, &p.0, Some(&self.bias), 1.0, &[])?,
            _ => mvsplat360_nn::linear::linear_fused(rows, &self.weight, Some(&self.bias), 1.0, &[])?,
        };
        y.reshape((n, h, w, self.c_out, k, k))?.permute((0, 3, 1, 4, 2, 5))?.contiguous()?.reshape((n, self.c_out, h * k, w * k))
    }
}

#[derive(Debug, Clone)]
pub enum Resize {
    Up(ConvTransposePatch),
    Identity,
    Down(Conv),
}

/// `ResidualConvUnit`: upstream's activation is `ReLU(inplace=True)` applied to the input first, so the skip
/// adds the *rectified* input: `conv2(relu(conv1(relu(x)))) + relu(x)`.
#[derive(Debug, Clone)]
pub struct ResidualConvUnit {
    pub conv1: Conv,
    pub conv2: Conv,
}

impl ResidualConvUnit {
    pub fn new(vb: VarBuilder, f: usize) -> Result<Self> {
        Ok(Self { conv1: Conv::new(vb.pp("conv1"), f, f, 3, 1, 1, true)?, conv2: Conv::new(vb.pp("conv2"), f, f, 3, 1, 1, true)? })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if let (Some(w1), Some(w2)) = (&self.conv1.winograd, &self.conv2.winograd) {
            // The ReLUs and the skip fused into the Winograd kernel's input read and output write.
            let h = w1.forward_epilogue(x, WinogradEpilogue { relu_input: true, relu_output: true, ..Default::default() })?;
            return w2.forward_epilogue(&h, WinogradEpilogue { residual: Some(x), relu_residual: true, ..Default::default() });
        }
        let x = x.relu()?;
        let out = self.conv2.forward(&self.conv1.forward(&x)?.relu()?)?;
        out + x
    }
}

/// `FeatureFusionBlock`: `(x0 [+ rcu1(x1)]) → rcu2 → bilinear resize (align_corners) → 1×1 conv`.
#[derive(Debug, Clone)]
pub struct FeatureFusionBlock {
    pub res_conf_unit1: Option<ResidualConvUnit>,
    pub res_conf_unit2: ResidualConvUnit,
    pub out_conv: Conv,
}

impl FeatureFusionBlock {
    pub fn new(vb: VarBuilder, f: usize, has_residual: bool) -> Result<Self> {
        Ok(Self {
            res_conf_unit1: if has_residual { Some(ResidualConvUnit::new(vb.pp("resConfUnit1"), f)?) } else { None },
            res_conf_unit2: ResidualConvUnit::new(vb.pp("resConfUnit2"), f)?,
            out_conv: Conv::new(vb.pp("out_conv"), f, f, 1, 1, 0, true)?,
        })
    }

    /// `size`: the output size; None doubles the input's (`scale_factor=2`).
    pub fn forward(&self, x0: &Tensor, x1: Option<&Tensor>, size: Option<(usize, usize)>) -> Result<Tensor> {
        let mut out = x0.clone();
        if let (Some(u), Some(x1)) = (&self.res_conf_unit1, x1) {
            out = (out + u.forward(x1)?)?;
        }
        // Reassigned, not shadowed: each intermediate is freed as soon as the next exists (peak memory).
        out = self.res_conf_unit2.forward(&out)?;
        let (_, _, h, w) = out.dims4()?;
        let size = size.unwrap_or((2 * h, 2 * w));
        out = mvsplat360_nn::upsample::upsample_bilinear(&out, size)?;
        self.out_conv.forward(&out)
    }
}

#[derive(Debug, Clone)]
pub struct DptHead {
    pub norm: LayerNorm,
    pub projects: Vec<Conv>,
    pub resize_layers: Vec<Resize>,
    /// `scratch.layer{1..4}_rn`: 3×3, no bias.
    pub layer_rn: Vec<Conv>,
    /// `scratch.refinenet{1..4}` (refinenet4 has no residual input).
    pub refinenet: Vec<FeatureFusionBlock>,
    pub output_conv1: Conv,
    pub output_conv2a: Conv,
    pub output_conv2b: Conv,
    pub activation: Activation,
    pub patch_size: usize,
    pub cfg: DptConfig,
    /// The 1×1 projections as linear layers packed for `nn`'s bf16 product ([`DptHead::pack_bf16`]).
    pub projects_bf16: Option<Vec<PackedBf16>>,
}

impl DptHead {
    pub fn new(vb: VarBuilder, dim_in: usize, patch_size: usize, output_dim: usize, activation: Activation, cfg: &DptConfig) -> Result<Self> {
        let oc = cfg.out_channels;
        let f = cfg.features;
        let projects = (0..4).map(|i| Conv::new(vb.pp("projects").pp(i), dim_in, oc[i], 1, 1, 0, true)).collect::<Result<Vec<_>>>()?;
        let rl = vb.pp("resize_layers");
        let resize_layers = vec![
            Resize::Up(ConvTransposePatch::new(rl.pp(0), oc[0], oc[0], 4)?),
            Resize::Up(ConvTransposePatch::new(rl.pp(1), oc[1], oc[1], 2)?),
            Resize::Identity,
            Resize::Down(Conv::new(rl.pp(3), oc[3], oc[3], 3, 2, 1, true)?),
        ];
        let sc = vb.pp("scratch");
        let layer_rn = (0..4).map(|i| Conv::new(sc.pp(format!("layer{}_rn", i + 1)), oc[i], f, 3, 1, 1, false)).collect::<Result<Vec<_>>>()?;
        let refinenet = (0..4).map(|i| FeatureFusionBlock::new(sc.pp(format!("refinenet{}", i + 1)), f, i != 3)).collect::<Result<Vec<_>>>()?;
        let head2 = 32;
        Ok(Self {
            norm: LayerNorm::new(vb.pp("norm"), dim_in, TORCH_LN_EPS)?,
            projects,
            resize_layers,
            layer_rn,
            refinenet,
            output_conv1: Conv::new(sc.pp("output_conv1"), f, f / 2, 3, 1, 1, true)?,
            output_conv2a: Conv::new(sc.pp("output_conv2").pp(0), f / 2, head2, 3, 1, 1, true)?,
            output_conv2b: Conv::new(sc.pp("output_conv2").pp(2), head2, output_dim, 1, 1, 0, true)?,
            activation,
            patch_size,
            cfg: cfg.clone(),
            projects_bf16: None,
        })
    }

    /// The head's products in bf16 on the CPU (issue 73; the model's packed bf16 trunk asks for it): the 1×1
    /// projections and the transposed convs through the packed linear product, the 3×3 stride-1 convs through
    /// the bf16 Winograd kernel, the stride-2 conv and the fusion blocks' 1×1 convs through
    /// `conv2d_fused_bf16`. The final 32 → 2/4 1×1 conv stays f32 (K = 32: too short for the packed product to
    /// gain). Norms, resizes, positional embeddings, transforms, ReLUs, sums and activations stay f32.
    pub fn pack_bf16(&mut self) -> Result<()> {
        let mut proj = Vec::with_capacity(self.projects.len());
        for p in &self.projects {
            let (oc, c) = (p.weight.dim(0)?, p.weight.dim(1)?);
            proj.push(PackedBf16(Arc::new(Bf16Weights::from_linear(&p.weight.reshape((oc, c))?)?)));
        }
        self.projects_bf16 = Some(proj);
        for r in &mut self.resize_layers {
            match r {
                Resize::Up(u) => u.pack_bf16()?,
                Resize::Down(d) => d.pack_bf16()?,
                Resize::Identity => {}
            }
        }
        for c in &mut self.layer_rn {
            c.pack_bf16()?;
        }
        for f in &mut self.refinenet {
            for u in f.res_conf_unit1.iter_mut().chain(std::iter::once(&mut f.res_conf_unit2)) {
                u.conv1.pack_bf16()?;
                u.conv2.pack_bf16()?;
            }
            f.out_conv.pack_bf16()?;
        }
        self.output_conv1.pack_bf16()?;
        self.output_conv2a.pack_bf16()
    }

    /// Whether [`DptHead::pack_bf16`] ran.
    pub fn bf16_packed(&self) -> bool {
        self.projects_bf16.is_some()
    }

    /// `x (N, C, h, w) + 0.1 · embed(uv grid of (h, w) with the image's aspect W/H)`.
    fn apply_pos_embed(x: &Tensor, img_w: usize, img_h: usize) -> Result<Tensor> {
        let (_, c, h, w) = x.dims4()?;
        let pe = Tensor::from_vec(position_embed_uv(w, h, img_w as f64 / img_h as f64, c, 0.1), (1, c, h, w), x.device())?.to_dtype(x.dtype())?;
        x.broadcast_add(&pe)
    }

    /// The embedding of [`Self::apply_pos_embed`] for a `(h, w)` grid of `nf` frames as rows `(nf·h·w, c)`.
    fn pos_embed_rows(nf: usize, h: usize, w: usize, c: usize, img_w: usize, img_h: usize, dev: &candle_core::Device) -> Result<Tensor> {
        let cf = position_embed_uv(w, h, img_w as f64 / img_h as f64, c, 0.1);
        let n = h * w;
        let mut rows = vec![0f32; nf * n * c];
        for (p, row) in rows.chunks_exact_mut(c).take(n).enumerate() {
            for (ch, v) in row.iter_mut().enumerate() {
                *v = cf[ch * n + p];
            }
        }
        let (first, rest) = rows.split_at_mut(n * c);
        for frame in rest.chunks_exact_mut(n * c) {
            frame.copy_from_slice(first);
        }
        Tensor::from_vec(rows, (nf * n, c), dev)
    }

    /// Predictions `(S, H, W, out)` and confidence `(S, H, W)` for images of `H × W`, in frame chunks.
    pub fn forward(&self, tokens: &BTreeMap<usize, Tensor>, img_h: usize, img_w: usize, patch_start_idx: usize) -> Result<(Tensor, Tensor)> {
        let first = tokens.get(&self.cfg.intermediate_layer_idx[0]).ok_or_else(|| candle_core::Error::Msg("DPT head: layer not kept".into()))?;
        let s = first.dim(0)?;
        let chunk = self.cfg.frames_chunk_size.max(1);
        let mut preds = Vec::new();
        let mut confs = Vec::new();
        for start in (0..s).step_by(chunk) {
            let (p, c) = self.forward_frames(tokens, img_h, img_w, patch_start_idx, start, chunk.min(s - start))?;
            preds.push(p);
            confs.push(c);
        }
        Ok((Tensor::cat(&preds, 0)?, Tensor::cat(&confs, 0)?))
    }

    fn forward_frames(
        &self,
        tokens: &BTreeMap<usize, Tensor>,
        img_h: usize,
        img_w: usize,
        patch_start_idx: usize,
        f0: usize,
        nf: usize,
    ) -> Result<(Tensor, Tensor)> {
        let p = self.patch_size;
        let (ph, pw) = (img_h / p, img_w / p);
        let mut feats = Vec::with_capacity(4);
        let prof = mvsplat360_nn::prof::scope("vggt.dpt.project_resize");
        for (i, layer) in self.cfg.intermediate_layer_idx.iter().enumerate() {
            let t = tokens.get(layer).ok_or_else(|| candle_core::Error::Msg(format!("DPT head: aggregated layer {layer} not kept")))?;
            let n_tok = t.dim(1)?;
            let x = t.narrow(0, f0, nf)?.narrow(1, patch_start_idx, n_tok - patch_start_idx)?.to_dtype(candle_core::DType::F32)?;
            let x = self.norm.forward(&x)?;
            let c = x.dim(2)?;
            // The 1×1 projection as a linear layer on the tokens (no transpose of the 2C-wide input), with the
            // positional embedding added in the gemm's destination; the resize reads the rows as they are.
            let proj = &self.projects[i];
            let oc = proj.weight.dim(0)?;
            let pe = Self::pos_embed_rows(nf, ph, pw, oc, img_w, img_h, x.device())?;
            let xr = x.reshape((nf * ph * pw, c))?;
            let rows = match &self.projects_bf16 {
                Some(pk) if bf16_applies(&xr) => mvsplat360_nn::linear::linear_fused_bf16(&xr, &pk[i].0, proj.bias.as_ref(), 1.0, &[(&pe, 1.0)])?,
                _ => mvsplat360_nn::linear::linear_fused(&xr, &proj.weight.reshape((oc, c))?, proj.bias.as_ref(), 1.0, &[(&pe, 1.0)])?,
            };
            let channels_first = |r: &Tensor| r.reshape((nf, ph * pw, oc))?.permute((0, 2, 1))?.contiguous()?.reshape((nf, oc, ph, pw));
            let x = match &self.resize_layers[i] {
                Resize::Up(u) => u.forward_rows(&rows, nf, ph, pw)?,
                Resize::Identity => channels_first(&rows)?,
                Resize::Down(d) => d.forward(&channels_first(&rows)?)?,
            };
            feats.push(x);
        }
        drop(prof);
        let prof = mvsplat360_nn::prof::scope("vggt.dpt.layer_rn");
        let mut rn: Vec<Tensor> = feats.iter().zip(&self.layer_rn).map(|(x, c)| c.forward(x)).collect::<Result<_>>()?;
        drop(feats);
        let size = |t: &Tensor| -> Result<(usize, usize)> { Ok((t.dim(2)?, t.dim(3)?)) };
        drop(prof);
        let prof = mvsplat360_nn::prof::scope("vggt.dpt.refinenet");
        // `out` reassigned and each level's input dropped once used: the full-size intermediates are freed as
        // soon as the next one exists (the heads' transient is most of the forward's peak memory).
        let mut out = self.refinenet[3].forward(&rn[3], None, Some(size(&rn[2])?))?;
        rn.truncate(3);
        out = self.refinenet[2].forward(&out, Some(&rn[2]), Some(size(&rn[1])?))?;
        rn.truncate(2);
        out = self.refinenet[1].forward(&out, Some(&rn[1]), Some(size(&rn[0])?))?;
        rn.truncate(1);
        out = self.refinenet[0].forward(&out, Some(&rn[0]), None)?;
        drop(rn);
        drop(prof);
        let _prof = mvsplat360_nn::prof::scope("vggt.dpt.output");
        out = self.output_conv1.forward(&out)?;
        out = mvsplat360_nn::upsample::upsample_bilinear(&out, (ph * p, pw * p))?;
        out = Self::apply_pos_embed(&out, img_w, img_h)?;
        out = self.output_conv2a.forward(&out)?.relu()?;
        out = self.output_conv2b.forward(&out)?;
        activate_head(&out, self.activation)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    fn rel_rms(a: &Tensor, r: &Tensor) -> f64 {
        let a = a.flatten_all().unwrap().to_dtype(DType::F64).unwrap().to_vec1::<f64>().unwrap();
        let r = r.flatten_all().unwrap().to_dtype(DType::F64).unwrap().to_vec1::<f64>().unwrap();
        let e = a.iter().zip(&r).map(|(x, y)| (x - y) * (x - y)).sum::<f64>();
        (e / r.iter().map(|y| y * y).sum::<f64>()).sqrt()
    }

    /// The packed head (every product in bf16: projections, transposed convs, bf16 Winograd, stride-2 and 1×1
    /// convs; the kernels' own error-model tests are in `nn`) on two seeds and two image sizes: with AVX512-BF16
    /// its outputs differ from the f32 head's, and masked at run time (storage only: f32 products on the bf16
    /// weights) they differ again; both within the parity tests' bound of 0.05 × RMS (≈ 13u, a chain of 17
    /// products of ≈ u each). Packing a clone leaves the f32 head's outputs bit for bit.
    #[test]
    fn packed_head_runs_bf16_products_and_falls_back_masked() {
        let dev = Device::Cpu;
        let cfg = DptConfig { features: 16, out_channels: [8, 16, 24, 24], intermediate_layer_idx: [0, 1, 2, 3], frames_chunk_size: 2 };
        let dpbf16 = mvsplat360_nn::bf16::path() == mvsplat360_nn::bf16::Bf16Path::Dpbf16;
        for (seed, (ph, pw)) in [(1u64, (5, 7)), (2, (6, 3))] {
            let vb = mvsplat360_dataset::weights::random_var_builder(seed, &dev);
            let head = DptHead::new(vb, 32, 4, 4, Activation::InvLog, &cfg).unwrap();
            let mut packed = head.clone();
            packed.pack_bf16().unwrap();
            assert!(packed.bf16_packed() && packed.layer_rn[0].winograd.as_ref().unwrap().is_bf16() && packed.refinenet[0].out_conv.packed.is_some());
            let tokens: BTreeMap<usize, Tensor> = (0..4).map(|i| (i, Tensor::randn(0f32, 1.0, (3, 1 + ph * pw, 32), &dev).unwrap())).collect();
            let (h, w) = (4 * ph, 4 * pw);
            let f = head.forward(&tokens, h, w, 1).unwrap();
            let b = packed.forward(&tokens, h, w, 1).unwrap();
            let m = mvsplat360_nn::bf16::with_bf16_masked(|| packed.forward(&tokens, h, w, 1)).unwrap();
            let f2 = head.forward(&tokens, h, w, 1).unwrap();
            let bits = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap().into_iter().map(f32::to_bits).collect::<Vec<_>>();
            assert_eq!(bits(&f.0), bits(&f2.0), "the f32 head changed");
            for (tag, o) in [("bf16", &b), ("masked", &m)] {
                let (e0, e1) = (rel_rms(&o.0, &f.0), rel_rms(&o.1, &f.1));
                eprintln!("seed {seed} {ph}x{pw} {tag}: rel rms {e0:.2e} (points), {e1:.2e} (confidence)");
                assert!(e0 <= 0.05 && e1 <= 0.05, "seed {seed} {tag}: {e0} / {e1}");
            }
            if dpbf16 {
                assert_ne!(bits(&b.0), bits(&f.0), "seed {seed}: the packed head computed in f32");
                assert_ne!(bits(&b.0), bits(&m.0), "seed {seed}: the mask did not reach the head's products");
            }
        }
    }
}
