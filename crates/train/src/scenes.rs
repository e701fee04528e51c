//! Training scenes at the training size: procedural (rendered on demand), folders of posed photos, `.torch`
//! chunks (streamed one chunk at a time). Folder and chunk scenes are scaled like `render --scene-scale auto`
//! does with user scenes, so training and inference see the same depth range.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use mvsplat360_camera::Camera;
use mvsplat360_dataset::{ImageF32, Scene};
use mvsplat360_pipeline::preprocess::{InputSize, Preprocess};
use rand::Rng;

use crate::config::Source;
use crate::data::procedural::{self, GenOptions};
use crate::error::{Result, TrainError};

/// One scene ready for the sampler: every view at the training size.
#[derive(Debug, Clone)]
pub struct TrainScene {
    pub name: String,
    pub images: Vec<ImageF32>,
    pub cameras: Vec<Camera>,
    /// Ground-truth ray-distance maps (H·W each, infinite = sky or unknown), for the sources that know them
    /// (procedural scenes; folder scenes with `depth/`, see [`read_depths`]).
    pub depths: Option<Vec<Vec<f32>>>,
}

/// A source of scenes with a cache of what it has loaded.
pub struct SceneSource {
    kind: Kind,
    pre: Preprocess,
    cache: HashMap<usize, TrainScene>,
}

enum Kind {
    Procedural { count: u64, seed: u64, views: usize, width: u32, height: u32 },
    Folder { scenes: Vec<PathBuf> },
    Chunks { files: Vec<PathBuf>, loaded: Option<(usize, Vec<Scene>)> },
}

impl SceneSource {
    pub fn open(src: &Source, width: u32, height: u32, multiple: u32) -> Result<Self> {
        let pre = Preprocess { size: InputSize::Fixed { width, height }, multiple };
        let kind = match src {
            Source::Procedural { count, seed, views } => {
                if *count == 0 || *views < 3 {
                    return Err(TrainError::Data(format!("procedural source: need count ≥ 1 and views ≥ 3 (got {count}, {views})")));
                }
                Kind::Procedural { count: *count, seed: *seed, views: *views, width, height }
            }
            Source::Folder { path } => Kind::Folder { scenes: scene_dirs(path)? },
            Source::Chunks { path } => Kind::Chunks { files: chunk_files(path)?, loaded: None },
        };
        Ok(Self { kind, pre, cache: HashMap::new() })
    }

    /// A random scene of this source for training step `step` (`seed`: the run's). The chunk a `chunks` source
    /// reads is a function of `(seed, step)` alone, not of what this process read before, so a resumed run and
    /// every rank read the chunk an uninterrupted single process would.
    pub fn draw(&mut self, rng: &mut impl Rng, seed: u64, step: u64) -> Result<TrainScene> {
        match &mut self.kind {
            Kind::Procedural { count, seed, views, width, height } => {
                let s = *seed + rng.gen_range(0..*count);
                let g = procedural::generate(s, &GenOptions { views: *views, width: *width, height: *height, samples: 2 });
                let images = g.views.iter().map(|v| ImageF32 { width: *width, height: *height, data: v.image.clone() }).collect();
                let depths = g.views.iter().map(|v| v.depth.clone()).collect();
                let cameras = g.views.into_iter().map(|v| v.camera).collect();
                Ok(TrainScene { name: g.name, images, cameras, depths: Some(depths) })
            }
            Kind::Folder { scenes } => {
                let i = rng.gen_range(0..scenes.len());
                if let Some(s) = self.cache.get(&i) {
                    return Ok(s.clone());
                }
                let s = read_folder_scene(&scenes[i], &self.pre)?;
                self.cache.insert(i, s.clone());
                Ok(s)
            }
            Kind::Chunks { files, loaded } => {
                // Stream: stay on one chunk for CHUNK_STEPS steps, as the official loader iterates chunk by chunk.
                let f = chunk_of_step(seed, step, files.len());
                if loaded.as_ref().is_none_or(|(g, _)| *g != f) {
                    let scenes = mvsplat360_dataset::torch_chunk::read_chunk(&files[f])
                        .map_err(|e| TrainError::Data(format!("{}: {e}", files[f].display())))?
                        .into_iter()
                        .map(|c| c.into_scene(&files[f]))
                        .collect::<std::result::Result<Vec<_>, _>>()
                        .map_err(|e| TrainError::Data(format!("{}: {e}", files[f].display())))?;
                    if scenes.is_empty() {
                        return Err(TrainError::Data(format!("{}: the chunk holds no scene", files[f].display())));
                    }
                    *loaded = Some((f, scenes));
                }
                let (_, scenes) = loaded.as_ref().expect("loaded above");
                let s = &scenes[rng.gen_range(0..scenes.len())];
                prepare(s, &self.pre)
            }
        }
    }
}

/// Training steps spent on one chunk of a `chunks` source before the next is drawn.
pub const CHUNK_STEPS: u64 = 20;

/// The chunk (of `n`) a `chunks` source reads at `step`: a fresh uniform draw every [`CHUNK_STEPS`] steps,
/// seeded by `(seed, step / CHUNK_STEPS)` (splitmix64).
pub fn chunk_of_step(seed: u64, step: u64, n: usize) -> usize {
    let mut z = seed ^ (step / CHUNK_STEPS).wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ 0xc4ce_b9fe_1a85_ec53;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    (z % n.max(1) as u64) as usize
}

/// Preprocess every view to the training size.
pub fn prepare(scene: &Scene, pre: &Preprocess) -> Result<TrainScene> {
    let mut images = Vec::with_capacity(scene.len());
    let mut cameras = Vec::with_capacity(scene.len());
    for i in 0..scene.len() {
        let img = scene.image(i).map_err(|e| TrainError::Data(format!("scene {}: {e}", scene.name)))?;
        let (img, cam) = pre.view(&img, &scene.cameras[i])?;
        images.push(img);
        cameras.push(cam);
    }
    Ok(TrainScene { name: scene.name.clone(), images, cameras, depths: None })
}

/// A folder scene at the training size, with its depth maps when it has them.
pub fn read_folder_scene(dir: &Path, pre: &Preprocess) -> Result<TrainScene> {
    let scene = mvsplat360_dataset::read_scene(dir).map_err(|e| TrainError::Data(format!("{}: {e}", dir.display())))?;
    let mut s = prepare(&scene, pre)?;
    s.depths = read_depths(dir, &scene, &s.cameras)?;
    Ok(s)
}

/// The ray-distance maps of a folder scene (`scripts/render-povray-scene --depth` writes them):
/// `depth/<view's file stem>.png`, 16-bit greyscale, distance = value × `unit` of `depth/depth.json`, 0 = unknown.
/// None when the folder has no `depth/depth.json`. Resampling a depth map would blend surfaces, so they are used
/// only when the photos already are at the training size (`prepared` = the views' cameras after preprocessing).
pub fn read_depths(dir: &Path, scene: &Scene, prepared: &[Camera]) -> Result<Option<Vec<Vec<f32>>>> {
    let meta = dir.join("depth").join("depth.json");
    if !meta.is_file() {
        return Ok(None);
    }
    #[derive(serde::Deserialize)]
    struct Meta {
        unit: f64,
    }
    let bad = |p: &Path, msg: String| TrainError::Data(format!("{}: {msg}", p.display()));
    let text = std::fs::read_to_string(&meta).map_err(|e| bad(&meta, e.to_string()))?;
    let m: Meta = serde_json::from_str(&text).map_err(|e| bad(&meta, format!("{e} (expected {{\"unit\": <distance per step>}})")))?;
    if !(m.unit.is_finite() && m.unit > 0.0) {
        return Err(bad(&meta, format!("`unit` must be a positive number, got {}", m.unit)));
    }
    let mut out = Vec::with_capacity(scene.len());
    for ((name, cam), pc) in scene.view_names.iter().zip(&scene.cameras).zip(prepared) {
        if (pc.width, pc.height, pc.fx, pc.cx, pc.cy) != (cam.width, cam.height, cam.fx, cam.cx, cam.cy) {
            return Err(bad(
                dir,
                format!(
                    "view {name} is {}×{} but trained at {}×{}: depth maps are only used when the photos are at the \
                     training size; render the scene at that size or remove depth/",
                    cam.width, cam.height, pc.width, pc.height
                ),
            ));
        }
        let stem = Path::new(name).file_stem().and_then(|s| s.to_str()).unwrap_or(name);
        let p = dir.join("depth").join(format!("{stem}.png"));
        let need = |e: String| bad(&p, format!("{e} (every view needs its depth map once depth/depth.json exists)"));
        let len = std::fs::metadata(&p).map_err(|e| need(e.to_string()))?.len();
        let reader = image::ImageReader::open(&p).and_then(|r| r.with_guessed_format()).map_err(|e| need(e.to_string()))?;
        let map = mvsplat360_dataset::image::decode_limited(reader, len).map_err(need)?;
        if map.color() != image::ColorType::L16 {
            return Err(bad(&p, format!("expected a 16-bit greyscale PNG, got {:?}", map.color())));
        }
        if (map.width(), map.height()) != (cam.width, cam.height) {
            return Err(bad(&p, format!("the depth map is {}×{} but its photo is {}×{}", map.width(), map.height(), cam.width, cam.height)));
        }
        out.push(map.to_luma16().into_raw().into_iter().map(|v| if v == 0 { f32::INFINITY } else { (v as f64 * m.unit) as f32 }).collect());
    }
    Ok(Some(out))
}

/// Scene folders under `path` (itself when it is a scene).
fn scene_dirs(path: &Path) -> Result<Vec<PathBuf>> {
    let is_scene = |p: &Path| p.join("transforms.json").is_file() || p.join("sparse").is_dir();
    if is_scene(path) {
        return Ok(vec![path.to_path_buf()]);
    }
    let rd = std::fs::read_dir(path).map_err(|e| TrainError::Data(format!("{}: {e} (a folder source needs a folder of scenes)", path.display())))?;
    let mut out: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir() && is_scene(p)).collect();
    out.sort();
    if out.is_empty() {
        return Err(TrainError::Data(format!("{}: no scene folders (with transforms.json or sparse/) inside", path.display())));
    }
    Ok(out)
}

fn chunk_files(path: &Path) -> Result<Vec<PathBuf>> {
    if path.is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    let rd =
        std::fs::read_dir(path).map_err(|e| TrainError::Data(format!("{}: {e} (a chunks source needs a .torch file or a folder of them)", path.display())))?;
    let mut out: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|x| x == "torch")).collect();
    out.sort();
    if out.is_empty() {
        return Err(TrainError::Data(format!("{}: no .torch chunks inside", path.display())));
    }
    Ok(out)
}

/// A scene of the held-out protocol the analysis examples share (`oracle`, `fill`): 32 views on a loop, 5
/// context views by farthest-point sampling, every other view a target. `arg` is a procedural seed (rendered
/// at `width`×`height` with its ray distances) or a scene folder (context views as `heldout` chooses them).
/// Returns the scene, its views and a label.
pub fn protocol_scene(arg: &str, width: u32, height: u32, multiple: u32) -> Result<(TrainScene, crate::sampler::ViewSample, String)> {
    use crate::sampler::{self, SamplerSettings, ViewSample};
    use mvsplat360_pipeline::views::{choose, ContextSpec, TargetSpec};
    use rand::SeedableRng;
    let (scene, mut v, label) = match arg.parse::<u64>() {
        Ok(seed) => {
            let g = procedural::generate(seed, &GenOptions { views: 32, width, height, samples: 2 });
            let images = g.views.iter().map(|v| ImageF32 { width, height, data: v.image.clone() }).collect();
            let depths = Some(g.views.iter().map(|v| v.depth.clone()).collect());
            let cameras: Vec<_> = g.views.into_iter().map(|v| v.camera).collect();
            let scene = TrainScene { name: g.name, images, cameras, depths };
            let s = SamplerSettings { num_context: 5, num_target: 1, gap: None, gap_initial: None, warm_up: 1.0, closed_loop: true, flip: false };
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            let v = sampler::sample(&scene.cameras, &s, &mut rng).ok_or_else(|| TrainError::Data(format!("seed {seed}: no views")))?;
            let label = format!("{} (seed {seed})", scene.name);
            (scene, v, label)
        }
        Err(_) => {
            let dir = Path::new(arg);
            let pre = Preprocess { size: InputSize::Fixed { width, height }, multiple };
            let scene = read_folder_scene(dir, &pre)?;
            let raw = mvsplat360_dataset::read_scene(dir).map_err(|e| TrainError::Data(format!("{}: {e}", dir.display())))?;
            let choice = choose(&raw, &ContextSpec::Count(5), &TargetSpec::Views(vec![0]))?;
            let v = ViewSample { context: choice.context, target: vec![], flip: false };
            let label = dir.file_name().map_or(arg.to_string(), |n| n.to_string_lossy().to_string());
            (scene, v, label)
        }
    };
    v.target = (0..scene.cameras.len()).filter(|i| !v.context.contains(i)).collect();
    Ok((scene, v, label))
}
