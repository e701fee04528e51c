//! `mvsplat360 pose`: a video or a folder of photos → a posed scene folder, by COLMAP or, for a few photos,
//! by the VGGT model; `--engine auto` chooses ([`plan`]).

use std::path::{Path, PathBuf};

use anyhow::Context;
use mvsplat360_pose::vggt::{VggtPoseOptions, VggtPoseReport, AUTO_MAX_PHOTOS, MIN_PHOTOS, WEIGHTS_HELP};
use mvsplat360_pose::{ColmapGpu, InputKind, Matcher, PoseError, PoseOptions, PoseReport};

/// Which engine poses the input.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum EngineChoice {
    /// A video → COLMAP; a photo folder with fewer than 20 photos and --vggt-weights → VGGT; otherwise COLMAP,
    /// with VGGT as the fallback (when --vggt-weights is given) if COLMAP registers too few views.
    Auto,
    /// The VGGT model on a photo folder (needs --vggt-weights).
    Vggt,
    /// COLMAP only.
    Colmap,
}

/// COLMAP's feature matcher.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum MatcherChoice {
    /// Sequential for a video or more than 100 photos, exhaustive for fewer.
    Auto,
    /// Every pair of images (about n²/2 pairs: 10 minutes for 100 photos on 2 CPU cores); for photos in no order.
    Exhaustive,
    /// Each image with the next ones in name (capture) order, plus the first and last frames for loop closure;
    /// for a video or photos taken walking along.
    Sequential,
}

/// Whether COLMAP may use the GPU.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum GpuChoice {
    /// The GPU for SIFT extraction and matching when COLMAP was built with CUDA (`colmap -h` says so).
    Auto,
    /// The CPU only, even for a CUDA build (`--SiftExtraction.use_gpu 0`, `--SiftMatching.use_gpu 0`), e.g. on a
    /// machine whose GPU is busy or has no driver.
    Off,
}

/// COLMAP, ffmpeg and VGGT settings shared by `pose` and by `render` on a video or a photo folder.
#[derive(clap::Args, Clone, Debug)]
pub struct PoseFlags {
    /// How the cameras are estimated. `auto` (default): a video goes to COLMAP; a photo folder with fewer than
    /// 20 photos goes to VGGT when --vggt-weights is given; anything else goes to COLMAP, and when COLMAP
    /// registers fewer views than needed on a photo folder, VGGT takes over if --vggt-weights is given.
    /// `vggt`: the VGGT model (a photo folder only; needs --vggt-weights). `colmap`: COLMAP only.
    #[arg(long, value_enum, default_value_t = EngineChoice::Auto)]
    pub engine: EngineChoice,
    /// VGGT weights: the official model.pt of VGGT-1B (https://huggingface.co/facebook/VGGT-1B, CC BY-NC 4.0,
    /// non-commercial) or of VGGT-1B-Commercial (gated by Meta), or a VGGT model folder (config.json +
    /// model.safetensors or model.pt); a path, or a name fetched into the Hugging Face cache when VGGT runs:
    /// `vggt-1b`, `vggt-1b-commercial` (HF_TOKEN with access), `hf:OWNER/REPO[/FILE][@REV]`, a Hub URL (an
    /// existing path wins). VGGT runs on the CPU in f32 (about 5 GB of weights for VGGT-1B), or bf16 with
    /// --encoder-dtype bf16.
    #[arg(long, value_name = "PATH|NAME")]
    pub vggt_weights: Option<PathBuf>,
    /// Frames sampled from a video: the sharpest frame of each of this many equal intervals (at least 60 for a
    /// full orbit).
    #[arg(long, default_value_t = 150)]
    pub frames: u64,
    /// Long side, in pixels, of the frames and photos COLMAP poses and the scene keeps (never scaled up); a 4K
    /// video stays tractable on a CPU. (VGGT always sees the photos 518 pixels wide; this sets what the scene
    /// keeps.)
    #[arg(long, default_value_t = 1000)]
    pub max_size: u32,
    /// COLMAP camera model, one camera shared by all images of one device (size and EXIF make, model, focal
    /// length): SIMPLE_RADIAL (default; steady on
    /// weak data), RADIAL, OPENCV, FULL_OPENCV, SIMPLE_PINHOLE or PINHOLE. The scene is undistorted to PINHOLE
    /// either way.
    #[arg(long, default_value = "SIMPLE_RADIAL")]
    pub camera_model: String,
    /// The `colmap` program (default: the one on PATH; Debian: `apt-get install colmap`).
    #[arg(long)]
    pub colmap: Option<PathBuf>,
    /// The `ffmpeg` program, with `ffprobe` beside it (default: the ones on PATH; Debian: `apt-get install ffmpeg`).
    #[arg(long)]
    pub ffmpeg: Option<PathBuf>,
    /// COLMAP's feature matcher (the scene's fingerprint includes a chosen one).
    #[arg(long, value_enum, default_value_t = MatcherChoice::Auto)]
    pub matcher: MatcherChoice,
    /// Whether COLMAP may use the GPU (bundle adjustment runs on the CPU either way).
    #[arg(long, value_enum, default_value_t = GpuChoice::Auto)]
    pub colmap_gpu: GpuChoice,
    /// VGGT's precision: `pose --encoder-dtype`, or `render`'s (one flag there for the models before the
    /// rasterizer).
    #[arg(skip = candle_core::DType::F32)]
    pub vggt_dtype: candle_core::DType,
}

impl PoseFlags {
    pub fn options(&self, min_views: usize) -> PoseOptions {
        PoseOptions {
            colmap: self.colmap.clone(),
            ffmpeg: self.ffmpeg.clone(),
            frames: self.frames,
            max_size: self.max_size,
            camera_model: self.camera_model.clone(),
            min_views,
            matcher: match self.matcher {
                MatcherChoice::Auto => None,
                MatcherChoice::Exhaustive => Some(Matcher::Exhaustive),
                MatcherChoice::Sequential => Some(Matcher::Sequential),
            },
            colmap_gpu: match self.colmap_gpu {
                GpuChoice::Auto => ColmapGpu::Auto,
                GpuChoice::Off => ColmapGpu::Off,
            },
        }
    }

    fn vggt_options(&self, weights: &Path) -> VggtPoseOptions {
        VggtPoseOptions { dtype: self.vggt_dtype, ..VggtPoseOptions::new(weights, self.max_size) }
    }
}

#[derive(clap::Args)]
pub struct Args {
    /// A video file (whatever ffmpeg reads: mp4, mov, mkv; H.264, HEVC) or a folder of photos
    /// (.jpg/.jpeg/.png). Five photos far apart cannot be posed by COLMAP: give --vggt-weights (VGGT poses
    /// them), or record a video around the scene, or take many photos, each sharing most of its view with the
    /// next.
    pub input: PathBuf,
    /// The scene folder to create: images/ (undistorted by COLMAP; as decoded by VGGT), sparse/0 (a PINHOLE
    /// COLMAP model), pose.json (the report), logs/ (COLMAP's logs). It must not exist, unless it was posed from
    /// this same input. One run at a time per folder: a second run into it is refused at once, naming the
    /// process posing it (the lock file `.NAME.pose.lock` beside it); rerun when that one is done to reuse its
    /// scene.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub flags: PoseFlags,
    /// Fewer images registered by COLMAP than this is a failure (the context views `render` will take).
    #[arg(long, default_value_t = 5)]
    pub min_views: usize,
    /// Print pose.json on stdout when done.
    #[arg(long)]
    pub json: bool,
    /// Precision of VGGT: `f32` (default) or `bf16` (the CPU's bf16 products on weights packed once, where it
    /// has AVX512-BF16: the aggregator and the DPT heads' convolutions; the camera head stays f32). pose.json
    /// records it (`settings.dtype`), and a scene posed in another precision is not reused.
    #[arg(long, default_value = "f32", value_parser = mvsplat360_pipeline::compute::parse_encoder_dtype)]
    pub encoder_dtype: candle_core::DType,
}

/// A scene posed by either engine.
#[derive(Debug, Clone)]
pub enum Posed {
    Colmap(Box<PoseReport>),
    Vggt(Box<VggtPoseReport>),
}

impl Posed {
    pub fn to_json(&self) -> serde_json::Result<String> {
        match self {
            Posed::Colmap(r) => serde_json::to_string(r),
            Posed::Vggt(r) => serde_json::to_string(r),
        }
    }
}

/// What runs: COLMAP (with VGGT as its fallback when weights are given) or VGGT.
#[derive(Debug, Clone, PartialEq)]
pub enum Plan {
    Colmap { fallback: Option<PathBuf> },
    Vggt { weights: PathBuf },
}

/// The engine for `input` under `--engine`, and why (said on stderr). `auto`: a video → COLMAP; a photo
/// folder with fewer than [`AUTO_MAX_PHOTOS`] photos and `--vggt-weights` → VGGT; otherwise COLMAP, with
/// VGGT as the fallback when weights are given.
pub fn plan(input: &Path, flags: &PoseFlags) -> anyhow::Result<(Plan, String)> {
    let kind = mvsplat360_pose::input_kind(input)?;
    let weights = flags.vggt_weights.clone();
    Ok(match (flags.engine, kind) {
        (EngineChoice::Vggt, InputKind::Video) => anyhow::bail!(
            "{}: --engine vggt poses a folder of photos, not a video; use --engine colmap (or auto) for a video, or extract a few frames into a folder",
            input.display()
        ),
        (EngineChoice::Vggt, InputKind::Photos) => match weights {
            Some(w) => (Plan::Vggt { weights: w }, "--engine vggt".into()),
            None => anyhow::bail!("--engine vggt needs the VGGT weights. {WEIGHTS_HELP}"),
        },
        (EngineChoice::Colmap, _) => (Plan::Colmap { fallback: None }, "--engine colmap".into()),
        (EngineChoice::Auto, InputKind::Video) => (Plan::Colmap { fallback: None }, "auto: a video goes to COLMAP".into()),
        (EngineChoice::Auto, InputKind::Photos) => {
            let n = mvsplat360_pose::photos::list(input)?.0.len();
            let photos = if n == 1 { "1 photo".to_string() } else { format!("{n} photos") };
            match weights {
                Some(w) if n < AUTO_MAX_PHOTOS => {
                    (Plan::Vggt { weights: w }, format!("auto: {photos} (fewer than {AUTO_MAX_PHOTOS}) and --vggt-weights → VGGT"))
                }
                Some(w) => {
                    (Plan::Colmap { fallback: Some(w) }, format!("auto: {photos} ({AUTO_MAX_PHOTOS} or more) → COLMAP, VGGT if COLMAP cannot pose them"))
                }
                None => (Plan::Colmap { fallback: None }, format!("auto: {photos}, no --vggt-weights → COLMAP")),
            }
        }
    })
}

/// Whether the scene folder `scene` was posed from `input` with these settings by an engine this plan allows
/// (checked by that engine's fingerprint).
pub fn reusable(input: &Path, scene: &Path, flags: &PoseFlags, min_views: usize) -> anyhow::Result<bool> {
    let Some((engine, fp)) = mvsplat360_pose::vggt::read_engine(scene) else { return Ok(false) };
    let (plan, _) = plan(input, flags)?;
    Ok(match (engine.as_str(), &plan) {
        ("vggt", Plan::Vggt { weights } | Plan::Colmap { fallback: Some(weights) }) => {
            let weights = vggt_weights(weights, true)?;
            mvsplat360_pose::vggt::fingerprint(input, &flags.vggt_options(&weights))? == fp
        }
        ("colmap", _) if flags.engine != EngineChoice::Vggt => mvsplat360_pose::fingerprint(input, &flags.options(min_views))? == fp,
        _ => false,
    })
}

/// Runs `pose` with the engine [`plan`] picks, with bars and the Ctrl-C handling that stops COLMAP and ffmpeg.
pub fn pose_scene(input: &Path, out: &Path, flags: &PoseFlags, min_views: usize, quiet: bool) -> anyhow::Result<Posed> {
    let (plan, why) = plan(input, flags)?;
    // A scene VGGT posed is checked against VGGT's fingerprint (COLMAP's would refuse it).
    let existing = mvsplat360_pose::vggt::read_engine(out).map(|(e, _)| e);
    let vggt_weights = match &plan {
        Plan::Vggt { weights } | Plan::Colmap { fallback: Some(weights) } => Some(weights.clone()),
        Plan::Colmap { fallback: None } => None,
    };
    if let (Some("vggt"), Some(w)) = (existing.as_deref(), &vggt_weights) {
        return run_vggt(input, out, flags, w, quiet);
    }
    if !quiet {
        eprintln!("posing {} ({why})", input.display());
    }
    match plan {
        Plan::Vggt { weights } => run_vggt(input, out, flags, &weights, quiet),
        Plan::Colmap { fallback } => {
            let kind = mvsplat360_pose::input_kind(input)?;
            match run_colmap(input, out, &flags.options(min_views), quiet) {
                Ok(r) => Ok(Posed::Colmap(Box::new(r))),
                Err(PoseError::NotPosed(msg)) if kind == InputKind::Photos => match fallback {
                    Some(w) => {
                        eprintln!("{msg}\nfalling back to VGGT ({}), as --engine auto does when COLMAP cannot pose a photo folder", w.display());
                        run_vggt(input, out, flags, &w, quiet)
                    }
                    None => Err(anyhow::anyhow!(
                        "{msg}\nFor a few photos far apart, the VGGT model estimates the cameras without COLMAP's overlap: {WEIGHTS_HELP}{}",
                        engine_hint(flags)
                    )),
                },
                // Too few photos for COLMAP (it refuses before running): say VGGT's way too.
                Err(e @ PoseError::Input { .. })
                    if kind == InputKind::Photos
                        && flags.vggt_weights.is_none()
                        && mvsplat360_pose::photos::list(input).is_ok_and(|(p, _)| p.len() >= MIN_PHOTOS && p.len() < min_views.max(2)) =>
                {
                    Err(anyhow::anyhow!("{e}\nFor a few photos, the VGGT model estimates the cameras: {WEIGHTS_HELP}{}", engine_hint(flags)))
                }
                Err(e) => Err(e.into()),
            }
        }
    }
}

fn engine_hint(flags: &PoseFlags) -> &'static str {
    if flags.engine == EngineChoice::Colmap {
        " (with --engine auto or vggt)"
    } else {
        ""
    }
}

fn run_colmap(input: &Path, out: &Path, opts: &PoseOptions, quiet: bool) -> Result<PoseReport, PoseError> {
    let bars = super::progress::Bars::new(quiet);
    // Every PoseError names the input or the program already.
    let report = mvsplat360_pose::pose(input, out, opts, &bars)?;
    if !quiet {
        let pct = 100.0 * report.registered_share;
        let err = report.mean_reprojection_error_px.map(|e| format!(", mean reprojection error {e:.2} px")).unwrap_or_default();
        eprintln!(
            "posed {} of {} images ({pct:.0} %){err} in {:.0} s (COLMAP {:.0} s) → {} (images/, sparse/0, pose.json)",
            report.registered,
            report.images_total,
            report.seconds.total,
            report.seconds.colmap,
            out.display()
        );
    }
    Ok(report)
}

/// `--vggt-weights` as a local path: a name is fetched (only once VGGT is to run; see [`super::names`]).
fn vggt_weights(w: &Path, quiet: bool) -> anyhow::Result<PathBuf> {
    let refuse = super::names::Default::Refuse("VGGT weights (give vggt-1b or a path)");
    super::names::resolve(w, "--vggt-weights", refuse, super::names::Freshness::Ask, quiet)
}

fn run_vggt(input: &Path, out: &Path, flags: &PoseFlags, weights: &Path, quiet: bool) -> anyhow::Result<Posed> {
    let weights = &vggt_weights(weights, quiet)?;
    let bars = super::progress::Bars::new(quiet);
    let r = mvsplat360_pose::vggt::pose_vggt(input, out, &flags.vggt_options(weights), &bars)?;
    if !quiet {
        let conf: Vec<String> = r.views.iter().map(|v| format!("{:.1}", v.mean_depth_confidence)).collect();
        eprintln!(
            "posed {} photos with VGGT (the model saw {}x{}; mean depth confidence per view {}; {} points, {}) in {:.0} s → {} (images/, sparse/0, pose.json). \
             The world is in VGGT's normalised units and the first camera is as predicted.",
            r.images_total,
            r.model_input.width,
            r.model_input.height,
            conf.join(", "),
            r.points.count,
            r.points.selection,
            r.seconds.total,
            out.display()
        );
        if r.images_total < 5 {
            eprintln!("note: {} photos; MVSplat360 takes 5 context views: render needs --num-context {} or fewer", r.images_total, r.images_total);
        }
    }
    Ok(Posed::Vggt(Box::new(r)))
}

pub fn run(a: Args, quiet: bool) -> anyhow::Result<()> {
    let _ = ctrlc::set_handler(|| {
        // COLMAP and ffmpeg run in their own process groups, which the terminal's Ctrl-C does not reach.
        mvsplat360_pose::stop_children();
        eprintln!("interrupted: nothing was written to the scene folder; a rerun continues from COLMAP's finished stages (VGGT starts again)");
        std::process::exit(130);
    });
    let flags = PoseFlags { vggt_dtype: a.encoder_dtype, ..a.flags };
    let posed = pose_scene(&a.input, &a.out, &flags, a.min_views, quiet)?;
    if a.json {
        println!("{}", posed.to_json().context("writing pose.json to stdout")?);
    }
    Ok(())
}
