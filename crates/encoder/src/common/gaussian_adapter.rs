//! Gaussian adapter (`encoder/common/gaussian_adapter.py` + its call in `encoder_costvolume.py`): raw per-pixel
//! parameters → world-space Gaussians. Everything that depends on the prediction is built from differentiable
//! tensor ops; per-view camera quantities (K⁻¹, Wigner-D) carry no gradient, as in the official code.

use candle_core::{DType, Result, Tensor, D};

use super::sh_rotation::{rotate_sh, sh_rotation_matrices};
use crate::config::EncoderCostVolumeCfg;
use crate::costvolume::DepthPredictorOutput;
use mvsplat360_nn::layout::channels_last;

/// Gaussians as the encoder returns them (B batches, G = V·H·W per batch, g = v·H·W + y·W + x).
#[derive(Debug, Clone)]
pub struct EncoderGaussians {
    /// `[B,G,3]` world-space centres.
    pub means: Tensor,
    /// `[B,G,3,3]` world-space covariances.
    pub covariances: Tensor,
    /// `[B,G,3,(sh_degree+1)²]` RGB SH, masked and rotated to world.
    pub harmonics: Tensor,
    /// `[B,G]` opacities in (0,1).
    pub opacities: Tensor,
    /// `[B,G,C,(feature_sh_degree+1)²]` feature SH, masked and rotated to world.
    pub feature_harmonics: Tensor,
    /// `[B,G,3]` camera-frame scales.
    pub scales: Tensor,
    /// `[B,G,4]` camera-frame unit quaternions, xyzw.
    pub rotations: Tensor,
    /// `[B,V,H,W,1,1]` depths.
    pub depths: Tensor,
}

/// Adapter internals the parity tests compare (`adapter.*` in the fixture).
#[derive(Debug, Clone)]
pub struct AdapterIntermediates {
    /// `[B,V,H·W,2]` normalised ray coordinates (x first).
    pub coordinates: Tensor,
    /// `[B,V,H·W]` opacities after the mapping.
    pub opacities: Tensor,
    /// `[B,V,H·W,3,3]` camera-frame covariances.
    pub covariance_camera: Tensor,
    /// `[B,V,n_sh,n_sh]` block-diagonal Wigner-D (blocks l = 0..sh_degree) per view.
    pub wigner_d: Tensor,
}

/// SH mask: 1 for degree 0, 0.1·0.25^l for degree l ≥ 1.
pub fn sh_mask(degree: usize) -> Vec<f32> {
    let mut m = Vec::with_capacity((degree + 1) * (degree + 1));
    for l in 0..=degree {
        let v = if l == 0 { 1.0 } else { 0.1 * 0.25f32.powi(l as i32) };
        m.extend(std::iter::repeat(v).take(2 * l + 1));
    }
    m
}

/// `map_pdf_to_opacity`: exponent 2^x with x ramping from `initial` to `final` over `warm_up` steps.
pub fn map_pdf_to_opacity(cfg: &EncoderCostVolumeCfg, pdf: &Tensor, global_step: u64) -> Result<Tensor> {
    let om = &cfg.opacity_mapping;
    let ramp = if om.warm_up == 0 { 1.0 } else { (global_step as f64 / om.warm_up as f64).min(1.0) };
    let x = om.initial as f64 + ramp * (om.r#final as f64 - om.initial as f64);
    let exponent = 2f64.powf(x);
    let one_minus = pdf.affine(-1.0, 1.0)?;
    let (a, b) = if exponent == 1.0 { (one_minus, pdf.clone()) } else { (one_minus.powf(exponent)?, pdf.powf(1.0 / exponent)?) };
    (a.affine(-1.0, 1.0)? + b)? * 0.5
}

/// Raw prediction → Gaussians at training step 0 (the test-time call). `extrinsics [B,V,4,4]` c2w,
/// `intrinsics [B,V,3,3]` normalised, `image_hw` = the depth maps' size.
pub fn gaussians_from_prediction(
    cfg: &EncoderCostVolumeCfg,
    pred: &DepthPredictorOutput,
    extrinsics: &Tensor,
    intrinsics: &Tensor,
    image_hw: (usize, usize),
) -> Result<EncoderGaussians> {
    Ok(gaussians_from_prediction_at_step(cfg, pred, extrinsics, intrinsics, image_hw, 0)?.0)
}

/// As [`gaussians_from_prediction`] at a given training step (opacity mapping), also returning internals.
pub fn gaussians_from_prediction_at_step(
    cfg: &EncoderCostVolumeCfg,
    pred: &DepthPredictorOutput,
    extrinsics: &Tensor,
    intrinsics: &Tensor,
    image_hw: (usize, usize),
    global_step: u64,
) -> Result<(EncoderGaussians, AdapterIntermediates)> {
    let (h, w) = image_hw;
    let (b, v, craw, hh, ww) = pred.raw_gaussians.dims5()?;
    if (hh, ww) != (h, w) || pred.depths.dims() != [b, v, h, w] {
        candle_core::bail!(
            "gaussian adapter: image size {h}x{w} disagrees with raw Gaussians {:?} / depths {:?}",
            pred.raw_gaussians.dims(),
            pred.depths.dims()
        );
    }
    if extrinsics.dims() != [b, v, 4, 4] || intrinsics.dims() != [b, v, 3, 3] {
        candle_core::bail!("gaussian adapter: extrinsics {:?} / intrinsics {:?} must be [B={b},V={v},4,4] / [B,V,3,3]", extrinsics.dims(), intrinsics.dims());
    }
    let ga = &cfg.gaussian_adapter;
    let d_sh = (ga.sh_degree + 1).pow(2);
    let nfc = ga.n_feature_channels;
    let d_fsh = (ga.feature_sh_degree + 1).pow(2);
    let want = 2 + 7 + 3 * d_sh + if nfc > 0 { nfc * d_fsh } else { 0 };
    if craw != want {
        candle_core::bail!(
            "gaussian adapter: {craw} raw channels, the configuration (sh_degree {}, {} feature channels of degree {}) needs {want}",
            ga.sh_degree,
            nfc,
            ga.feature_sh_degree
        );
    }
    let dev = pred.raw_gaussians.device();
    let p = h * w;
    let raw = channels_last(&pred.raw_gaussians)?.reshape((b, v, p, craw))?.to_dtype(DType::F32)?;
    let depths = pred.depths.reshape((b, v, p, 1))?;

    // Ray coordinates: pixel centre plus a sub-pixel offset of at most half a pixel.
    let mut base = Vec::with_capacity(p * 2);
    for y in 0..h {
        for x in 0..w {
            base.push((x as f32 + 0.5) / w as f32);
            base.push((y as f32 + 0.5) / h as f32);
        }
    }
    let base = Tensor::from_vec(base, (1, 1, p, 2), dev)?;
    let pixel_size = Tensor::new(&[1.0f32 / w as f32, 1.0 / h as f32], dev)?;
    let offset = candle_nn::ops::sigmoid(&raw.narrow(D::Minus1, 0, 2)?)?;
    let coordinates = base.broadcast_add(&(offset - 0.5)?.broadcast_mul(&pixel_size)?)?;

    // Per-view camera quantities.
    let ext = extrinsics.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let intr = intrinsics.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let (mut kinv, mut mult, mut rot, mut origin) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for i in 0..b * v {
        let k: Vec<f64> = intr[i * 9..i * 9 + 9].iter().map(|&x| x as f64).collect();
        let ki = crate::costvolume::depth_predictor_multiview::inv3(&k, 1e-20)
            .ok_or_else(|| candle_core::Error::Msg(format!("gaussian adapter: intrinsics of item {i} are singular")))?;
        kinv.extend(ki.iter().map(|&x| x as f32));
        // 0.1 · Σᵢ (K[:2,:2]⁻¹ · (1/W, 1/H))ᵢ
        let det2 = k[0] * k[4] - k[1] * k[3];
        let inv2 = [k[4] / det2, -k[1] / det2, -k[3] / det2, k[0] / det2];
        let (px, py) = (1.0 / w as f64, 1.0 / h as f64);
        mult.push((0.1 * ((inv2[0] * px + inv2[1] * py) + (inv2[2] * px + inv2[3] * py))) as f32);
        for r in 0..3 {
            rot.extend_from_slice(&ext[i * 16 + r * 4..i * 16 + r * 4 + 3]);
            origin.push(ext[i * 16 + r * 4 + 3]);
        }
    }
    let kinv = Tensor::from_vec(kinv, (b, v, 1, 3, 3), dev)?;
    let mult = Tensor::from_vec(mult, (b, v, 1, 1), dev)?;
    let rot = Tensor::from_vec(rot, (b, v, 1, 3, 3), dev)?;
    let origin = Tensor::from_vec(origin, (b, v, 1, 3), dev)?;

    // Scales.
    let smin = ga.gaussian_scale_min as f64;
    let smax = ga.gaussian_scale_max as f64;
    let scales = candle_nn::ops::sigmoid(&raw.narrow(D::Minus1, 2, 3)?)?.affine(smax - smin, smin)?;
    let scales = scales.broadcast_mul(&depths)?.broadcast_mul(&mult)?;

    // Quaternions (xyzw) and camera-frame covariance R·S·Sᵀ·Rᵀ.
    let q = raw.narrow(D::Minus1, 5, 4)?;
    let qn = q.sqr()?.sum_keepdim(D::Minus1)?.sqrt()?;
    let rotations = q.broadcast_div(&(qn + 1e-8)?)?;
    let rmat = quaternion_to_matrix(&rotations)?;
    // candle's CPU matmul takes at most one batch dimension beyond the first: flatten to 3-D.
    let bvp = b * v * p;
    let rs = rmat.broadcast_mul(&scales.unsqueeze(3)?)?.reshape((bvp, 3, 3))?;
    let cov_cam = rs.matmul(&rs.transpose(1, 2)?.contiguous()?)?;
    let rot_b = rot.broadcast_as((b, v, p, 3, 3))?.contiguous()?.reshape((bvp, 3, 3))?;
    let cov_world = rot_b.matmul(&cov_cam)?.matmul(&rot_b.transpose(1, 2)?.contiguous()?)?;
    let cov_cam = cov_cam.reshape((b, v, p, 3, 3))?;

    // Means: camera centre + unit ray direction · depth (the official behaviour, not z-depth).
    let ones = Tensor::ones((b, v, p, 1), DType::F32, dev)?;
    let homog = Tensor::cat(&[&coordinates, &ones], D::Minus1)?.reshape((b * v, p, 3))?;
    let kinv_t = kinv.reshape((b * v, 3, 3))?.transpose(1, 2)?.contiguous()?;
    let dirs = homog.matmul(&kinv_t)?;
    let dirs = dirs.broadcast_div(&dirs.sqr()?.sum_keepdim(D::Minus1)?.sqrt()?)?;
    let rot_t = rot.reshape((b * v, 3, 3))?.transpose(1, 2)?.contiguous()?;
    let dirs = dirs.matmul(&rot_t)?.reshape((b, v, p, 3))?;
    let means = origin.broadcast_add(&dirs.broadcast_mul(&depths)?)?;

    // Opacity.
    let dens = pred.densities.reshape((b, v, p))?;
    let opacities = (map_pdf_to_opacity(cfg, &dens, global_step)? / cfg.gaussians_per_pixel as f64)?;

    // SH: mask, then rotate each degree block by the view's Wigner-D.
    let rot33 = rot.squeeze(2)?;
    let d_rgb = sh_rotation_matrices(&rot33, ga.sh_degree)?;
    let mask = Tensor::from_vec(sh_mask(ga.sh_degree), d_sh, dev)?;
    let sh = raw.narrow(D::Minus1, 9, 3 * d_sh)?.reshape((b, v, p, 3, d_sh))?.broadcast_mul(&mask)?;
    let harmonics = rotate_sh(&sh, &d_rgb)?;
    let feature_harmonics = if nfc > 0 {
        let d_f = sh_rotation_matrices(&rot33, ga.feature_sh_degree)?;
        let fmask = Tensor::from_vec(sh_mask(ga.feature_sh_degree), d_fsh, dev)?;
        let fsh = raw.narrow(D::Minus1, 9 + 3 * d_sh, nfc * d_fsh)?.reshape((b, v, p, nfc, d_fsh))?.broadcast_mul(&fmask)?;
        rotate_sh(&fsh, &d_f)?
    } else {
        Tensor::zeros((b, v, p, 0, d_fsh), DType::F32, dev)?
    };

    let g = v * p;
    let gaussians = EncoderGaussians {
        means: means.reshape((b, g, 3))?,
        covariances: cov_world.reshape((b, g, 3, 3))?,
        harmonics: harmonics.reshape((b, g, 3, d_sh))?,
        opacities: opacities.reshape((b, g))?,
        feature_harmonics: feature_harmonics.reshape((b, g, nfc, d_fsh))?,
        scales: scales.reshape((b, g, 3))?,
        rotations: rotations.reshape((b, g, 4))?,
        depths: pred.depths.reshape((b, v, h, w, 1, 1))?,
    };
    let inter = AdapterIntermediates { coordinates, opacities, covariance_camera: cov_cam, wigner_d: d_rgb };
    Ok((gaussians, inter))
}

/// Rotation matrix of (x, y, z, w) quaternions `[..., 4]` → `[..., 3, 3]`, with the official 2/(|q|² + 1e-8).
pub fn quaternion_to_matrix(q: &Tensor) -> Result<Tensor> {
    let last = q.rank() - 1;
    let c = |i: usize| q.narrow(last, i, 1);
    let (i, j, k, r) = (c(0)?, c(1)?, c(2)?, c(3)?);
    let two_s = (q.sqr()?.sum_keepdim(last)? + 1e-8)?.recip()? * 2.0;
    let two_s = two_s?;
    let m = |a: &Tensor, b: &Tensor| a.mul(b);
    let one_minus = |t: Tensor| -> Result<Tensor> { two_s.mul(&t)?.affine(-1.0, 1.0) };
    let times = |t: Tensor| -> Result<Tensor> { two_s.mul(&t) };
    let entries = [
        one_minus((m(&j, &j)? + m(&k, &k)?)?)?,
        times((m(&i, &j)? - m(&k, &r)?)?)?,
        times((m(&i, &k)? + m(&j, &r)?)?)?,
        times((m(&i, &j)? + m(&k, &r)?)?)?,
        one_minus((m(&i, &i)? + m(&k, &k)?)?)?,
        times((m(&j, &k)? - m(&i, &r)?)?)?,
        times((m(&i, &k)? - m(&j, &r)?)?)?,
        times((m(&j, &k)? + m(&i, &r)?)?)?,
        one_minus((m(&i, &i)? + m(&j, &j)?)?)?,
    ];
    let mut shape = q.dims()[..last].to_vec();
    shape.extend_from_slice(&[3, 3]);
    Tensor::cat(&entries, last)?.reshape(shape)
}
