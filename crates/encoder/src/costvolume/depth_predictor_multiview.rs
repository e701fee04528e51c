//! Depth predictor (`depth_predictor_multiview.py`). Internally the batch dimension is `(v b)` (view-major),
//! exactly as the official code "for historical reasons"; outputs are returned as `(b, v)`.

use candle_core::{DType, Device, Module, Result, Tensor};
use candle_nn::VarBuilder;

use super::ldm_unet::util::Act;
use super::ldm_unet::{Conv2d, GroupNorm, UNetCfg, UNetModel};
use crate::bf16::{refuse_var, ConvWeight};
use crate::config::EncoderCostVolumeCfg;
use mvsplat360_nn::activation::gelu;
use mvsplat360_nn::conv::{Winograd3x3, WinogradEpilogue};
use mvsplat360_nn::upsample::{upsample_bilinear, upsample_nearest};
use mvsplat360_nn::warp_correlation::{warp_correlation, warp_correlation_bf16};

/// Inputs of the depth predictor (all `(b, v)`-major as the encoder holds them).
#[derive(Debug, Clone, Copy)]
pub struct DepthPredictorInput<'a> {
    /// `[B,V,C,h,w]` CNN features.
    pub features_cnn: &'a Tensor,
    /// `[B,V,C,h,w]` transformer features.
    pub features_trans: &'a Tensor,
    /// `[B,V,3,H,W]` raw images in [0,1].
    pub images: &'a Tensor,
    /// `[B,V,3,3]` normalised intrinsics.
    pub intrinsics: &'a Tensor,
    /// `[B,V,4,4]` camera-to-world.
    pub extrinsics: &'a Tensor,
    /// `[B,V]`.
    pub near: &'a Tensor,
    /// `[B,V]`.
    pub far: &'a Tensor,
    /// `[B,V,K]` (u32 or i64, K ≥ costvolume_nearest_n_views, usually V), argsort of camera-centre distances
    /// (column 0 = self); columns `1..costvolume_nearest_n_views` are the views the cost volume warps from.
    pub cameras_dist_index: &'a Tensor,
}

/// Intermediates named as in the fixture (`depth.*`), batch dimension `(v b)`.
#[derive(Debug, Clone)]
pub struct DepthIntermediates {
    /// `[(v b), D]` disparity candidates of each view.
    pub disparity_candidates: Tensor,
    /// `[(v b), D, h, w]`.
    pub cost_volume: Tensor,
    pub corr_refine_net_out: Tensor,
    pub cost_volume_refined: Tensor,
    pub depth_head_lowres_out: Tensor,
    /// `[(v b), 1, h, w]`.
    pub pdf_max_lowres: Tensor,
    pub coarse_disparity_lowres: Tensor,
    /// `[(v b), 1, H, W]`.
    pub fullres_disparity: Tensor,
    pub pdf_max_fullres: Tensor,
    /// `[(v b), C, H, W]` upsampler output (conv → bilinear ×up → GELU).
    pub upsampler_out: Tensor,
    pub proj_feature_out: Tensor,
    pub refine_unet_out: Tensor,
    /// `[(v b), 2·gpp, H, W]`: disparity delta, raw density.
    pub to_disparity_out: Tensor,
}

/// Outputs of the depth predictor.
#[derive(Debug, Clone)]
pub struct DepthPredictorOutput {
    /// `[B,V,H,W]` refined depth (1 / clamped fine disparity).
    pub depths: Tensor,
    /// `[B,V,H,W]` sigmoid(raw density).
    pub densities: Tensor,
    /// `[B,V,C_raw,H,W]` raw Gaussian parameters (`to_gaussians` output, C_raw = 120 for DL3DV).
    pub raw_gaussians: Tensor,
    /// Present when requested via [`DepthPredictorMultiView::forward_with_intermediates`].
    pub intermediates: Option<DepthIntermediates>,
}

/// Raw channels per Gaussian: 2 (xy offset) + 3 (scale) + 4 (quaternion) + RGB SH + feature SH.
pub fn gaussian_raw_channels(cfg: &EncoderCostVolumeCfg) -> usize {
    let g = &cfg.gaussian_adapter;
    let d_sh = (g.sh_degree + 1).pow(2);
    let d_fsh = if g.n_feature_channels > 0 { (g.feature_sh_degree + 1).pow(2) } else { 0 };
    cfg.num_surfaces * (2 + 7 + 3 * d_sh + g.n_feature_channels * d_fsh)
}

#[derive(Debug, Clone)]
pub struct DepthPredictorMultiView {
    cfg: EncoderCostVolumeCfg,
    // corr_refine_net: conv → GN(8) → GELU → UNet → conv
    corr_conv: Conv2d,
    corr_norm: GroupNorm,
    corr_unet: UNetModel,
    corr_out: Conv2d,
    regressor_residual: Conv2d,
    depth_head: (Conv2d, Conv2d),
    upsampler: Conv2d,
    proj_feature: Conv2d,
    // refine_unet: conv → GN(4) → GELU → UNet
    refine_conv: Conv2d,
    refine_norm: GroupNorm,
    refine_unet: UNetModel,
    to_gaussians: (Conv2d, Conv2d),
    /// Packed bf16 ([`Self::pack_bf16`]): the Gaussian head's two full-resolution 3×3 convolutions as bf16
    /// Winograd F(2×2, 3×3), the encoder's largest bf16 stage (0.28–0.33× their f32 time against 0.45–0.66× for
    /// the direct bf16 kernel on these shapes: docs/research/cpu-bf16.md §6).
    to_gaussians_winograd: Option<(Winograd3x3, Winograd3x3)>,
    to_disparity: (Conv2d, Conv2d),
}

impl DepthPredictorMultiView {
    /// `vb` = `encoder.depth_predictor`.
    pub fn new(vb: VarBuilder, cfg: &EncoderCostVolumeCfg) -> Result<Self> {
        if cfg.gaussians_per_pixel != 1 || cfg.num_surfaces != 1 {
            candle_core::bail!(
                "depth predictor: only gaussians_per_pixel = 1 and num_surfaces = 1 are supported (got {} and {})",
                cfg.gaussians_per_pixel,
                cfg.num_surfaces
            );
        }
        let c = cfg.d_feature;
        let nd = cfg.num_depth_candidates;
        let cv = cfg.costvolume_unet_feat_dim;
        let du = cfg.depth_unet_feat_dim;
        let raw = gaussian_raw_channels(cfg);
        let corr = vb.pp("corr_refine_net");
        let refine = vb.pp("refine_unet");
        let unet_cfg = |ch: usize, attn: &[usize], mult: &[usize]| UNetCfg {
            in_channels: ch,
            model_channels: ch,
            out_channels: ch,
            num_res_blocks: 1,
            attention_resolutions: attn.to_vec(),
            channel_mult: mult.to_vec(),
            num_head_channels: 32,
            num_frames: cfg.num_views,
        };
        Ok(Self {
            cfg: cfg.clone(),
            corr_conv: Conv2d::same3(corr.pp("0"), nd + c, cv)?,
            corr_norm: GroupNorm::new(corr.pp("1"), 8, cv)?,
            corr_unet: UNetModel::new(corr.pp("3"), &unet_cfg(cv, &cfg.costvolume_unet_attn_res, &cfg.costvolume_unet_channel_mult))?,
            corr_out: Conv2d::same3(corr.pp("4"), cv, nd)?,
            regressor_residual: Conv2d::new(vb.pp("regressor_residual"), nd + c, nd, 1, 1, 0)?,
            depth_head: (Conv2d::same3(vb.pp("depth_head_lowres").pp("0"), nd, 2 * nd)?, Conv2d::same3(vb.pp("depth_head_lowres").pp("2"), 2 * nd, nd)?),
            upsampler: Conv2d::same3(vb.pp("upsampler").pp("0"), 2 * c, c)?,
            proj_feature: Conv2d::same3(vb.pp("proj_feature"), c, du)?,
            refine_conv: Conv2d::same3(refine.pp("0"), 3 + du + 2, du)?,
            refine_norm: GroupNorm::new(refine.pp("1"), 4, du)?,
            refine_unet: UNetModel::new(refine.pp("3"), &unet_cfg(du, &cfg.depth_unet_attn_res, &cfg.depth_unet_channel_mult))?,
            to_gaussians: (Conv2d::same3(vb.pp("to_gaussians").pp("0"), du + 3 + c, 2 * raw)?, Conv2d::same3(vb.pp("to_gaussians").pp("2"), 2 * raw, raw)?),
            to_gaussians_winograd: None,
            to_disparity: (
                Conv2d::same3(vb.pp("to_disparity").pp("0"), du, 2 * du)?,
                Conv2d::same3(vb.pp("to_disparity").pp("2"), 2 * du, 2 * cfg.gaussians_per_pixel)?,
            ),
        })
    }

    pub fn forward(&self, inp: &DepthPredictorInput) -> Result<DepthPredictorOutput> {
        self.forward_impl(inp, false)
    }

    /// Every convolution (UNets, heads, upsampler, projections) packed in bf16, the Gaussian head's two as
    /// bf16 Winograd (CPU inference; the cost volume, norms, softmax and depth stay f32: see [`crate::bf16`]).
    pub fn pack_bf16(&mut self) -> Result<()> {
        for c in [
            &mut self.corr_conv,
            &mut self.corr_out,
            &mut self.regressor_residual,
            &mut self.depth_head.0,
            &mut self.depth_head.1,
            &mut self.upsampler,
            &mut self.proj_feature,
            &mut self.refine_conv,
            &mut self.to_disparity.0,
            &mut self.to_disparity.1,
        ] {
            c.pack_bf16()?;
        }
        if self.to_gaussians_winograd.is_none() {
            let wino = |c: &Conv2d| match &c.weight {
                ConvWeight::F32(w) => {
                    refuse_var(w)?;
                    Winograd3x3::new_bf16(w, Some(&c.bias))
                }
                ConvWeight::Bf16(_) => candle_core::bail!("depth predictor: the Gaussian head's convolutions are packed already"),
            };
            self.to_gaussians_winograd = Some((wino(&self.to_gaussians.0)?, wino(&self.to_gaussians.1)?));
        }
        self.corr_unet.pack_bf16()?;
        self.refine_unet.pack_bf16()
    }

    /// As [`Self::forward`], also returning the `depth.*` intermediates.
    pub fn forward_with_intermediates(&self, inp: &DepthPredictorInput) -> Result<DepthPredictorOutput> {
        self.forward_impl(inp, true)
    }

    fn forward_impl(&self, inp: &DepthPredictorInput, keep: bool) -> Result<DepthPredictorOutput> {
        let (b, v, _c, h, w) = inp.features_trans.dims5()?;
        let (_, _, c3, hh, ww) = inp.images.dims5()?;
        let up = self.cfg.downscale_factor;
        if inp.features_cnn.dims() != inp.features_trans.dims() || c3 != 3 || hh != h * up || ww != w * up {
            candle_core::bail!(
                "depth predictor: features {:?}/{:?} and images {:?} disagree (images must be {}× the feature map)",
                inp.features_trans.dims(),
                inp.features_cnn.dims(),
                inp.images.dims(),
                up
            );
        }
        let n = v * b;
        let to_vb = |t: &Tensor| -> Result<Tensor> {
            let mut dims = t.dims().to_vec();
            let rest: Vec<usize> = dims.split_off(2);
            let mut shape = vec![n];
            shape.extend_from_slice(&rest);
            let perm: Vec<usize> = [1, 0].into_iter().chain(2..t.rank()).collect();
            t.permute(perm)?.contiguous()?.reshape(shape)
        };
        let feat01 = to_vb(inp.features_trans)?;
        let cnn = to_vb(inp.features_cnn)?;
        let images = to_vb(inp.images)?;
        let mut t = std::time::Instant::now();

        // Cost volume against the nearest views.
        let geo = CostVolumeGeometry::new(inp, self.cfg.num_depth_candidates, self.cfg.costvolume_nearest_n_views)?;
        mvsplat360_nn::prof::lap("encoder.cost_volume.geometry", &mut t);
        let cost_volume = cost_volume_as(&feat01, inp.features_trans, &geo, self.corr_conv.weight.is_bf16())?;
        let disp_candidates = Tensor::from_vec(geo.disparities.clone(), (n, geo.d), feat01.device())?;
        let corr_in = Tensor::cat(&[&cost_volume, &feat01], 1)?;
        mvsplat360_nn::prof::lap("encoder.cost_volume", &mut t);

        // Cost-volume refinement (UNet branch + 1×1 residual).
        let x = self.corr_norm.forward_act(&self.corr_conv.forward(&corr_in)?, Act::Gelu)?;
        let x = self.corr_unet.forward_frames(&x, v)?;
        let corr_refine_out = self.corr_out.forward(&x)?;
        let refined = (&corr_refine_out + self.regressor_residual.forward(&corr_in)?)?;
        mvsplat360_nn::prof::lap("encoder.corr_unet", &mut t);

        // Softmax over candidates → coarse disparity and peak probability.
        let logits = self.depth_head.1.forward(&gelu(&self.depth_head.0.forward(&refined)?)?)?;
        let pdf = candle_nn::ops::softmax(&logits, 1)?;
        let coarse = pdf.broadcast_mul(&disp_candidates.reshape((n, geo.d, 1, 1))?)?.sum_keepdim(1)?;
        let pdf_max = pdf.max_keepdim(1)?;
        let pdf_max_full = upsample_nearest(&pdf_max, (hh, ww))?;
        let fullres = upsample_bilinear(&coarse, (hh, ww))?;
        mvsplat360_nn::prof::lap("encoder.depth_head", &mut t);

        // Depth refinement.
        let upsampled = gelu(&upsample_bilinear(&self.upsampler.forward(&Tensor::cat(&[&feat01, &cnn], 1)?)?, (hh, ww))?)?;
        let proj = self.proj_feature.forward(&upsampled)?;
        let refine_in = Tensor::cat(&[&images, &proj, &fullres, &pdf_max_full], 1)?;
        mvsplat360_nn::prof::lap("encoder.upsampler+proj", &mut t);
        let x = self.refine_norm.forward_act(&self.refine_conv.forward(&refine_in)?, Act::Gelu)?;
        let refine_out = self.refine_unet.forward_frames(&x, v)?;
        mvsplat360_nn::prof::lap("encoder.refine_unet", &mut t);

        let gin = Tensor::cat(&[&refine_out, &images, &upsampled], 1)?;
        // Each full-resolution intermediate is dropped once used (a shadowed binding would live to the end).
        let prof = mvsplat360_nn::prof::scope("encoder.to_gaussians.conv0");
        let g = match &self.to_gaussians_winograd {
            // GELU as the convolution's epilogue (the same values): no full-resolution pre-activation tensor.
            Some((w0, _)) => {
                let g = w0.forward_epilogue(&gin, WinogradEpilogue { gelu_output: true, ..Default::default() })?;
                drop((prof, gin));
                g
            }
            None => {
                let h = self.to_gaussians.0.forward(&gin)?;
                drop((prof, gin));
                let prof = mvsplat360_nn::prof::scope("encoder.to_gaussians.gelu");
                let g = gelu(&h)?;
                drop((prof, h));
                g
            }
        };
        let prof = mvsplat360_nn::prof::scope("encoder.to_gaussians.conv1");
        let raw = match &self.to_gaussians_winograd {
            Some((_, w1)) => w1.forward(&g)?,
            None => self.to_gaussians.1.forward(&g)?,
        };
        drop((prof, g));
        mvsplat360_nn::prof::lap("encoder.to_gaussians", &mut t);
        let disp_dens = self.to_disparity.1.forward(&gelu(&self.to_disparity.0.forward(&refine_out)?)?)?;
        mvsplat360_nn::prof::lap("encoder.to_disparity", &mut t);
        let gpp = self.cfg.gaussians_per_pixel;
        let delta = disp_dens.narrow(1, 0, gpp)?;
        let densities = candle_nn::ops::sigmoid(&disp_dens.narrow(1, gpp, gpp)?)?;
        let lo = Tensor::from_vec(geo.disp_min.clone(), (n, 1, 1, 1), feat01.device())?;
        let hi = Tensor::from_vec(geo.disp_max.clone(), (n, 1, 1, 1), feat01.device())?;
        let fine = (&fullres + &delta)?.broadcast_maximum(&lo)?.broadcast_minimum(&hi)?;
        let depths = fine.recip()?;

        // "(v b) 1 H W -> b v H W"
        let from_vb = |t: &Tensor| -> Result<Tensor> {
            let ch = t.dim(1)?;
            t.reshape((v, b, ch, hh, ww))?.permute((1, 0, 2, 3, 4))?.contiguous()
        };
        let out_depths = from_vb(&depths)?.squeeze(2)?;
        let out_dens = from_vb(&densities)?.squeeze(2)?;
        let raw_gaussians = from_vb(&raw)?;
        let intermediates = if keep {
            Some(DepthIntermediates {
                disparity_candidates: disp_candidates,
                cost_volume,
                corr_refine_net_out: corr_refine_out,
                cost_volume_refined: refined,
                depth_head_lowres_out: logits,
                pdf_max_lowres: pdf_max,
                coarse_disparity_lowres: coarse,
                fullres_disparity: fullres,
                pdf_max_fullres: pdf_max_full,
                upsampler_out: upsampled,
                proj_feature_out: proj,
                refine_unet_out: refine_out,
                to_disparity_out: disp_dens,
            })
        } else {
            None
        };
        Ok(DepthPredictorOutput { depths: out_depths, densities: out_dens, raw_gaussians, intermediates })
    }
}

/// Everything the plane sweep needs that does not carry gradients (the official code builds it under
/// `torch.no_grad()`): per `(v b)` item its source views, sampling grids and disparity bounds.
#[derive(Debug, Clone)]
pub struct CostVolumeGeometry {
    /// Items `(v b)`, candidates, feature map size.
    pub n: usize,
    pub d: usize,
    pub h: usize,
    pub w: usize,
    /// For each neighbour rank r (1..nn), the flat `(b v)` index of the source view of every `(v b)` item.
    pub sources: Vec<Vec<u32>>,
    /// For each neighbour rank, the sampling grid `[(v b), D·h, w, 2]` flattened.
    pub grids: Vec<Vec<f32>>,
    /// `[(v b)·D]` disparity candidates, uniform in disparity from 1/far to 1/near.
    pub disparities: Vec<f32>,
    pub disp_min: Vec<f32>,
    pub disp_max: Vec<f32>,
}

fn to_vec_f32(t: &Tensor) -> Result<Vec<f32>> {
    t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()
}

/// `torch.linspace(0, 1, steps)` in f32, including its symmetric evaluation (from both ends).
fn linspace01(steps: usize) -> Vec<f32> {
    if steps == 1 {
        return vec![0.0];
    }
    let step = 1.0f32 / (steps - 1) as f32;
    let half = steps / 2;
    (0..steps).map(|i| if i < half { step * i as f32 } else { 1.0 - step * (steps - 1 - i) as f32 }).collect()
}

fn inv4(m: &[f64; 16]) -> Option<[f64; 16]> {
    let mut a = *m;
    let mut inv = [0f64; 16];
    for i in 0..4 {
        inv[i * 5] = 1.0;
    }
    for col in 0..4 {
        let piv = (col..4).max_by(|&r1, &r2| a[r1 * 4 + col].abs().total_cmp(&a[r2 * 4 + col].abs()))?;
        if a[piv * 4 + col].abs() < 1e-12 {
            return None;
        }
        for k in 0..4 {
            a.swap(col * 4 + k, piv * 4 + k);
            inv.swap(col * 4 + k, piv * 4 + k);
        }
        let p = a[col * 4 + col];
        for k in 0..4 {
            a[col * 4 + k] /= p;
            inv[col * 4 + k] /= p;
        }
        for r in 0..4 {
            if r != col {
                let f = a[r * 4 + col];
                for k in 0..4 {
                    a[r * 4 + k] -= f * a[col * 4 + k];
                    inv[r * 4 + k] -= f * inv[col * 4 + k];
                }
            }
        }
    }
    Some(inv)
}

/// Inverse of a row-major 3×3 matrix, `None` when |det| < `eps` (callers pick the singularity threshold).
pub(crate) fn inv3(m: &[f64], eps: f64) -> Option<[f64; 9]> {
    let det = m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6]) + m[2] * (m[3] * m[7] - m[4] * m[6]);
    if det.abs() < eps {
        return None;
    }
    let id = 1.0 / det;
    Some([
        (m[4] * m[8] - m[5] * m[7]) * id,
        (m[2] * m[7] - m[1] * m[8]) * id,
        (m[1] * m[5] - m[2] * m[4]) * id,
        (m[5] * m[6] - m[3] * m[8]) * id,
        (m[0] * m[8] - m[2] * m[6]) * id,
        (m[2] * m[3] - m[0] * m[5]) * id,
        (m[3] * m[7] - m[4] * m[6]) * id,
        (m[1] * m[6] - m[0] * m[7]) * id,
        (m[0] * m[4] - m[1] * m[3]) * id,
    ])
}

impl CostVolumeGeometry {
    pub fn new(inp: &DepthPredictorInput, num_candidates: usize, nearest_n_views: usize) -> Result<Self> {
        let (b, v, _, h, w) = inp.features_trans.dims5()?;
        let n = v * b;
        let d = num_candidates;
        let nn = nearest_n_views.min(v);
        if nn < 2 {
            candle_core::bail!("cost volume: costvolume_nearest_n_views = {nearest_n_views} with {v} views leaves no view to warp from");
        }
        let idx = inp.cameras_dist_index;
        let kcols = idx.dims().get(2).copied().unwrap_or(0);
        if idx.rank() != 3 || idx.dims()[..2] != [b, v] || kcols < nn {
            candle_core::bail!("cost volume: cameras_dist_index must be [B={b},V={v},K≥{nn}] (column 0 = self), got {:?}", idx.dims());
        }
        let idx: Vec<i64> = idx.to_dtype(DType::I64)?.flatten_all()?.to_vec1()?;
        let ext = to_vec_f32(inp.extrinsics)?;
        let intr = to_vec_f32(inp.intrinsics)?;
        let near = to_vec_f32(inp.near)?;
        let far = to_vec_f32(inp.far)?;
        if ext.len() != b * v * 16 || intr.len() != b * v * 9 || near.len() != b * v || far.len() != b * v {
            candle_core::bail!("cost volume: extrinsics [B,V,4,4], intrinsics [B,V,3,3], near/far [B,V] expected for B={b}, V={v}");
        }
        let mat4 = |bv: usize| -> [f64; 16] { std::array::from_fn(|i| ext[bv * 16 + i] as f64) };

        // Disparity candidates, in f32 as the official code computes them.
        let lin = linspace01(d);
        let mut disparities = Vec::with_capacity(n * d);
        let (mut disp_min, mut disp_max) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for vi in 0..v {
            for bi in 0..b {
                let lo = 1.0f32 / far[bi * v + vi];
                let hi = 1.0f32 / near[bi * v + vi];
                disparities.extend(lin.iter().map(|&t| lo + t * (hi - lo)));
                disp_min.push(lo);
                disp_max.push(hi);
            }
        }

        let mut sources = Vec::new();
        let mut grids = Vec::new();
        for rank in 1..nn {
            let mut src = Vec::with_capacity(n);
            let mut grid = vec![0f32; n * d * h * w * 2];
            for vi in 0..v {
                for bi in 0..b {
                    let item = vi * b + bi;
                    let s = idx[(bi * v + vi) * kcols + rank];
                    if s < 0 || s as usize >= v {
                        candle_core::bail!("cost volume: cameras_dist_index has view {s} out of 0..{v}");
                    }
                    let s = s as usize;
                    src.push((bi * v + s) as u32);
                    // Relative pose inv(c2w_src)·c2w_ref maps reference-camera points into the source camera.
                    let inv_src =
                        inv4(&mat4(bi * v + s)).ok_or_else(|| candle_core::Error::Msg(format!("cost volume: extrinsics of view {s} are singular")))?;
                    let rf = mat4(bi * v + vi);
                    let mut pose = [0f64; 16];
                    for r in 0..4 {
                        for cc in 0..4 {
                            pose[r * 4 + cc] = (0..4).map(|k| inv_src[r * 4 + k] * rf[k * 4 + cc]).sum();
                        }
                    }
                    // The reference view's K (scaled to the feature map) is used for both back-projection and
                    // projection, as in the official code.
                    let kb = (bi * v + vi) * 9;
                    let mut k: [f64; 9] = std::array::from_fn(|i| intr[kb + i] as f64);
                    for cc in 0..3 {
                        k[cc] *= w as f64;
                        k[3 + cc] *= h as f64;
                    }
                    let kinv = inv3(&k, 1e-15).ok_or_else(|| candle_core::Error::Msg(format!("cost volume: intrinsics of view {vi} are singular")))?;
                    for di in 0..d {
                        let depth = (1.0f32 / disparities[item * d + di]) as f64;
                        for y in 0..h {
                            for x in 0..w {
                                let (xf, yf) = (x as f64, y as f64);
                                let p = [kinv[0] * xf + kinv[1] * yf + kinv[2], kinv[3] * xf + kinv[4] * yf + kinv[5], kinv[6] * xf + kinv[7] * yf + kinv[8]];
                                let mut q = [0f64; 3];
                                for r in 0..3 {
                                    q[r] = (pose[r * 4] * p[0] + pose[r * 4 + 1] * p[1] + pose[r * 4 + 2] * p[2]) * depth + pose[r * 4 + 3];
                                }
                                let pr: [f64; 3] = std::array::from_fn(|r| k[r * 3] * q[0] + k[r * 3 + 1] * q[1] + k[r * 3 + 2] * q[2]);
                                let z = pr[2].max(1e-3);
                                let gx = 2.0 * (pr[0] / z) / (w as f64 - 1.0) - 1.0;
                                let gy = 2.0 * (pr[1] / z) / (h as f64 - 1.0) - 1.0;
                                let o = (((item * d + di) * h + y) * w + x) * 2;
                                grid[o] = gx as f32;
                                grid[o + 1] = gy as f32;
                            }
                        }
                    }
                }
            }
            sources.push(src);
            grids.push(grid);
        }
        Ok(Self { n, d, h, w, sources, grids, disparities, disp_min, disp_max })
    }
}

/// Plane-sweep correlation: for each neighbour rank, warp its features into the reference view at every
/// candidate depth (bilinear, zeros) and take dot/√C with the reference features; average over neighbours.
/// The warp and the dot are fused ([`warp_correlation`]), so the warped features never exist in memory.
/// `feat01 [(v b),C,h,w]`, `features [B,V,C,h,w]` → `[(v b), D, h, w]`.
pub fn cost_volume(feat01: &Tensor, features: &Tensor, geo: &CostVolumeGeometry) -> Result<Tensor> {
    cost_volume_as(feat01, features, geo, false)
}

/// [`cost_volume`], its channel dot products in bf16 when `bf16` (a packed encoder: `warp_correlation_bf16`).
fn cost_volume_as(feat01: &Tensor, features: &Tensor, geo: &CostVolumeGeometry, bf16: bool) -> Result<Tensor> {
    let (b, v, c, h, w) = features.dims5()?;
    let dev: &Device = feat01.device();
    let flat = features.reshape((b * v, c, h, w))?;
    let mut total: Option<Tensor> = None;
    for (src, grid) in geo.sources.iter().zip(&geo.grids) {
        let feat10 = flat.index_select(&Tensor::from_vec(src.clone(), geo.n, dev)?, 0)?;
        let prof = mvsplat360_nn::prof::scope("encoder.cost_volume.warp_correlation");
        let corr = if bf16 { warp_correlation_bf16(feat01, &feat10, grid, geo.d)? } else { warp_correlation(feat01, &feat10, grid, geo.d)? };
        drop(prof);
        let corr = (corr / (c as f64).sqrt())?;
        total = Some(match total {
            Some(t) => (t + corr)?,
            None => corr,
        });
    }
    let total = total.ok_or_else(|| candle_core::Error::Msg("cost volume: no neighbour views".into()))?;
    total / geo.sources.len() as f64
}
