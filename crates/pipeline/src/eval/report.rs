//! The evaluation's report: per-method means over the scenes, FID over all of them, and `metrics.md`.

use super::*;

pub(super) fn mean(v: &[f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let m = v.iter().sum::<f64>() / v.len() as f64;
    m.is_finite().then_some(m)
}

/// Averages over per-image scores (a network metric only when every image has it).
pub(super) fn method_scores(m: Method, imgs: &[&ImageScores]) -> MethodScores {
    let all = |f: fn(&ImageScores) -> Option<f64>| -> Option<Vec<f64>> { imgs.iter().map(|s| f(s)).collect() };
    MethodScores {
        folder: m.dir().into(),
        images: imgs.len(),
        psnr: mean(&imgs.iter().map(|s| s.psnr).collect::<Vec<_>>()),
        ssim: mean(&imgs.iter().map(|s| s.ssim).collect::<Vec<_>>()),
        lpips: all(|s| s.lpips).and_then(|v| mean(&v)),
        dists: all(|s| s.dists).and_then(|v| mean(&v)),
        fid: None,
    }
}

/// Set-level FID of one method from the scenes' saved features.
pub(super) fn set_fid(out: &Path, records: &[&SceneRecord], m: Method, warnings: &mut Vec<String>) -> Result<Option<f64>> {
    let d = mvsplat360_metrics::inception::DIM;
    let (mut pred, mut gt, mut n) = (Vec::<f64>::new(), Vec::<f64>::new(), 0usize);
    for r in records {
        let path = features_file(out, &r.scene);
        let t = candle_core::safetensors::load(&path, &Device::Cpu)
            .map_err(|e| PipelineError::Compute { stage: "FID", msg: format!("{}: {e}", path.display()) })?;
        let rows = |k: &str| -> Result<Vec<f32>> {
            let x = t.get(k).ok_or_else(|| PipelineError::Compute { stage: "FID", msg: format!("{}: no `{k}` features", path.display()) })?;
            x.flatten_all().and_then(|x| x.to_vec1::<f32>()).map_err(compute("FID"))
        };
        let (p, g) = (rows(m.key())?, rows("gt")?);
        if p.len() != r.scored.len() * d || g.len() != p.len() {
            return Err(PipelineError::Compute { stage: "FID", msg: format!("{}: feature count does not match the scene's images", path.display()) });
        }
        pred.extend(p.into_iter().map(f64::from));
        gt.extend(g.into_iter().map(f64::from));
        n += r.scored.len();
    }
    if n < 2 {
        warnings.push(format!("FID of {} skipped (null): it needs at least 2 images, got {n}", m.dir()));
        return Ok(None);
    }
    Ok(mvsplat360_metrics::frechet::frechet_from_features(&pred, n, &gt, n, d))
}

pub(super) fn fmt_opt(v: Option<f64>, digits: usize) -> String {
    v.map(|x| format!("{x:.digits$}")).unwrap_or_else(|| "–".into())
}

/// The markdown tables: overall per method (the paper's columns), then per scene for the primary method.
pub fn markdown(summary_line: &str, methods: &[(Method, MethodScores)], per_scene: &[(String, MethodScores)], primary: Method, blended: bool) -> String {
    let mut s = String::from("# Evaluation\n\n");
    s.push_str(summary_line);
    s.push_str("\n\n| Method | Folder | Images | PSNR↑ | SSIM↑ | LPIPS↓ | DISTS↓ | FID↓ |\n|---|---|---:|---:|---:|---:|---:|---:|\n");
    for (m, sc) in methods {
        s.push_str(&format!(
            "| {} | `{}` | {} | {} | {} | {} | {} | {} |\n",
            m.label(blended),
            sc.folder,
            sc.images,
            fmt_opt(sc.psnr, 2),
            fmt_opt(sc.ssim, 3),
            fmt_opt(sc.lpips, 3),
            fmt_opt(sc.dists, 3),
            fmt_opt(sc.fid, 2)
        ));
    }
    s.push_str(&format!("\n## Per scene (`{}`)\n\n| Scene | Images | PSNR↑ | SSIM↑ | LPIPS↓ | DISTS↓ |\n|---|---:|---:|---:|---:|---:|\n", primary.dir()));
    for (k, sc) in per_scene {
        s.push_str(&format!(
            "| {k} | {} | {} | {} | {} | {} |\n",
            sc.images,
            fmt_opt(sc.psnr, 2),
            fmt_opt(sc.ssim, 3),
            fmt_opt(sc.lpips, 3),
            fmt_opt(sc.dists, 3)
        ));
    }
    s.push_str("\nPSNR, SSIM, LPIPS (VGG) and DISTS are means over the images; FID is over the whole image set. – = not computed (metric weights missing, or FID with fewer than 2 images).\n");
    s
}
