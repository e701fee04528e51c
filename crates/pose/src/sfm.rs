//! The COLMAP runs, as nerfstudio's `ns-process-data` drives them: feature extraction with one shared camera
//! (per device: image size and EXIF make, model and focal length), a sequential (video; its first and last frames also matched, for loop closure) or exhaustive
//! (photos) matcher, the incremental mapper, then `image_undistorter` to a PINHOLE model. Each stage feeds a
//! progress bar from COLMAP's own log lines.

use std::path::{Path, PathBuf};

use crate::colmap_log::{self, MapperLog};
use crate::engine::{run_logged, ColmapGpu, ColmapInfo, CommandRecord};
use crate::error::PoseError;
use crate::Progress;

/// Camera models `--camera-model` takes (perspective models that `image_undistorter` turns into PINHOLE).
pub const CAMERA_MODELS: [&str; 6] = ["SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "SIMPLE_PINHOLE", "PINHOLE"];

/// `--matcher`; without it a video, or more than [`crate::EXHAUSTIVE_MAX`] photos, is matched in sequence and
/// fewer photos exhaustively.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Matcher {
    Sequential,
    Exhaustive,
}

impl Matcher {
    pub(crate) fn command(self) -> &'static str {
        match self {
            Matcher::Sequential => "sequential_matcher",
            Matcher::Exhaustive => "exhaustive_matcher",
        }
    }
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// Runs one COLMAP command, with a bar fed by `progress_of` over its lines; a non-zero exit is an error
/// naming the log (unless `allow_failure`: the mapper's failure is a result the caller explains).
#[allow(clippy::too_many_arguments)]
fn colmap_stage(
    colmap: &ColmapInfo,
    stage: &str,
    args: Vec<String>,
    logs: &Path,
    total: u64,
    progress: &dyn Progress,
    on_line: &mut dyn FnMut(&str) -> Option<u64>,
    allow_failure: bool,
) -> Result<CommandRecord, PoseError> {
    let argv: Vec<String> = std::iter::once(s(&colmap.path)).chain(std::iter::once(stage.to_string())).chain(args).collect();
    let log = logs.join(format!("{stage}.log"));
    progress.begin(stage, total);
    let rec = run_logged(stage, &argv, &log, &mut |l| {
        if let Some(pos) = on_line(l) {
            progress.set(pos);
        }
    })?;
    progress.end();
    if crate::engine::was_stopped() {
        return Err(PoseError::Interrupted { stage: stage.into(), work: logs.parent().unwrap_or(logs).to_path_buf() });
    }
    if rec.exit_code != Some(0) && !allow_failure {
        let tail = last_lines(&log, 6);
        return Err(PoseError::Engine {
            program: format!("colmap {stage}"),
            msg: format!("failed ({}); its log is {}; last lines:\n{tail}", rec.exit_code.map_or("killed".into(), |c| format!("exit {c}")), log.display()),
        });
    }
    Ok(rec)
}

pub fn last_lines(path: &Path, n: usize) -> String {
    let t = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = t.lines().filter(|l| !l.trim().is_empty()).collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

pub struct Work<'a> {
    pub colmap: &'a ColmapInfo,
    pub root: &'a Path,
    pub images: PathBuf,
    pub database: PathBuf,
    pub logs: PathBuf,
    pub gpu: ColmapGpu,
}

impl Work<'_> {
    pub fn extract(&self, camera_model: &str, per_folder: bool, n: u64, progress: &dyn Progress) -> Result<CommandRecord, PoseError> {
        let mut args = vec!["--database_path".into(), s(&self.database), "--image_path".into(), s(&self.images)];
        args.extend(["--ImageReader.camera_model".into(), camera_model.into()]);
        // One camera for all frames of one device (a folder each when there are several, see
        // `photos::camera_groups`): intrinsics are shared, which keeps the focal from drifting.
        let single = if per_folder { "--ImageReader.single_camera_per_folder" } else { "--ImageReader.single_camera" };
        args.extend([single.into(), "1".into()]);
        args.extend(self.colmap.extraction_gpu_flag(self.gpu));
        colmap_stage(self.colmap, "feature_extractor", args, &self.logs, n, progress, &mut |l| colmap_log::extraction_progress(l).map(|p| p.0), false)
    }

    pub fn matches(&self, matcher: Matcher, n: u64, progress: &dyn Progress) -> Result<CommandRecord, PoseError> {
        let mut args = vec!["--database_path".into(), s(&self.database)];
        args.extend(self.colmap.matching_gpu_flag(self.gpu));
        let mut total = n;
        colmap_stage(
            self.colmap,
            matcher.command(),
            args,
            &self.logs,
            n,
            progress,
            &mut |l| {
                let (i, of) = colmap_log::matching_progress(l)?;
                if of != total {
                    total = of;
                    progress.set_total(of);
                }
                Some(i)
            },
            false,
        )
    }

    /// Matches the first frames against the last ones (`loop_pairs`), which the sequential matcher never pairs;
    /// `None` when the sequence is too short to have such pairs.
    pub fn close_loop(&self, names: &[String], progress: &dyn Progress) -> Result<Option<CommandRecord>, PoseError> {
        let pairs = loop_pairs(names);
        if pairs.is_empty() {
            return Ok(None);
        }
        let list = self.root.join("loop_pairs.txt");
        let text: String = pairs.iter().map(|(a, b)| format!("{a} {b}\n")).collect();
        std::fs::write(&list, text).map_err(|e| PoseError::io(&list, e))?;
        let mut args = vec!["--database_path".into(), s(&self.database), "--match_list_path".into(), s(&list), "--match_type".into(), "pairs".into()];
        args.extend(self.colmap.matching_gpu_flag(self.gpu));
        let rec = colmap_stage(self.colmap, "matches_importer", args, &self.logs, 0, progress, &mut |l| colmap_log::matching_progress(l).map(|p| p.0), false)?;
        Ok(Some(rec))
    }

    /// The mapper, into `sparse/0`, `sparse/1`, …; returns its record and what its log said.
    pub fn map(&self, n: u64, progress: &dyn Progress) -> Result<(CommandRecord, MapperLog, PathBuf), PoseError> {
        let sparse = self.root.join("sparse");
        if sparse.exists() {
            std::fs::remove_dir_all(&sparse).map_err(|e| PoseError::io(&sparse, e))?;
        }
        std::fs::create_dir_all(&sparse).map_err(|e| PoseError::io(&sparse, e))?;
        let mut args = vec!["--database_path".into(), s(&self.database), "--image_path".into(), s(&self.images), "--output_path".into(), s(&sparse)];
        // nerfstudio's setting for COLMAP ≥ 3.7: a tighter global bundle adjustment tolerance.
        args.push("--Mapper.ba_global_function_tolerance=1e-6".into());
        let mut log = MapperLog::default();
        let mut best = 0u64;
        let rec = colmap_stage(
            self.colmap,
            "mapper",
            args,
            &self.logs,
            n,
            progress,
            &mut |l| {
                log.feed(l);
                if colmap_log::starts_model(l) {
                    best = best.max(2);
                }
                if let Some(k) = colmap_log::registered_count(l) {
                    best = best.max(k);
                }
                Some(best)
            },
            true,
        )?;
        Ok((rec, log, sparse))
    }

    pub fn undistort(&self, model: &Path, out: &Path, n: u64, progress: &dyn Progress) -> Result<CommandRecord, PoseError> {
        let args = vec![
            "--image_path".into(),
            s(&self.images),
            "--input_path".into(),
            s(model),
            "--output_path".into(),
            s(out),
            "--output_type".into(),
            "COLMAP".into(),
        ];
        colmap_stage(self.colmap, "image_undistorter", args, &self.logs, n, progress, &mut |l| colmap_log::undistortion_progress(l).map(|p| p.0), false)
    }

    pub fn analyze(&self, model: &Path, progress: &dyn Progress) -> Result<(CommandRecord, Option<f64>), PoseError> {
        let args = vec!["--path".into(), s(model)];
        let rec = colmap_stage(self.colmap, "model_analyzer", args, &self.logs, 0, progress, &mut |_| None, true)?;
        let text = std::fs::read_to_string(self.logs.join("model_analyzer.log")).unwrap_or_default();
        Ok((rec, colmap_log::mean_reprojection_error(&text)))
    }
}

/// Frames matched for loop closure: each of the first `LOOP_FRAMES` against each of the last, where the
/// sequential matcher's window did not already pair them. A video that goes round the scene ends where it began;
/// without these pairs the mapper sees an open chain and its drift ends up in the last frames (measured on the
/// 24-frame test video at 320×180, 5 runs each: worst centre error 1.0–1.8 % of the scene radius without, 0.6–0.8 % with).
pub fn loop_pairs(names: &[String]) -> Vec<(String, String)> {
    let n = names.len();
    let k = LOOP_FRAMES.min(n / 2);
    let mut out = vec![];
    for i in 0..k {
        for j in n - k..n {
            if j > i + SEQUENTIAL_OVERLAP {
                out.push((names[i].clone(), names[j].clone()));
            }
        }
    }
    out
}

/// Frames at each end of a sequence matched for loop closure: 100 pairs, seconds next to the sequential matcher.
pub const LOOP_FRAMES: usize = 10;
/// COLMAP's `SequentialMatching.overlap` default: frames this close are paired by the sequential matcher.
const SEQUENTIAL_OVERLAP: usize = 10;

/// The sub-models the mapper wrote (`sparse/N` holding `images.bin`), with their registered image names,
/// largest first (ties: the lower index, the one COLMAP built first).
pub fn sub_models(sparse: &Path) -> Result<Vec<(usize, PathBuf, Vec<String>)>, PoseError> {
    let mut out = vec![];
    let Ok(rd) = std::fs::read_dir(sparse) else { return Ok(out) };
    for e in rd.flatten() {
        let p = e.path();
        let Some(idx) = p.file_name().and_then(|n| n.to_str()).and_then(|n| n.parse::<usize>().ok()) else { continue };
        let images = p.join("images.bin");
        if !images.is_file() {
            continue;
        }
        let names = mvsplat360_dataset::colmap::read_images_bin(&images)?.into_iter().map(|i| i.name).collect();
        out.push((idx, p, names));
    }
    choose_order(&mut out);
    Ok(out)
}

/// Largest first; among equals the lower index.
pub fn choose_order<T>(models: &mut [(usize, T, Vec<String>)]) {
    models.sort_by(|a, b| b.2.len().cmp(&a.2.len()).then(a.0.cmp(&b.0)));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loop_pairs_join_the_ends_beyond_the_sequential_window() {
        let names = |n: usize| (0..n).map(|i| format!("f{i:02}")).collect::<Vec<_>>();
        // 60 frames: every one of the first 10 with every one of the last 10.
        let p = loop_pairs(&names(60));
        assert_eq!(p.len(), 100);
        assert_eq!((p[0].0.as_str(), p[0].1.as_str(), p[99].0.as_str(), p[99].1.as_str()), ("f00", "f50", "f09", "f59"));
        // 24 frames: first 0..10 × last 14..24 with j − i > 10: 4 × 10 + 9 + 8 + 7 + 6 + 5 + 4.
        let p = loop_pairs(&names(24));
        assert_eq!(p.len(), 79);
        assert!(p.iter().all(|(a, b)| b[1..].parse::<usize>().unwrap() > a[1..].parse::<usize>().unwrap() + 10));
        // Up to 11 frames every pair is inside the window; at 12 only the two ends are outside it.
        assert!(loop_pairs(&names(11)).is_empty() && loop_pairs(&names(2)).is_empty());
        assert_eq!(loop_pairs(&names(12)), vec![("f00".to_string(), "f11".to_string())]);
    }

    #[test]
    fn the_largest_sub_model_is_kept() {
        let n = |k: usize| (0..k).map(|i| format!("{i}.jpg")).collect::<Vec<_>>();
        let mut m = vec![(0, (), n(7)), (1, (), n(12)), (2, (), n(12)), (3, (), n(2))];
        choose_order(&mut m);
        let order: Vec<usize> = m.iter().map(|x| x.0).collect();
        assert_eq!(order, [1, 2, 0, 3]);
        let mut one = vec![(0, (), n(3))];
        choose_order(&mut one);
        assert_eq!(one[0].0, 0);
    }
}
