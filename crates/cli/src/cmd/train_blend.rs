//! `mvsplat360 train-blend`: train a model folder's learned blender on rendered scenes and write the folder with
//! it (`OUT/model`), as the shipped model's blender was made (see `mvsplat360_train::blend`).

use std::path::PathBuf;

use anyhow::Context;
use mvsplat360_pipeline::blend::BlendSettings;
use mvsplat360_train::blend::{BlendRequest, SceneSource};

#[derive(clap::Args)]
pub struct Args {
    /// Model folder whose encoder and test-time fitting make the blender's inputs (default: the shipped model),
    /// a path or a name (`default`, `hf:OWNER/REPO[@REV]` = that repository as a folder; an existing path wins).
    /// Its own blender, if any, is not used and is replaced in OUT/model.
    #[arg(long, value_name = "DIR|NAME")]
    pub model: Option<PathBuf>,
    /// Training scenes: scene folders, folders of scene folders, or `procedural:FIRST-LAST` (generated scenes
    /// with these seeds, written under OUT/procedural). Each runs the held-out protocol: 5 context views by
    /// farthest-point sampling, every other view a target.
    #[arg(long, required = true, num_args = 1..)]
    pub train: Vec<SceneSource>,
    /// Validation scenes (same forms), scored every `--every` steps; never trained on.
    #[arg(long, num_args = 1..)]
    pub val: Vec<SceneSource>,
    /// Output folder: cache/ (the blender's inputs per scene; reused by a re-run), checkpoint.safetensors,
    /// log.jsonl and model/ (the model folder with the blender).
    #[arg(long)]
    pub out: PathBuf,
    /// Candidates' layout PLANESxVIEWSxSPAN: PLANES depths (× SPAN^[-1, 1] around the rendered one) in each of
    /// the VIEWS nearest context photos.
    #[arg(long, default_value = "7x2x1.6", value_parser = parse_layout)]
    pub layout: (usize, usize, f64),
    /// Channels of the blender's CNN.
    #[arg(long, default_value_t = 16)]
    pub width: usize,
    /// Optimizer steps.
    #[arg(long, default_value_t = 800)]
    pub steps: u64,
    /// Adam's learning rate at step 1 (cosine decay to 0 at the last step).
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Targets per step.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Seed of the batch draws and flips.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Steps between checkpoints, log lines and validation scores.
    #[arg(long, default_value_t = 100)]
    pub every: u64,
    /// Continue from OUT/checkpoint.safetensors (the same flags are required).
    #[arg(long)]
    pub resume: bool,
    /// Test-time fitting steps of the inputs' renders (default: the model's own; as `render --fit-steps`).
    #[arg(long)]
    pub fit_steps: Option<usize>,
    /// Where the encoder, fitting and training run: cpu, cuda (GPU 0) or cuda:N (a `--features cuda` build).
    #[arg(long, default_value = "cpu")]
    pub device: mvsplat360_pipeline::compute::DeviceSpec,
}

fn parse_layout(s: &str) -> Result<(usize, usize, f64), String> {
    let bad = || format!("`{s}` is not a layout: use PLANESxVIEWSxSPAN, e.g. 7x2x1.6");
    let p: Vec<&str> = s.split('x').collect();
    if p.len() != 3 {
        return Err(bad());
    }
    Ok((p[0].parse().map_err(|_| bad())?, p[1].parse().map_err(|_| bad())?, p[2].parse().map_err(|_| bad())?))
}

pub fn run(a: Args, quiet: bool) -> anyhow::Result<()> {
    let model = match a.model {
        Some(m) => super::names::resolve(&m, "--model", super::names::Default::ModelFolder, super::names::Freshness::Ask, quiet)?,
        None => mvsplat360_pipeline::model::default_model_dir().context("the shipped model assets/models/default is missing; give --model")?,
    };
    let (planes, views, span) = a.layout;
    let req = BlendRequest {
        model,
        fit_steps: a.fit_steps,
        compute: mvsplat360_pipeline::compute::Compute { device: a.device, ..Default::default() },
        train: a.train,
        val: a.val,
        layout: BlendSettings { planes, views, span, width: a.width },
        steps: a.steps,
        lr: a.lr,
        batch: a.batch,
        seed: a.seed,
        every: a.every,
        resume: a.resume,
        stop_after: None,
        out: a.out.clone(),
    };
    super::progress::clean_partials_on_interrupt(&req.out);
    let bars = super::progress::Bars::new(quiet);
    let t = std::time::Instant::now();
    let s = mvsplat360_train::blend::run(&req, &bars).with_context(|| format!("training a blender into {}", a.out.display()))?;
    if !quiet {
        let v = |x: Option<f64>| x.map(|p| format!("{p:.3}")).unwrap_or_else(|| "–".into());
        eprintln!(
            "{} training targets of {} scenes, {} validation scenes: validation PSNR {} (renders as they are: {}); {:.0} s",
            s.train_images,
            s.train_scenes,
            s.val_scenes,
            v(s.val_psnr),
            v(s.val_psnr_renders),
            t.elapsed().as_secs_f64()
        );
    }
    if let Some(m) = &s.model {
        println!("{}", m.display());
    }
    Ok(())
}
