//! Scoring a scene's saved images as the official scorer does (it reads the PNGs): PSNR, SSIM, LPIPS, DISTS per
//! image and the Inception features that FID needs, written per scene so that a resumed run re-scores nothing.

use super::*;

/// The metric networks that were found.
pub(super) struct Nets {
    pub(super) lpips: Option<Lpips>,
    pub(super) dists: Option<Dists>,
    pub(super) fid: Option<FidInception>,
}

impl Nets {
    pub(super) fn used(&self) -> Networks {
        Networks { lpips: self.lpips.is_some(), dists: self.dists.is_some(), fid: self.fid.is_some(), fid_variant: self.fid.as_ref().map(|n| n.variant()) }
    }
}

pub(super) fn load_net<T>(what: &str, r: std::result::Result<T, MetricsWeightsError>, warnings: &mut Vec<String>) -> Result<Option<T>> {
    match r {
        Ok(n) => Ok(Some(n)),
        Err(e @ MetricsWeightsError::Missing { .. }) => {
            warnings.push(format!("{what} skipped (null): {e}"));
            Ok(None)
        }
        Err(e) => Err(PipelineError::Compute { stage: "metric weights", msg: e.to_string() }),
    }
}

pub(super) fn load_nets(req: &EvalRequest, warnings: &mut Vec<String>) -> Result<Nets> {
    let wd = req.weights_dir.as_deref();
    let dev = Device::Cpu;
    Ok(Nets {
        lpips: if req.lpips { load_net("LPIPS", Lpips::load(wd, Net::Vgg, &dev), warnings)? } else { None },
        dists: if req.dists { load_net("DISTS", Dists::load(wd, &dev), warnings)? } else { None },
        fid: if req.fid { load_net("FID", FidInception::load(wd, &dev).map(|n| n.with_variant(req.fid_variant)), warnings)? } else { None },
    })
}

pub(super) fn image_tensor(imgs: &[&RgbImage]) -> Result<Tensor> {
    let (w, h) = (imgs[0].width, imgs[0].height);
    let mut v = Vec::with_capacity(imgs.len() * 3 * w * h);
    for im in imgs {
        v.extend_from_slice(&im.data);
    }
    Tensor::from_vec(v, (imgs.len(), 3, h, w), &Device::Cpu).map_err(compute("metrics"))
}

/// Inception features of a set of images: (N, 2048) row-major.
pub(super) fn fid_features(net: &FidInception, imgs: &[RgbImage]) -> Result<Vec<f32>> {
    let mut out = Vec::with_capacity(imgs.len() * mvsplat360_metrics::inception::DIM);
    for batch in imgs.chunks(NET_BATCH) {
        let refs: Vec<&RgbImage> = batch.iter().collect();
        let t = image_tensor(&refs)?;
        let f = net.features(&t).and_then(|f| f.flatten_all()?.to_vec1::<f32>()).map_err(compute("FID features"))?;
        out.extend(f);
    }
    Ok(out)
}

/// Score a scene's saved images (the official scorer reads the PNGs too); writes its Inception features.
pub(super) fn score_scene(out: &Path, plan: &ScenePlan, methods: &[Method], nets: &Nets) -> Result<BTreeMap<String, Vec<ImageScores>>> {
    let load = |dir: &str| -> Result<Vec<RgbImage>> {
        plan.scored
            .iter()
            .map(|&v| {
                let p = out.join(dir).join(image_name(&plan.key, v));
                load_rgb(&p).map_err(|e| PipelineError::Compute { stage: "metrics", msg: e.to_string() })
            })
            .collect()
    };
    let gt = load(GT_DIR)?;
    let mut feats: HashMap<String, Tensor> = HashMap::new();
    let feat_tensor = |v: Vec<f32>| Tensor::from_vec(v, (plan.scored.len(), mvsplat360_metrics::inception::DIM), &Device::Cpu).map_err(compute("FID features"));
    if let Some(net) = &nets.fid {
        feats.insert("gt".into(), feat_tensor(fid_features(net, &gt)?)?);
    }
    let mut result = BTreeMap::new();
    for &m in methods {
        let pred = load(m.dir())?;
        let mut scores = Vec::with_capacity(pred.len());
        for (k, (p, g)) in pred.iter().zip(&gt).enumerate() {
            if (p.width, p.height) != (g.width, g.height) {
                return Err(PipelineError::Compute {
                    stage: "metrics",
                    msg: format!("{}: size differs from its ground truth", image_name(&plan.key, plan.scored[k])),
                });
            }
            let ssim = mvsplat360_metrics::ssim::ssim(&p.data, &g.data, 3, p.height, p.width).map_err(compute("SSIM"))?;
            let psnr = mvsplat360_metrics::psnr::psnr(&p.data, &g.data);
            let v = plan.scored[k];
            scores.push(ImageScores { name: image_name(&plan.key, v), view: v, psnr, ssim, lpips: None, dists: None });
        }
        if nets.lpips.is_some() || nets.dists.is_some() {
            for (b, (pc, gc)) in pred.chunks(NET_BATCH).zip(gt.chunks(NET_BATCH)).enumerate() {
                let tp = image_tensor(&pc.iter().collect::<Vec<_>>())?;
                let tg = image_tensor(&gc.iter().collect::<Vec<_>>())?;
                if let Some(net) = &nets.lpips {
                    for (k, d) in net.distance(&tp, &tg).map_err(compute("LPIPS"))?.into_iter().enumerate() {
                        scores[b * NET_BATCH + k].lpips = Some(d as f64);
                    }
                }
                if let Some(net) = &nets.dists {
                    for (k, d) in net.distance(&tp, &tg).map_err(compute("DISTS"))?.into_iter().enumerate() {
                        scores[b * NET_BATCH + k].dists = Some(d as f64);
                    }
                }
            }
        }
        if let Some(net) = &nets.fid {
            feats.insert(m.key().into(), feat_tensor(fid_features(net, &pred)?)?);
        }
        result.insert(m.key().to_string(), scores);
    }
    if nets.fid.is_some() {
        let f = features_file(out, &plan.key);
        output::atomic_write(&f, |tmp| candle_core::safetensors::save(&feats, tmp).map_err(|e| e.to_string()))?;
    }
    Ok(result)
}

/// Images per metric-network pass.
pub(super) const NET_BATCH: usize = 4;
