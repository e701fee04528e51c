//! Which views are context (encoder input) and which cameras are rendered: explicit view indices,
//! farthest-point sampling, an evaluation index, a 360° orbit or the scene's own path.

use std::path::{Path, PathBuf};

use mvsplat360_camera::{trajectory, Camera};
use mvsplat360_dataset::Scene;

use crate::error::{flag, Result};

/// How the context views are chosen.
#[derive(Debug, Clone, PartialEq)]
pub enum ContextSpec {
    /// Explicit view indices (`--context 3,17,40`).
    Views(Vec<usize>),
    /// Farthest-point sampling of the camera centres (`--num-context N`).
    Count(usize),
    /// An evaluation index (`--index FILE [--scene-key K]`).
    Index { file: PathBuf, scene_key: Option<String> },
}

/// Which cameras are rendered.
#[derive(Debug, Clone, PartialEq)]
pub enum TargetSpec {
    /// The cameras of these views (sorted), so renders compare pixel for pixel with the photos.
    Views(Vec<usize>),
    /// A closed 360° orbit of this many frames around the context cameras.
    Orbit(usize),
    /// The scene's own camera path, smoothed (`render_stable_poses`), this many frames.
    Path(usize),
    /// The evaluation index's targets (needs `ContextSpec::Index`).
    Index,
}

/// One rendered camera: a scene view's (with its photo) or a generated one.
#[derive(Debug, Clone)]
pub struct Target {
    pub camera: Camera,
    /// The scene view it comes from, when it is one.
    pub view: Option<usize>,
}

/// The resolved choice.
#[derive(Debug, Clone)]
pub struct ViewChoice {
    pub context: Vec<usize>,
    /// Targets in the scene's raw camera space (before preprocessing).
    pub targets: Vec<Target>,
    /// Subset of target view indices to score (the index's `target_quantify`), when given.
    pub quantify: Option<Vec<usize>>,
}

/// Parse `3,17,40` into view indices.
pub fn parse_list(s: &str) -> std::result::Result<Vec<usize>, String> {
    s.split(',')
        .map(|p| p.trim())
        .filter(|p| !p.is_empty())
        .map(|p| p.parse::<usize>().map_err(|_| format!("`{p}` is not a view index (expected e.g. 3,17,40)")))
        .collect()
}

fn check_indices(which: &'static str, list: &[usize], scene: &Scene) -> Result<()> {
    for &i in list {
        if i >= scene.len() {
            return Err(flag(
                which,
                format!("view {i} is out of range: scene {} has {} views (0..{})", scene.name, scene.len(), scene.len().saturating_sub(1)),
            ));
        }
    }
    let mut seen = std::collections::BTreeSet::new();
    for &i in list {
        if !seen.insert(i) {
            return Err(flag(which, format!("view {i} ({}) is listed twice", scene.view_names[i])));
        }
    }
    Ok(())
}

/// The index entry for `scene`: `scene_key`, else the scene's name, else the only entry.
pub fn index_entry(file: &Path, scene_key: Option<&str>, scene: &Scene) -> Result<mvsplat360_dataset::EvaluationEntry> {
    let index = mvsplat360_dataset::read_evaluation_index(file)?;
    let key = match scene_key {
        Some(k) => k.to_string(),
        None if index.contains_key(&scene.name) => scene.name.clone(),
        None if index.len() == 1 => index.keys().next().cloned().unwrap_or_default(),
        None => {
            return Err(flag(
                "--scene-key",
                format!("{} has {} scenes and none is named {}; pick one with --scene-key", file.display(), index.len(), scene.name),
            ))
        }
    };
    match index.get(&key) {
        Some(Some(e)) => {
            mvsplat360_dataset::index::check_entry(file, &key, e, scene.len())?;
            Ok(e.clone())
        }
        Some(None) => Err(flag("--scene-key", format!("{}: scene {key} is null in the index (skipped by the protocol)", file.display()))),
        None => Err(flag("--scene-key", format!("{}: no scene {key} in the index", file.display()))),
    }
}

/// Resolve the context and target choice against a scene; every bad index is one error naming the flag.
pub fn choose(scene: &Scene, context: &ContextSpec, targets: &TargetSpec) -> Result<ViewChoice> {
    let mut entry = None;
    let ctx = match context {
        ContextSpec::Views(v) => {
            check_indices("--context", v, scene)?;
            v.clone()
        }
        ContextSpec::Count(n) => {
            if *n > scene.len() {
                return Err(flag("--num-context", format!("scene {} has {} views, fewer than {n}", scene.name, scene.len())));
            }
            mvsplat360_camera::select::farthest_views(&scene.cameras, *n, mvsplat360_camera::select::FpsStart::First)
        }
        ContextSpec::Index { file, scene_key } => {
            let e = index_entry(file, scene_key.as_deref(), scene)?;
            check_indices("--index (context)", &e.context, scene)?;
            let c = e.context.clone();
            entry = Some(e);
            c
        }
    };
    if ctx.len() < 2 {
        let which = match context {
            ContextSpec::Count(_) => "--num-context",
            ContextSpec::Index { .. } => "--index",
            ContextSpec::Views(_) => "--context",
        };
        return Err(flag(which, format!("need at least 2 context views (the encoder matches views against each other), got {}", ctx.len())));
    }
    let ctx_cams: Vec<Camera> = ctx.iter().map(|&i| scene.cameras[i].clone()).collect();
    let mut quantify = None;
    let tg = match targets {
        TargetSpec::Views(v) => {
            check_indices("--targets", v, scene)?;
            let mut v = v.clone();
            v.sort_unstable();
            v.into_iter().map(|i| Target { camera: scene.cameras[i].clone(), view: Some(i) }).collect()
        }
        TargetSpec::Orbit(m) => {
            if *m == 0 {
                return Err(flag("--orbit", "needs at least 1 frame"));
            }
            trajectory::orbit(&ctx_cams, *m).into_iter().map(|c| Target { camera: c, view: None }).collect()
        }
        TargetSpec::Path(m) => {
            if *m == 0 {
                return Err(flag("--path", "needs at least 1 frame"));
            }
            stable_path(&scene.cameras, *m).into_iter().map(|c| Target { camera: c, view: None }).collect()
        }
        TargetSpec::Index => {
            let Some(e) = &entry else {
                return Err(flag("--targets", "the index's targets need --index"));
            };
            check_indices("--index (target)", &e.target, scene)?;
            quantify = e.target_quantify.clone();
            e.target.iter().map(|&i| Target { camera: scene.cameras[i].clone(), view: Some(i) }).collect()
        }
    };
    Ok(ViewChoice { context: ctx, targets: tg, quantify })
}

/// The scene's own path as the official video mode renders it: `frames` views equally spaced through the
/// sequence (all views when there are fewer), poses smoothed by the official stabilisation (kernel 15).
pub fn stable_path(cameras: &[Camera], frames: usize) -> Vec<Camera> {
    let n = cameras.len();
    let picked: Vec<Camera> = if frames >= n { cameras.to_vec() } else { (0..frames).map(|i| cameras[(i * n) / frames].clone()).collect() };
    trajectory::stabilize_official(&picked, STABLE_K_SIZE)
}

/// Smoothing kernel size of the official `render_stable_poses` (`test.stable_k_size`).
pub const STABLE_K_SIZE: usize = 15;
