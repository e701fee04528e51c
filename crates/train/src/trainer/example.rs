//! Training examples: views sampled from a scene, brought to model units, encoded and rasterized at the targets.

use super::*;

/// One training example at model scale: context and targets with their photos.
#[derive(Clone)]
pub struct Example {
    pub context_images: Tensor,
    pub context_cameras: Vec<Camera>,
    pub target_images: Tensor,
    pub target_cameras: Vec<Camera>,
    /// (V,H,W) ground-truth ray distances of the context views in model units (infinite = sky), when the
    /// source knows them.
    pub context_depths: Option<Tensor>,
}

impl Example {
    /// The photos and depths on `dev` (cameras stay on the host; the encoder builds its camera tensors there).
    pub fn to_device(self, dev: &Device) -> Result<Self> {
        if dev.same_device(self.context_images.device()) {
            return Ok(self);
        }
        Ok(Self {
            context_images: self.context_images.to_device(dev)?,
            target_images: self.target_images.to_device(dev)?,
            context_depths: self.context_depths.map(|d| d.to_device(dev)).transpose()?,
            ..self
        })
    }

    /// Mean |ln d − ln d_true| of pixel-aligned, view-major Gaussians `g` of the context views, d = each
    /// Gaussian's distance from its view's camera, over the pixels whose true distance is below 0.9 `far`
    /// (sky and the far background left out); None when the source knows no depths.
    pub fn context_distance_error(&self, g: &Gaussians, far: f32) -> Result<Option<f64>> {
        let Some(depths) = self.context_depths.as_ref() else { return Ok(None) };
        let truth: Vec<f32> = depths.flatten_all()?.to_vec1()?;
        let m: Vec<f32> = g.means.flatten_all()?.to_vec1()?;
        let per = truth.len() / self.context_cameras.len();
        let (mut s, mut n) = (0.0, 0);
        for (i, &t) in truth.iter().enumerate() {
            if t as f64 >= 0.9 * far as f64 {
                continue;
            }
            let o = self.context_cameras[i / per].center();
            let d = ((m[3 * i] as f64 - o.x).powi(2) + (m[3 * i + 1] as f64 - o.y).powi(2) + (m[3 * i + 2] as f64 - o.z).powi(2)).sqrt();
            s += (d / t as f64).ln().abs();
            n += 1;
        }
        Ok(Some(s / n.max(1) as f64))
    }
}

/// What the encoder and rasterizer make of an example.
pub struct Rendered {
    /// (T,3,H,W) target renders.
    pub rgb: Tensor,
    /// (T,C,H,W) rendered latent features.
    pub features: Tensor,
    pub gaussians: Gaussians,
    /// (V,H,W) the encoder's per-pixel ray distances of the context views.
    pub depths: Tensor,
}

/// Randomness of optimizer step `step`, micro-batch `micro`: a pure function of the seed, so that a resumed
/// run draws exactly what the uninterrupted one drew.
pub fn step_rng(seed: u64, step: u64, micro: u32) -> rand::rngs::StdRng {
    let mut x = seed ^ 0x9E37_79B9_7F4A_7C15u64.wrapping_mul(step.wrapping_add(1)) ^ ((micro as u64) << 48);
    // splitmix64 finaliser
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    rand::rngs::StdRng::seed_from_u64(x ^ (x >> 31))
}

/// Build an example from a scene: sample views, scale like `render --scene-scale auto`, flip.
pub fn make_example(scene: &TrainScene, s: &SamplerSettings, near: f32, far: f32, rng: &mut impl Rng) -> Result<Option<Example>> {
    let Some(v) = sampler::sample(&scene.cameras, s, rng) else { return Ok(None) };
    example_from_views(scene, &v, near, far).map(Some)
}

/// The example of chosen views: scaled like `render --scene-scale auto` (from the context cameras), flipped
/// when `v.flip`.
pub fn example_from_views(scene: &TrainScene, v: &sampler::ViewSample, near: f32, far: f32) -> Result<Example> {
    let ctx: Vec<Camera> = v.context.iter().map(|&i| scene.cameras[i].clone()).collect();
    let (tf, _) = scene_transform(SceneScale::Auto, &ctx, near, far);
    let prep = |idx: &[usize]| -> Result<(Tensor, Vec<Camera>)> {
        let (w, h) = (scene.images[idx[0]].width as usize, scene.images[idx[0]].height as usize);
        let mut data = Vec::with_capacity(idx.len() * 3 * w * h);
        let mut cams = Vec::with_capacity(idx.len());
        for &i in idx {
            let mut img = scene.images[i].data.clone();
            let mut cam = tf.apply(&scene.cameras[i]);
            if v.flip {
                sampler::flip_image(&mut img, w);
                cam = sampler::flip_camera(&cam);
            }
            data.extend_from_slice(&img);
            cams.push(cam);
        }
        Ok((Tensor::from_vec(data, (idx.len(), 3, h, w), &Device::Cpu)?, cams))
    };
    let (ci, cc) = prep(&v.context)?;
    let (ti, tc) = prep(&v.target)?;
    let context_depths = match &scene.depths {
        Some(depths) => {
            let (w, h) = (scene.images[v.context[0]].width as usize, scene.images[v.context[0]].height as usize);
            let mut data = Vec::with_capacity(v.context.len() * w * h);
            for &i in &v.context {
                // Scaling the scene scales every distance; a flip mirrors the map with its image.
                let mut d: Vec<f32> = depths[i].iter().map(|&x| (x as f64 * tf.scale) as f32).collect();
                if v.flip {
                    sampler::flip_image(&mut d, w);
                }
                data.extend_from_slice(&d);
            }
            Some(Tensor::from_vec(data, (v.context.len(), h, w), &Device::Cpu)?)
        }
        None => None,
    };
    Ok(Example { context_images: ci, context_cameras: cc, target_images: ti, target_cameras: tc, context_depths })
}

/// Encoder forward and target renders: (renders (T,3,H,W), Gaussians).
pub fn render_example(model: &Model, ex: &Example) -> Result<(Tensor, Gaussians)> {
    let r = render_example_full(model, ex)?;
    Ok((r.rgb, r.gaussians))
}

/// As [`render_example`], also returning the rendered features and the encoder's depths.
pub fn render_example_full(model: &Model, ex: &Example) -> Result<Rendered> {
    let dev = ex.context_images.device().clone();
    let v = ex.context_cameras.len();
    let k: Vec<[f64; 4]> = ex.context_cameras.iter().map(|c| c.normalized_intrinsics()).collect();
    let c2w: Vec<[[f64; 4]; 4]> = ex.context_cameras.iter().map(|c| c.c2w).collect();
    let (intr, extr) = camera_tensors(&k, &c2w, &dev)?;
    let (near, far) = (model.cfg.model.near, model.cfg.model.far);
    let nt = Tensor::full(near, (1, v), &dev)?;
    let ft = Tensor::full(far, (1, v), &dev)?;
    let g = model.encoder.forward(&ex.context_images.unsqueeze(0)?, &intr, &extr, &nt, &ft)?;
    let gs = Gaussians {
        means: g.means.i(0)?,
        covariances: g.covariances.i(0)?,
        opacities: g.opacities.i(0)?,
        harmonics: g.harmonics.i(0)?,
        feature_harmonics: g.feature_harmonics.i(0)?,
    };
    let mut renders = Vec::with_capacity(ex.target_cameras.len());
    let mut features = Vec::with_capacity(ex.target_cameras.len());
    for c in &ex.target_cameras {
        let grad_mode = match model.cfg.train.raster_grad {
            crate::config::RasterGrad::Official => mvsplat360_splat::GradMode::Official,
            crate::config::RasterGrad::Exact => mvsplat360_splat::GradMode::Exact,
        };
        let r = mvsplat360_splat::render(&gs, &RasterCamera::from_camera(c, near, far), &RenderOptions { grad_mode, ..RenderOptions::default() })?;
        renders.push(r.rgb);
        features.push(r.features);
    }
    let depths = g.depths.i(0)?.reshape((v, ex.context_images.dim(2)?, ex.context_images.dim(3)?))?;
    Ok(Rendered { rgb: Tensor::stack(&renders, 0)?, features: Tensor::stack(&features, 0)?, gaussians: gs, depths })
}
