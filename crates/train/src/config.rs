//! The training configuration (`mvsplat360 train --config <toml>`). Encoder fields keep the official YAML names;
//! paths are relative to the working directory. A config may start from another: `base = "other.toml"` (relative
//! to the config's folder) takes that file's settings, and the config's own tables override them key by key
//! (a value that is not a table, such as `data.sources`, replaces the base's whole).

use std::path::{Path, PathBuf};

use mvsplat360_encoder::EncoderCostVolumeCfg;
use serde::{Deserialize, Serialize};

use crate::error::{Result, TrainError};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub model: ModelSection,
    pub data: DataSection,
    pub train: TrainSection,
}

/// What is trained: the encoder at a fixed input size, and optionally the refiner's UNet ([`crate::refiner`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSection {
    /// Experiment name written into the model folder.
    #[serde(default = "default_experiment")]
    pub experiment: String,
    /// Training (and the shipped model's) input size; multiples of the encoder's 64.
    pub width: u32,
    pub height: u32,
    #[serde(default = "one")]
    pub near: f32,
    #[serde(default = "hundred")]
    pub far: f32,
    /// Encoder config (official names; unspecified fields = DL3DV experiment defaults).
    #[serde(default)]
    pub encoder: EncoderCostVolumeCfg,
    /// Refiner (UNet, VAE, CLIP configs with official names; unspecified fields = MVSplat360's). Absent: 3DGS
    /// only. Present: its UNet is trained with the diffusion and latent-alignment losses, VAE and CLIP frozen.
    #[serde(default)]
    pub refiner: Option<mvsplat360_pipeline::model::RefinerModelConfig>,
    /// Test-time fitting that `render` runs by default with the exported model (`[model.fit]`; not trained,
    /// written into the model folder's config).
    #[serde(default)]
    pub fit: Option<mvsplat360_pipeline::fit::FitSettings>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum Source {
    /// Procedural scenes rendered on the fly: `count` distinct seeds starting at `seed`.
    Procedural {
        count: u64,
        #[serde(default)]
        seed: u64,
        #[serde(default = "default_views")]
        views: usize,
    },
    /// A folder of scenes (each subfolder with `transforms.json` or COLMAP `sparse/`), e.g. POV-Ray renders.
    Folder { path: PathBuf },
    /// `.torch` chunks (RE10K/DL3DV layout): a chunk file or a folder of them, streamed one chunk at a time.
    Chunks { path: PathBuf },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataSection {
    pub sources: Vec<Source>,
    /// Probability of each source per step (default: equal).
    #[serde(default)]
    pub weights: Vec<f64>,
    #[serde(default = "five")]
    pub num_context: usize,
    /// Targets per step (official: 14).
    #[serde(default = "fourteen")]
    pub num_target: usize,
    /// Frame-gap window [min, max] of the sampler; omitted: the whole sequence (a closed 360° loop), see
    /// [`crate::sampler`].
    #[serde(default)]
    pub gap: Option<[usize; 2]>,
    /// Curriculum: the window's gap at step 0, widening linearly to `gap` (or the whole sequence) over
    /// `gap_warm_up_steps` (the official `initial_{min,max}_distance_between_context_views` and `warm_up_steps`).
    #[serde(default)]
    pub gap_initial: Option<[usize; 2]>,
    #[serde(default)]
    pub gap_warm_up_steps: u64,
    /// Treat sequences as closed loops (indices wrap around).
    #[serde(default = "yes")]
    pub closed_loop: bool,
    /// Random horizontal flips (image and camera together).
    #[serde(default = "yes")]
    pub flip: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LrGroup {
    /// Parameters whose name contains this string get `scale` × the scheduled lr.
    pub contains: String,
    pub scale: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainSection {
    /// What this run trains: `model` (the encoder, and the refiner's UNet with `[model.refiner]`) or `vae`
    /// (the refiner's first-stage autoencoder alone, from seeded random weights — the stand-in for SVD's
    /// pretrained VAE where its weights are not at hand; its model folder is a `refiner_init` for a `model` run).
    #[serde(default)]
    pub stage: Stage,
    /// Optimizer steps.
    pub steps: u64,
    /// Peak learning rate of the one-cycle schedule.
    #[serde(default = "default_lr")]
    pub lr: f64,
    #[serde(default)]
    pub lr_groups: Vec<LrGroup>,
    #[serde(default = "default_pct_start")]
    pub pct_start: f64,
    /// Micro-batches per optimizer step (losses are averaged over them, as Lightning does).
    #[serde(default = "two")]
    pub accumulate: u32,
    /// Run the micro-batches of one step on parallel threads (more cores busy, memory × `accumulate`); the
    /// result equals the sequential run's up to float summation order inside the kernels.
    #[serde(default)]
    pub parallel_micro_batches: bool,
    /// Gradient-norm clipping (0 = off).
    #[serde(default = "default_clip")]
    pub clip_grad_norm: f64,
    #[serde(default)]
    pub seed: u64,
    #[serde(default = "one_f64")]
    pub mse_weight: f64,
    #[serde(default = "default_lpips")]
    pub lpips_weight: f64,
    /// LPIPS applies from this step on.
    #[serde(default)]
    pub lpips_after_step: u64,
    /// Weight of the depth-supervision loss ([`crate::loss::depth_log_l1`] on the context views' encoder depths)
    /// for examples whose source knows true depth (procedural scenes); 0 = off, as officially. A small model
    /// trained on a few CPU hours learns matching far faster with it than from photometric losses alone.
    #[serde(default)]
    pub depth_weight: f64,
    /// Rasterizer backward: `official` (what the official CUDA backward returns, used in training) or `exact`
    /// (the true derivative; for gradient checks).
    #[serde(default)]
    pub raster_grad: RasterGrad,
    /// Name prefixes of parameters that stay fixed (e.g. `encoder.backbone`).
    #[serde(default)]
    pub freeze: Vec<String>,
    /// Initial weights: a model folder or a weights file with `encoder.*` keys (official checkpoints included).
    /// `mvsplat360 train` also takes a name here (`default`, `dl3dv`, `hf:OWNER/REPO[/FILE][@REV]`), resolved to a
    /// local path before the run (docs/weights.md, "Names"); an existing path wins.
    #[serde(default)]
    pub init: Option<PathBuf>,
    /// Refiner weights (with `[model.refiner]`): svd.safetensors, a converted MVSplat360 checkpoint, a model
    /// folder or a diffusers SVD folder (`unet/`, `vae/`, `image_encoder/`); absent = seeded random weights.
    /// `mvsplat360 train` also takes a name (`svd`, `dl3dv`, `hf:…`), as for `init`.
    /// Stage `vae`: the autoencoder to continue from (its keys only; e.g. an earlier `vae` run's model folder).
    #[serde(default)]
    pub refiner_init: Option<PathBuf>,
    /// Weight of the refiner's losses (diffusion + 0.01·latent alignment; official 1).
    #[serde(default = "one_f64")]
    pub refiner_weight: f64,
    /// Stage `vae`: weight of the KL term (per element, as the L1 term; Stable Diffusion's autoencoders: 1e-6).
    #[serde(default = "default_kl")]
    pub kl_weight: f64,
    #[serde(default = "hundred_u64")]
    pub checkpoint_every: u64,
    /// Checkpoints kept on disk (older ones are deleted).
    #[serde(default = "three")]
    pub keep_checkpoints: usize,
    /// Output folder (checkpoints, log.jsonl, loss.png, the final model folder).
    pub out: PathBuf,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    #[default]
    Model,
    Vae,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RasterGrad {
    #[default]
    Official,
    Exact,
}

fn default_experiment() -> String {
    "project".into()
}
fn one() -> f32 {
    1.0
}
fn hundred() -> f32 {
    100.0
}
fn default_views() -> usize {
    32
}
fn five() -> usize {
    5
}
fn fourteen() -> usize {
    14
}
fn yes() -> bool {
    true
}
fn default_lr() -> f64 {
    2e-4
}
fn default_kl() -> f64 {
    1e-6
}
fn default_pct_start() -> f64 {
    0.01
}
fn two() -> u32 {
    2
}
fn default_clip() -> f64 {
    0.5
}
fn one_f64() -> f64 {
    1.0
}
fn default_lpips() -> f64 {
    0.05
}
fn hundred_u64() -> u64 {
    100
}
fn three() -> usize {
    3
}

impl TrainConfig {
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| TrainError::Config { path: path.into(), msg: format!("cannot read: {e}") })?;
        Self::from_toml(&text, path)
    }

    pub fn from_toml(text: &str, path: &Path) -> Result<Self> {
        let table = resolve_base(text, path, &mut vec![path.canonicalize().unwrap_or_else(|_| path.into())])?;
        let cfg: Self = table.try_into().map_err(|e: toml::de::Error| TrainError::Config { path: path.into(), msg: e.to_string() })?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// The encoder config actually built (view count and depth range from the other sections).
    pub fn encoder(&self) -> EncoderCostVolumeCfg {
        let mut e = self.model.encoder.clone();
        e.num_views = self.data.num_context;
        e.near = self.model.near;
        e.far = self.model.far;
        e.costvolume_nearest_n_views = e.costvolume_nearest_n_views.min(self.data.num_context);
        e.multiview_trans_nearest_n_views = e.multiview_trans_nearest_n_views.min(self.data.num_context);
        e
    }

    fn validate(&self, path: &Path) -> Result<()> {
        let bad = |field: &str, msg: String| Err(TrainError::Config { path: path.into(), msg: format!("`{field}`: {msg}") });
        let m = self.model.encoder.image_multiple() as u32;
        if self.model.width == 0 || self.model.height == 0 || self.model.width % m != 0 || self.model.height % m != 0 {
            return bad("model.width/height", format!("{}x{} must be positive multiples of {m}", self.model.width, self.model.height));
        }
        if !(self.model.near > 0.0 && self.model.far > self.model.near) {
            return bad("model.near/far", format!("need 0 < near < far, got {} and {}", self.model.near, self.model.far));
        }
        if self.data.sources.is_empty() {
            return bad("data.sources", "add at least one source (procedural, folder or chunks)".into());
        }
        if !self.data.weights.is_empty()
            && (self.data.weights.len() != self.data.sources.len()
                || self.data.weights.iter().any(|w| !(*w >= 0.0))
                || self.data.weights.iter().sum::<f64>() <= 0.0)
        {
            return bad("data.weights", "one non-negative weight per source, not all zero".into());
        }
        if self.data.num_context < 2 {
            return bad("data.num_context", "the cost volume needs at least 2 context views".into());
        }
        if self.data.num_target == 0 {
            return bad("data.num_target", "must be at least 1".into());
        }
        if let Some([lo, hi]) = self.data.gap_initial {
            if lo > hi || hi < self.data.num_context {
                return bad("data.gap_initial", format!("[{lo}, {hi}] must satisfy min ≤ max and max ≥ num_context"));
            }
        }
        if let Some([lo, hi]) = self.data.gap {
            if lo > hi || hi < self.data.num_context {
                return bad("data.gap", format!("[{lo}, {hi}] must satisfy min ≤ max and max ≥ num_context"));
            }
        }
        if self.train.refiner_init.is_some() && self.model.refiner.is_none() {
            return bad("train.refiner_init", "add a [model.refiner] section (the refiner's configs) or remove this".into());
        }
        if let Some(r) = &self.model.refiner {
            let want = 4 + self.model.encoder.gaussian_adapter.n_feature_channels;
            if r.unet.in_channels != want {
                return bad("model.refiner.unet.in_channels", format!("{} ≠ 4 latent + {} feature channels = {want}", r.unet.in_channels, want - 4));
            }
        }
        if self.train.stage == Stage::Vae && self.model.refiner.is_none() {
            return bad("train.stage", "`vae` trains the refiner's autoencoder: add [model.refiner.vae] (and the other refiner sections)".into());
        }
        if self.train.steps == 0 {
            return bad("train.steps", "must be at least 1".into());
        }
        if !(self.train.lr > 0.0 && self.train.lr.is_finite()) {
            return bad("train.lr", format!("{} is not a positive number", self.train.lr));
        }
        if !(self.train.pct_start > 0.0 && self.train.pct_start < 1.0) {
            return bad("train.pct_start", "must lie in (0, 1)".into());
        }
        for (field, w) in [
            ("train.mse_weight", self.train.mse_weight),
            ("train.lpips_weight", self.train.lpips_weight),
            ("train.depth_weight", self.train.depth_weight),
            ("train.kl_weight", self.train.kl_weight),
        ] {
            if !(w >= 0.0 && w.is_finite()) {
                return bad(field, format!("{w} is not a non-negative number"));
            }
        }
        if self.train.accumulate == 0 {
            return bad("train.accumulate", "must be at least 1".into());
        }
        if self.train.checkpoint_every == 0 {
            return bad("train.checkpoint_every", "must be at least 1".into());
        }
        if self.train.keep_checkpoints == 0 {
            return bad("train.keep_checkpoints", "keep at least 1 (resuming needs it)".into());
        }
        Ok(())
    }
}

/// `text` as a TOML table with its `base` chain merged in; `chain` holds the files being read, to refuse cycles.
fn resolve_base(text: &str, path: &Path, chain: &mut Vec<PathBuf>) -> Result<toml::Table> {
    let err = |msg: String| TrainError::Config { path: path.into(), msg };
    let mut table: toml::Table = toml::from_str(text).map_err(|e| err(e.to_string()))?;
    let Some(base) = table.remove("base") else { return Ok(table) };
    let toml::Value::String(rel) = base else { return Err(err("`base`: expected the path of another config (a string)".into())) };
    let base_path = path.parent().unwrap_or(Path::new("")).join(&rel);
    let key = base_path.canonicalize().unwrap_or_else(|_| base_path.clone());
    if chain.contains(&key) || chain.len() >= 16 {
        return Err(err(format!("`base`: {} is already in the chain of bases (a cycle)", base_path.display())));
    }
    let base_text = std::fs::read_to_string(&base_path)
        .map_err(|e| err(format!("`base`: cannot read {} ({e}); the path is relative to this config's folder", base_path.display())))?;
    chain.push(key);
    let mut merged = resolve_base(&base_text, &base_path, chain)?;
    chain.pop();
    merge(&mut merged, table);
    Ok(merged)
}

/// Tables merge key by key; any other value replaces.
fn merge(into: &mut toml::Table, over: toml::Table) {
    for (k, v) in over {
        match (into.get_mut(&k), v) {
            (Some(toml::Value::Table(a)), toml::Value::Table(b)) => merge(a, b),
            (_, v) => {
                into.insert(k, v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: &str = r#"
[model]
width = 128
height = 64
[data]
sources = [{ kind = "procedural", count = 10 }]
[train]
steps = 5
out = "out/x"
"#;

    #[test]
    fn defaults_are_the_official_settings() {
        let c = TrainConfig::from_toml(MIN, Path::new("t.toml")).unwrap();
        assert_eq!((c.train.accumulate, c.train.clip_grad_norm, c.train.pct_start, c.train.lpips_weight), (2, 0.5, 0.01, 0.05));
        assert_eq!((c.data.num_context, c.data.num_target), (5, 14));
        assert_eq!(c.encoder().num_views, 5);
        let back = TrainConfig::from_toml(&c.to_toml(), Path::new("t.toml")).unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn errors_name_the_field() {
        let e = TrainConfig::from_toml(&MIN.replace("width = 128", "width = 100"), Path::new("c.toml")).unwrap_err().to_string();
        assert!(e.contains("c.toml") && e.contains("model.width"), "{e}");
        let e = TrainConfig::from_toml(&MIN.replace("steps = 5", "steps = 5\nbogus = 1"), Path::new("c.toml")).unwrap_err().to_string();
        assert!(e.contains("bogus"), "{e}");
    }

    /// `configs/train/` of the repository: the shipped encoder's stages in `recipe/`, the attempts in `attempts/`, the
    /// tiny refiner's in `refiner/`.
    fn committed_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/train")
    }

    /// Every `.toml` under `dir`, subfolders included, sorted by path.
    fn tomls(dir: &Path) -> Vec<PathBuf> {
        let mut found = Vec::new();
        for e in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
            let p = e.unwrap().path();
            if p.is_dir() {
                found.extend(tomls(&p));
            } else if p.extension().is_some_and(|x| x == "toml") {
                found.push(p);
            }
        }
        found.sort();
        found
    }

    /// Every committed config (recipe, attempts, tiny refiner) parses and validates; a bad curriculum window names
    /// its field.
    #[test]
    fn committed_configs_parse() {
        let dir = committed_dir();
        let all = tomls(&dir);
        for p in &all {
            TrainConfig::from_file(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        }
        let recipe = all.iter().filter(|p| p.parent().is_some_and(|d| d.ends_with("recipe"))).count();
        assert!(recipe >= 2 && all.len() > recipe, "expected the recipe's stages and other configs under {}", dir.display());
        let e = TrainConfig::from_toml(&MIN.replace("count = 10 }]", "count = 10 }]\ngap_initial = [6, 3]"), Path::new("c.toml")).unwrap_err().to_string();
        assert!(e.contains("data.gap_initial"), "{e}");
    }

    /// The shipped encoder's recipe, `configs/train/recipe/NN-name.toml` in stage order, is a chain that reproduces:
    /// stage 01 starts from scratch, and every later stage's `init` is a model folder of the stage before it — its
    /// final `<out>/model`, or `<out>/model-STEP` (`train --export STEP`) where an earlier checkpoint was shipped, a
    /// checkpoint still on disk when that stage has run all its steps. Each stage writes to `out/train/<file stem>`.
    #[test]
    fn recipe_stages_chain() {
        let dir = committed_dir().join("recipe");
        let stages = tomls(&dir);
        assert!(stages.len() >= 2, "expected the recipe's stages in {}", dir.display());
        let mut prev: Option<(u32, TrainConfig)> = None;
        for p in &stages {
            let stem = p.file_stem().and_then(|s| s.to_str()).unwrap();
            let n: u32 = stem
                .split_once('-')
                .filter(|(n, _)| n.len() == 2)
                .and_then(|(n, _)| n.parse().ok())
                .unwrap_or_else(|| panic!("{}: a stage is named NN-name.toml", p.display()));
            let c = TrainConfig::from_file(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            assert_eq!(c.train.out, Path::new("out/train").join(stem), "{}: `out` is out/train/{stem}", p.display());
            match &prev {
                None => assert!(n == 1 && c.train.init.is_none(), "{}: the first stage is 01 and starts from scratch (no `init`)", p.display()),
                Some((m, before)) => {
                    assert!(n > *m, "{}: stage numbers increase", p.display());
                    check_init_is_output_of(p, &c, *m, before);
                }
            }
            prev = Some((n, c));
        }
    }

    /// `c`'s (file `p`) `init` is `<out>/model` of stage `m` (`before`) or `<out>/model-STEP` for a checkpoint that a
    /// full run of that stage keeps.
    fn check_init_is_output_of(p: &Path, c: &TrainConfig, m: u32, before: &TrainConfig) {
        let init = c.train.init.as_deref().unwrap_or_else(|| panic!("{}: no `init`; it continues stage {m:02}", p.display()));
        let t = &before.train;
        assert_eq!(
            init.parent(),
            Some(t.out.as_path()),
            "{}: `init` {} is not a model folder of stage {m:02} ({})",
            p.display(),
            init.display(),
            t.out.display()
        );
        let name = init.file_name().and_then(|s| s.to_str()).unwrap_or_default();
        if name == "model" {
            return;
        }
        let step: u64 = name
            .strip_prefix("model-")
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("{}: `init` {} is neither <out>/model nor <out>/model-STEP", p.display(), init.display()));
        // The checkpoints a full run leaves: one every `checkpoint_every` steps and the last, the newest kept.
        let mut saved: Vec<u64> = (1..=t.steps / t.checkpoint_every).map(|k| k * t.checkpoint_every).collect();
        if saved.last() != Some(&t.steps) {
            saved.push(t.steps);
        }
        let kept = &saved[saved.len().saturating_sub(t.keep_checkpoints)..];
        assert!(
            kept.contains(&step),
            "{}: `init` {} needs stage {m:02}'s step {step}, not among the checkpoints its run keeps ({kept:?})",
            p.display(),
            init.display()
        );
    }

    /// Stage 10 written out in full equals stage 8 as a base with stage 10's changes on top.
    #[test]
    fn base_config_with_overrides_equals_the_full_config() {
        let dir = committed_dir().join("recipe");
        let full = TrainConfig::from_file(&dir.join("10-povray-share.toml")).unwrap();
        let text = r#"
base = "08-repaired-povray.toml"
[data]
sources = [
    { kind = "procedural", count = 100000, seed = 600000, views = 32 },
    { kind = "folder", path = "data/povray-train" },
    { kind = "folder", path = "data/povray-train2" },
    { kind = "folder", path = "data/povray-train3" },
]
weights = [0.55, 0.12, 0.18, 0.15]
[train]
seed = 20261231
init = "out/train/08-repaired-povray/model-1100"
keep_checkpoints = 4
out = "out/train/10-povray-share"
"#;
        let derived = TrainConfig::from_toml(text, &dir.join("derived.toml")).unwrap();
        assert_eq!(derived, full);
        // Without the override of one key the base's value stays: the merge is per key, not per table.
        let e = TrainConfig::from_toml(&text.replace("seed = 20261231\n", ""), &dir.join("derived.toml")).unwrap();
        assert_eq!((e.train.seed, e.train.lr, e.model.width), (20261229, 1e-4, 128));
    }

    #[test]
    fn base_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.toml"), dir.path().join("b.toml"));
        std::fs::write(&a, "base = \"b.toml\"\n").unwrap();
        std::fs::write(&b, "base = \"a.toml\"\n").unwrap();
        let e = TrainConfig::from_file(&a).unwrap_err().to_string();
        assert!(e.contains("cycle") && e.contains("a.toml"), "{e}");
        let e = TrainConfig::from_toml("base = \"missing.toml\"\n", &a).unwrap_err().to_string();
        assert!(e.contains("missing.toml") && e.contains("a.toml") && e.contains("relative to this config"), "{e}");
        let e = TrainConfig::from_toml("base = 3\n", &a).unwrap_err().to_string();
        assert!(e.contains("`base`"), "{e}");
    }
}
