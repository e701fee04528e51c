//! The training loop: sample views, encode, rasterize the targets, MSE + LPIPS, accumulate, clip, Adam with the
//! one-cycle schedule; checkpoints and a JSONL log that a resumed run continues exactly.

use crate::log::StepRecord;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use sha2::{Digest, Sha256};

use candle_core::{DType, Device, IndexOp, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use mvsplat360_camera::Camera;
use mvsplat360_encoder::encoder_costvolume::camera_tensors;
use mvsplat360_encoder::EncoderCostVolume;
use mvsplat360_metrics::lpips::Lpips;
use mvsplat360_pipeline::compute::DeviceSpec;
use mvsplat360_pipeline::model::{DataConfig, ModelConfig, MODEL_FORMAT};
use mvsplat360_pipeline::scale::{scene_transform, SceneScale};
use mvsplat360_splat::camera::RasterCamera;
use mvsplat360_splat::{Gaussians, RenderOptions};
use rand::{Rng, SeedableRng};

use crate::checkpoint::{self, State};
use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use crate::optim::{clip_grad_norm, Adam, OneCycle, Param};
use crate::refiner::TrainRefiner;
use crate::sampler::{self, SamplerSettings};
use crate::scenes::{SceneSource, TrainScene};

mod example;
mod export;
mod model;
mod objective;
mod reduce;

pub use example::{example_from_views, make_example, render_example, render_example_full, step_rng, Example, Rendered};
pub use export::export_checkpoint;
use export::*;
pub use model::Model;
pub use objective::losses;
use objective::*;
use reduce::*;

/// Progress and interruption, supplied by the caller (the CLI shows a bar; tests stay silent).
pub trait Monitor {
    fn note(&self, _msg: &str) {}
    fn step(&self, _rec: &StepRecord, _total: u64) {}
    /// Checked after every step; true = write a checkpoint and stop.
    fn should_stop(&self) -> bool {
        false
    }
}

pub struct Quiet;
impl Monitor for Quiet {}

#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Continue from the newest checkpoint in `train.out` (a fresh start when there is none).
    pub resume: bool,
    /// Folder of the metric weights (LPIPS); None = the default search.
    pub weights_dir: Option<PathBuf>,
    /// Where the encoder, rasterizer and losses run (`--device`); data, sampling and checkpoints stay on the host.
    /// In a data-parallel run rank r uses `cuda:(N + r)` for `cuda:N`.
    pub device: DeviceSpec,
    /// This process's rank in a data-parallel run ([`crate::dist::launch`]); None = a single process.
    pub dist: Option<crate::dist::Rank>,
    /// Resume a checkpoint written with another world size (the global batch changes from then on).
    pub allow_world_change: bool,
    /// `--dist-backend` of a data-parallel run.
    pub dist_backend: crate::dist::Backend,
}

#[derive(Debug, Clone)]
pub struct Summary {
    pub steps: u64,
    pub last: Option<StepRecord>,
    pub model_dir: PathBuf,
    pub train_seconds: f64,
    pub lpips: bool,
}

/// Train as configured; returns when `train.steps` are done or the monitor asks to stop.
pub fn run(cfg: &TrainConfig, opts: &RunOptions, mon: &dyn Monitor) -> Result<Summary> {
    let out = cfg.train.out.clone();
    std::fs::create_dir_all(&out).map_err(|e| TrainError::Write { path: out.clone(), msg: e.to_string() })?;
    let (rank, world) = opts.dist.as_ref().map_or((0, 1), |r| (r.rank, r.world));
    // Rank 0 owns the output folder: lock, log, plots, checkpoints, model folders.
    let main = rank == 0;
    let _lock = if main { Some(checkpoint::RunLock::acquire(&out)?) } else { None };
    let dev = match &opts.dist {
        Some(r) => r.device(opts.device)?,
        None => opts.device,
    }
    .open()?;
    let config_text = cfg.to_toml();
    let mut coll = match &opts.dist {
        Some(r) => {
            let backend = opts.dist_backend.resolve(dev.is_cuda())?;
            let fingerprint = u64::from_le_bytes(Sha256::digest(config_text.as_bytes())[..8].try_into().expect("8 bytes"));
            Some(crate::dist::connect(r, backend, fingerprint, &dev)?)
        }
        None => None,
    };
    let model = Model::new_on(cfg, &dev)?;
    let multiple = cfg.model.encoder.image_multiple() as u32;
    let mut sources = cfg.data.sources.iter().map(|s| SceneSource::open(s, cfg.model.width, cfg.model.height, multiple)).collect::<Result<Vec<_>>>()?;
    let lpips = if cfg.train.lpips_weight > 0.0 {
        match Lpips::load(opts.weights_dir.as_deref(), mvsplat360_metrics::lpips::Net::Vgg, &dev) {
            Ok(l) => Some(l),
            Err(e) => {
                mon.note(&format!("training without LPIPS (its VGG weights are missing: {e}); run scripts/metric-weights/fetch"));
                None
            }
        }
    } else {
        None
    };
    let frozen = |n: &str| cfg.train.freeze.iter().any(|p| n.starts_with(p.as_str()));
    let params: Vec<Param> = model
        .vars()
        .into_iter()
        .filter(|(n, _)| !frozen(n))
        .map(|(name, var)| {
            let lr_scale = cfg.train.lr_groups.iter().find(|g| name.contains(&g.contains)).map(|g| g.scale).unwrap_or(1.0);
            Param { name, var, lr_scale }
        })
        .collect();
    if params.is_empty() {
        return Err(TrainError::Config { path: PathBuf::from("train.freeze"), msg: "every parameter is frozen; nothing to train".into() });
    }
    let mut adam = Adam::new(params)?;
    let sched = OneCycle::new(cfg.train.lr, cfg.train.steps, cfg.train.pct_start);

    let mut start = 0u64;
    let mut train_seconds = 0.0;
    if opts.resume {
        if let Some(ck) = checkpoint::load_latest(&out)? {
            if !written_with(&ck, cfg) {
                return Err(TrainError::Checkpoint(format!(
                    "{} was written with a different config; resume with the same config or choose another `train.out`",
                    ck.path.display()
                )));
            }
            if let Some(w) = ck.state.world.filter(|&w| w != world as u64) {
                let k = cfg.train.accumulate as u64;
                let what = format!(
                    "{} was written by {w} rank(s): {} examples per step ({w} × train.accumulate {k}); this run has {world}: {} per step",
                    ck.path.display(),
                    w * k,
                    world as u64 * k
                );
                if !opts.allow_world_change {
                    return Err(TrainError::Checkpoint(format!(
                        "{what}; resume with --world-size {w}, or pass --allow-world-change to continue with the new batch"
                    )));
                }
                mon.note(&format!("{what}; continuing with the new batch (--allow-world-change)"));
            }
            model.load_state_dict(&ck.model)?;
            adam.load_state(&ck.optim)?;
            start = ck.state.step;
            train_seconds = ck.state.train_seconds;
            mon.note(&format!("resuming from {} (step {start})", ck.path.display()));
        } else {
            mon.note("no checkpoint to resume from; starting at step 0");
        }
    } else if !checkpoint::list(&out)?.is_empty() {
        return Err(TrainError::Checkpoint(format!(
            "{} already holds checkpoints; pass --resume to continue them or choose another output folder",
            out.display()
        )));
    }
    if start == 0 && main {
        // The step-0 model, for before/after comparisons.
        mvsplat360_pipeline::model::write_model_dir(&out.join("model-step0"), &model.model_config(), &model.model_tensors()?)?;
    }
    if let Some(c) = coll.as_mut() {
        let (words, _) = weights_digest(&model, start)?;
        crate::dist::check_agreement(
            c.as_mut(),
            &words,
            &format!("the step and weights they start from (rank 0: step {start}; to resume, every rank must read the same checkpoint in `train.out`, a folder all machines share)"),
        )?;
    }
    let log_path = out.join("log.jsonl");
    let mut records = Vec::new();
    let mut log = None;
    if main {
        records = crate::log::read(&log_path)?.into_iter().filter(|r| r.step <= start).collect::<Vec<_>>();
        crate::log::rewrite(&log_path, &records)?;
        log = Some(
            std::fs::OpenOptions::new()
                .append(true)
                .create(true)
                .open(&log_path)
                .map_err(|e| TrainError::Write { path: log_path.clone(), msg: e.to_string() })?,
        );
    }

    let mut settings = SamplerSettings {
        num_context: cfg.data.num_context,
        num_target: cfg.data.num_target,
        gap: cfg.data.gap,
        gap_initial: cfg.data.gap_initial,
        warm_up: 0.0,
        closed_loop: cfg.data.closed_loop,
        flip: cfg.data.flip,
    };
    let weights: Vec<f64> = if cfg.data.weights.is_empty() { vec![1.0; sources.len()] } else { cfg.data.weights.clone() };
    let wsum: f64 = weights.iter().sum();
    let accum = cfg.train.accumulate;
    // Every loss is divided by all micro-batches of the step, over all ranks (Lightning's 1/k times DDP's mean).
    let denom = (accum as usize * world) as f64;
    let save = |adam: &Adam, step: u64, secs: f64| -> Result<()> {
        let state =
            State { step, seed: cfg.train.seed, config: config_text.clone(), train_seconds: secs, world: Some(world as u64), files: Default::default() };
        checkpoint::save(&out, &state, &model.state_dict()?, &adam.state_tensors()?, cfg.train.keep_checkpoints)?;
        Ok(())
    };
    let mut step = start;
    while step < cfg.train.steps {
        let t0 = Instant::now();
        settings.warm_up = if cfg.data.gap_warm_up_steps == 0 { 1.0 } else { step as f64 / cfg.data.gap_warm_up_steps as f64 };
        let mut grads: Vec<Option<Tensor>> = vec![None; adam.params.len()];
        let (mut sum_loss, mut sum_mse, mut sum_lp, mut sum_ref) = (0f64, 0f64, None::<f64>, None::<(f64, f64)>);
        let (mut n_lp, mut n_ref) = (0usize, 0usize);
        let mut sum_vae: Option<(f64, f64)> = None;
        // Mean over the micro-batches whose scene has ground-truth depth.
        let mut depth_terms = Vec::new();
        // Examples are drawn in micro-batch order (sources cache scenes); forward and backward may then run in
        // parallel, and gradients are summed in micro-batch order either way.
        let mut examples = Vec::with_capacity(accum as usize);
        // Rank r's micro-batch m is the step's micro-batch r·k + m, as in one process accumulating world·k.
        let global = |micro: u32| rank as u32 * accum + micro;
        for micro in 0..accum {
            let mut rng = step_rng(cfg.train.seed, step, global(micro));
            examples.push(draw_example(&mut sources, &weights, wsum, &settings, cfg, step, &mut rng)?.to_device(&dev)?);
        }
        let train_encoder = adam.params.iter().any(|p| p.name.starts_with("encoder."));
        let micro_step = |micro: u32, ex: &Example| -> Result<MicroResult> {
            if let Some(v) = model.vae.as_ref() {
                let mut rng = step_rng(cfg.train.seed ^ 0x7AE0_0000_0000_0000, step, global(micro));
                let l = v.losses(&ex.target_images, &mut rng)?;
                let mse = crate::loss::mse(&l.recon.detach(), &ex.target_images)?;
                let mut total = (&l.l1 + (&l.kl * cfg.train.kl_weight)?)?;
                let lp = lpips_term(cfg, lpips.as_ref(), step, &l.recon, &ex.target_images)?;
                if let Some(x) = &lp {
                    total = (total + (x * cfg.train.lpips_weight)?)?;
                }
                let tv = total.to_scalar::<f32>()? as f64;
                if !tv.is_finite() {
                    return Err(TrainError::NonFinite { step: step + 1, what: format!("loss {tv}") });
                }
                let g = (total / denom)?.backward()?;
                return Ok(MicroResult {
                    loss: tv,
                    mse: mse.to_scalar::<f32>()? as f64,
                    lpips: lp.map(|l| l.to_scalar::<f32>()).transpose()?.map(|l| l as f64),
                    depth: None,
                    refiner: None,
                    vae: Some((l.l1.to_scalar::<f32>()? as f64, l.kl.to_scalar::<f32>()? as f64)),
                    grads: adam.params.iter().map(|p| g.get(p.var.as_tensor()).cloned()).collect(),
                });
            }
            let mut rendered = render_example_full(&model, ex)?;
            if !train_encoder {
                // A frozen encoder (e.g. a refiner-only run): no backward through the rasterizer and encoder.
                rendered.rgb = rendered.rgb.detach();
                rendered.features = rendered.features.detach();
                rendered.depths = rendered.depths.detach();
            }
            let (pred, feats) = (&rendered.rgb, &rendered.features);
            let (mut total, mse, lp) = losses(cfg, lpips.as_ref(), step, pred, &ex.target_images)?;
            let mut depth_term = None;
            if let Some(gt) = ex.context_depths.as_ref().filter(|_| cfg.train.depth_weight > 0.0) {
                let d = crate::loss::depth_log_l1(&rendered.depths, gt, cfg.model.near, cfg.model.far)?;
                total = (total + (&d * cfg.train.depth_weight)?)?;
                depth_term = Some(d.to_scalar::<f32>()? as f64);
            }
            let mut refiner_terms = None;
            if let Some(r) = model.refiner.as_ref().filter(|_| cfg.train.refiner_weight > 0.0) {
                // A stream of its own, so adding the refiner leaves the examples' draws unchanged.
                let mut rng = step_rng(cfg.train.seed ^ 0x5EF1_4E70_0000_0000, step, global(micro));
                let rl = r.losses(feats, &ex.target_images, &ex.context_images, &mut rng)?;
                total = (total + ((&rl.diffusion + &rl.alignment)? * cfg.train.refiner_weight)?)?;
                refiner_terms = Some((rl.diffusion.to_scalar::<f32>()? as f64, rl.alignment.to_scalar::<f32>()? as f64));
            }
            let tv = total.to_scalar::<f32>()? as f64;
            if !tv.is_finite() {
                return Err(TrainError::NonFinite { step: step + 1, what: format!("loss {tv}") });
            }
            // Lightning divides each micro-batch's loss by the accumulation count.
            let g = (total / denom)?.backward()?;
            let grads = adam.params.iter().map(|p| g.get(p.var.as_tensor()).cloned()).collect();
            Ok(MicroResult {
                loss: tv,
                mse: mse.to_scalar::<f32>()? as f64,
                lpips: lp.map(|l| l.to_scalar::<f32>()).transpose()?.map(|l| l as f64),
                depth: depth_term,
                refiner: refiner_terms,
                vae: None,
                grads,
            })
        };
        let results: Vec<Result<MicroResult>> = if cfg.train.parallel_micro_batches && accum > 1 {
            std::thread::scope(|sc| {
                let handles: Vec<_> = examples.iter().zip(0u32..).map(|(ex, m)| sc.spawn(move || micro_step(m, ex))).collect();
                handles.into_iter().map(|h| h.join().unwrap_or_else(|_| Err(TrainError::Data("a micro-batch thread panicked".into())))).collect()
            })
        } else {
            examples.iter().zip(0u32..).map(|(ex, m)| micro_step(m, ex)).collect()
        };
        for r in results {
            let r = r?;
            sum_loss += r.loss / denom;
            sum_mse += r.mse / denom;
            if let Some(l) = r.lpips {
                *sum_lp.get_or_insert(0.0) += l / denom;
                n_lp += 1;
            }
            depth_terms.extend(r.depth);
            if let Some((d, a)) = r.refiner {
                let s = sum_ref.get_or_insert((0.0, 0.0));
                s.0 += d / denom;
                s.1 += a / denom;
                n_ref += 1;
            }
            if let Some((l1, kl)) = r.vae {
                let s = sum_vae.get_or_insert((0.0, 0.0));
                s.0 += l1 / denom;
                s.1 += kl / denom;
            }
            for (i, gi) in r.grads.into_iter().enumerate() {
                if let Some(gi) = gi {
                    grads[i] = Some(match grads[i].take() {
                        None => gi,
                        Some(a) => (a + gi)?,
                    });
                }
            }
        }
        let mut depth_mean = (!depth_terms.is_empty()).then(|| depth_terms.iter().sum::<f64>() / depth_terms.len() as f64);
        let mut stop_all = None;
        if let Some(c) = coll.as_mut() {
            // Sampled before the sums, so that every rank stops after the same step.
            let stop_here = mon.should_stop();
            let sums = StepSums {
                loss: sum_loss,
                mse: sum_mse,
                lpips: sum_lp,
                n_lpips: n_lp,
                refiner: sum_ref,
                n_refiner: n_ref,
                vae: sum_vae,
                depth: &depth_terms,
                stop: stop_here,
            };
            let r = reduce_step(c.as_mut(), sums, &mut grads, &adam.params, &dev)?;
            (sum_loss, sum_mse, sum_lp, sum_ref, sum_vae, depth_mean, stop_all) = (r.loss, r.mse, r.lpips, r.refiner, r.vae, r.depth, Some(r.stop));
        }
        let norm = if cfg.train.clip_grad_norm > 0.0 { clip_grad_norm(&mut grads, cfg.train.clip_grad_norm)? } else { crate::optim::grad_norm(&grads)? };
        if !norm.is_finite() {
            return Err(TrainError::NonFinite { step: step + 1, what: format!("gradient norm {norm}") });
        }
        let lr = sched.lr(step);
        adam.step(&grads, lr)?;
        step += 1;
        let secs = t0.elapsed().as_secs_f64();
        train_seconds += secs;
        let rec = StepRecord {
            step,
            loss: sum_loss,
            mse: sum_mse,
            lpips: sum_lp,
            depth: depth_mean,
            diffusion: sum_ref.map(|r| r.0),
            alignment: sum_ref.map(|r| r.1),
            l1: sum_vae.map(|v| v.0),
            kl: sum_vae.map(|v| v.1),
            lr,
            grad_norm: norm,
            seconds: secs,
        };
        if let Some(log) = log.as_mut() {
            let line = serde_json::to_string(&rec).map_err(|e| TrainError::Write { path: log_path.clone(), msg: e.to_string() })?;
            writeln!(log, "{line}").and_then(|_| log.flush()).map_err(|e| TrainError::Write { path: log_path.clone(), msg: e.to_string() })?;
            records.push(rec.clone());
        }
        mon.step(&rec, cfg.train.steps);
        let stop = stop_all.unwrap_or_else(|| mon.should_stop());
        if step % cfg.train.checkpoint_every == 0 || step == cfg.train.steps || stop {
            if let Some(c) = coll.as_mut() {
                let (words, _) = weights_digest(&model, step)?;
                crate::dist::check_agreement(c.as_mut(), &words, &format!("their weights after step {step} (a nondeterministic step?)"))?;
            }
            if main {
                save(&adam, step, train_seconds)?;
                let _ = crate::log::plot(&records, &out.join("loss.png"));
            }
        }
        if stop {
            return Err(TrainError::Interrupted);
        }
    }
    if coll.is_some() && main {
        let (_, hex) = weights_digest(&model, step)?;
        mon.note(&format!("the {world} ranks' weights are identical (SHA-256 {})", &hex[..16]));
    }
    let model_dir = out.join("model");
    if main {
        mvsplat360_pipeline::model::write_model_dir(&model_dir, &model.model_config(), &model.model_tensors()?)?;
        let _ = crate::log::plot(&records, &out.join("loss.png"));
    }
    Ok(Summary { steps: step, last: records.last().cloned(), model_dir, train_seconds, lpips: lpips.is_some() })
}

/// The step and a SHA-256 of every trained weight (by name), as 32-bit words for [`crate::dist::check_agreement`],
/// and the hash in hex.
fn weights_digest(model: &Model, step: u64) -> Result<(Vec<u32>, String)> {
    let mut vars = model.vars();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    let mut h = Sha256::new();
    for (name, var) in &vars {
        h.update(name.as_bytes());
        let v: Vec<f32> = var.as_tensor().flatten_all()?.to_dtype(DType::F32)?.to_device(&Device::Cpu)?.to_vec1()?;
        for x in v {
            h.update(x.to_le_bytes());
        }
    }
    let d = h.finalize();
    let mut words = vec![step as u32, (step >> 32) as u32];
    words.extend(d.chunks_exact(4).map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes"))));
    Ok((words, d.iter().map(|b| format!("{b:02x}")).collect()))
}

struct MicroResult {
    loss: f64,
    mse: f64,
    lpips: Option<f64>,
    depth: Option<f64>,
    refiner: Option<(f64, f64)>,
    /// Stage `vae`: (l1, kl).
    vae: Option<(f64, f64)>,
    grads: Vec<Option<Tensor>>,
}

#[allow(clippy::too_many_arguments)]
fn draw_example(
    sources: &mut [SceneSource],
    weights: &[f64],
    wsum: f64,
    s: &SamplerSettings,
    cfg: &TrainConfig,
    step: u64,
    rng: &mut impl Rng,
) -> Result<Example> {
    for _ in 0..20 {
        let mut u = rng.gen_range(0.0..wsum);
        let mut k = 0;
        while k + 1 < weights.len() && u >= weights[k] {
            u -= weights[k];
            k += 1;
        }
        let scene = sources[k].draw(rng, cfg.train.seed, step)?;
        if let Some(ex) = make_example(&scene, s, cfg.model.near, cfg.model.far, rng)? {
            return Ok(ex);
        }
    }
    Err(TrainError::Data(format!("no scene has enough views for {} context + targets; add longer sequences or lower data.num_context", s.num_context)))
}

pub fn out_dir(cfg: &TrainConfig) -> &Path {
    &cfg.train.out
}
