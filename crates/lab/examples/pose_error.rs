//! How far estimated cameras (a COLMAP run's) are from the true ones:
//! `pose_error ESTIMATED_SCENE TRUE_SCENE [--json] [--offset K]`.
//!
//! Views are matched by file stem; where stems differ (`frame_00013.png` against `0012.jpg`) by the stem's
//! trailing integer, plus K (ffmpeg numbers frames from 1: `--offset -1`). The estimate may hold a subset of the
//! views. Centres are aligned with the least-squares similarity; errors are in % of the true scene radius,
//! degrees, and % of focal length at the true width. Prints a per-view table, then one JSON line (only the JSON
//! line with `--json`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use mvsplat360_camera::{camera_errors, Camera};

fn main() -> anyhow::Result<()> {
    let mut paths = Vec::new();
    let (mut json, mut offset) = (false, 0i64);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--json" => json = true,
            "--offset" => offset = args.next().context("--offset needs a number")?.parse().context("--offset needs an integer")?,
            _ if a.starts_with("--") => bail!("unknown option {a}"),
            _ => paths.push(PathBuf::from(a)),
        }
    }
    let [est_path, true_path] = paths.as_slice() else {
        bail!("usage: pose_error ESTIMATED_SCENE TRUE_SCENE [--json] [--offset K]");
    };
    let est = read(est_path)?;
    let truth = read(true_path)?;
    let pairs = match_views(&est.view_names, &truth.view_names, offset)?;
    let unmatched: Vec<&str> = (0..est.len()).filter(|i| !pairs.iter().any(|p| p.0 == *i)).map(|i| est.view_names[i].as_str()).collect();
    if !unmatched.is_empty() {
        eprintln!("{} estimated views match no true view: {}", unmatched.len(), unmatched.join(", "));
    }
    let pick = |cams: &[Camera], idx: &dyn Fn(&(usize, usize)) -> usize| pairs.iter().map(|p| cams[idx(p)].clone()).collect::<Vec<_>>();
    let (e_cams, t_cams) = (pick(&est.cameras, &|p| p.0), pick(&truth.cameras, &|p| p.1));
    let errs = camera_errors(&e_cams, &t_cams).with_context(|| format!("aligning {} matched views", pairs.len()))?;

    if !json {
        println!("{:<24} {:<24} {:>10} {:>10} {:>9}", "estimated", "true", "centre %", "rot deg", "focal %");
        for (k, &(i, j)) in pairs.iter().enumerate() {
            println!(
                "{:<24} {:<24} {:>10.4} {:>10.4} {:>9.4}",
                est.view_names[i],
                truth.view_names[j],
                100.0 * errs.centre[k],
                errs.rotation_deg[k],
                100.0 * errs.focal[k]
            );
        }
    }
    let worst = |v: &[f64]| v.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|(k, _)| truth.view_names[pairs[k].1].clone());
    let line = serde_json::json!({
        "n_matched": pairs.len(),
        "n_estimated": est.len(),
        "n_true": truth.len(),
        "scene_radius": errs.scene_radius,
        "scale": errs.similarity.scale,
        "centre_err_mean_pct": 100.0 * errs.centre_stats.mean,
        "centre_err_max_pct": 100.0 * errs.centre_stats.max,
        "centre_err_max_view": worst(&errs.centre),
        "rot_err_mean_deg": errs.rotation_stats.mean,
        "rot_err_max_deg": errs.rotation_stats.max,
        "rot_err_max_view": worst(&errs.rotation_deg),
        "focal_err_mean_pct": 100.0 * errs.focal_stats.mean,
        "focal_err_max_pct": 100.0 * errs.focal_stats.max,
    });
    println!("{line}");
    Ok(())
}

fn read(path: &Path) -> anyhow::Result<mvsplat360_dataset::Scene> {
    mvsplat360_dataset::read_scene(path).with_context(|| format!("reading the scene {}", path.display()))
}

fn stem(name: &str) -> &str {
    Path::new(name).file_stem().and_then(|s| s.to_str()).unwrap_or(name)
}

/// The integer the stem ends with (`frame_00012` → 12), if any.
fn trailing_number(stem: &str) -> Option<i64> {
    let digits = stem.len() - stem.trim_end_matches(|c: char| c.is_ascii_digit()).len();
    stem[stem.len() - digits..].parse().ok()
}

/// (estimated index, true index) pairs: by equal stem, else by trailing integer (+ offset). A number shared by two
/// true views, or two estimated views claiming one true view, is an error: silent mismatches would read as pose
/// errors.
fn match_views(est: &[String], truth: &[String], offset: i64) -> anyhow::Result<Vec<(usize, usize)>> {
    let by_stem: HashMap<&str, usize> = truth.iter().enumerate().map(|(j, n)| (stem(n), j)).collect();
    let mut by_number: HashMap<i64, Vec<usize>> = HashMap::new();
    for (j, n) in truth.iter().enumerate() {
        if let Some(k) = trailing_number(stem(n)) {
            by_number.entry(k).or_default().push(j);
        }
    }
    let mut pairs = Vec::new();
    let mut taken: HashMap<usize, usize> = HashMap::new();
    for (i, n) in est.iter().enumerate() {
        let s = stem(n);
        let j = match by_stem.get(s) {
            Some(&j) if offset == 0 => Some(j),
            _ => match trailing_number(s).and_then(|k| by_number.get(&(k + offset))) {
                Some(js) if js.len() > 1 => {
                    let names: Vec<&str> = js.iter().map(|&j| truth[j].as_str()).collect();
                    bail!("estimated view {n}: its number matches several true views ({})", names.join(", "))
                }
                Some(js) => Some(js[0]),
                None => None,
            },
        };
        if let Some(j) = j {
            if let Some(prev) = taken.insert(j, i) {
                bail!("estimated views {} and {n} both match the true view {}", est[prev], truth[j]);
            }
            pairs.push((i, j));
        }
    }
    if pairs.is_empty() {
        bail!("no estimated view matches a true view by file stem or trailing number (e.g. {:?} vs {:?})", est.first(), truth.first());
    }
    Ok(pairs)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn views_match_by_stem_or_trailing_number() {
        let truth = names(&["images/000.jpg", "images/001.jpg", "images/012.jpg"]);
        assert_eq!(match_views(&names(&["012.png", "000.png"]), &truth, 0).unwrap(), vec![(0, 2), (1, 0)]);
        assert_eq!(match_views(&names(&["frame_00012.png", "x.png"]), &truth, 0).unwrap(), vec![(0, 2)]);
        assert_eq!(match_views(&names(&["frame_00013.png", "frame_00001.png"]), &truth, -1).unwrap(), vec![(0, 2), (1, 0)]);
        assert!(match_views(&names(&["a12.png", "b12.png"]), &truth, 0).is_err());
        assert!(match_views(&names(&["5.png"]), &names(&["a5.jpg", "b5.jpg"]), 0).is_err());
        assert!(match_views(&names(&["zzz.png"]), &truth, 0).is_err());
    }
}
