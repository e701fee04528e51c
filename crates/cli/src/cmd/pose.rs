//! `mvsplat360 pose`: a video or a folder of overlapping photos → a posed scene folder, by COLMAP.

use std::path::PathBuf;

use mvsplat360_pose::{PoseOptions, PoseReport};

/// COLMAP and ffmpeg settings shared by `pose` and by `render` on a video or a photo folder.
#[derive(clap::Args, Clone, Debug)]
pub struct PoseFlags {
    /// Frames sampled from a video: the sharpest frame of each of this many equal intervals (at least 60 for a
    /// full orbit).
    #[arg(long, default_value_t = 150)]
    pub frames: u64,
    /// Long side, in pixels, of the frames and photos COLMAP poses and the scene keeps (never scaled up); a 4K
    /// video stays tractable on a CPU.
    #[arg(long, default_value_t = 1000)]
    pub max_size: u32,
    /// COLMAP camera model, one camera shared by all images of one size: SIMPLE_RADIAL (default; steady on
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
        }
    }
}

#[derive(clap::Args)]
pub struct Args {
    /// A video file (whatever ffmpeg reads: mp4, mov, mkv; H.264, HEVC) or a folder of overlapping photos
    /// (.jpg/.jpeg/.png). Five photos far apart cannot be posed by COLMAP: record a video around the scene or
    /// take many photos, each sharing most of its view with the next.
    pub input: PathBuf,
    /// The scene folder to create: images/ (undistorted), sparse/0 (a PINHOLE COLMAP model), pose.json (the
    /// report), logs/ (COLMAP's logs). It must not exist, unless it was posed from this same input.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub flags: PoseFlags,
    /// Fewer registered images than this is a failure (the context views `render` will take).
    #[arg(long, default_value_t = 5)]
    pub min_views: usize,
    /// Print pose.json on stdout when done.
    #[arg(long)]
    pub json: bool,
}

/// Runs `pose`, with bars and the Ctrl-C handling that stops COLMAP and ffmpeg.
pub fn pose_scene(input: &std::path::Path, out: &std::path::Path, opts: &PoseOptions, quiet: bool) -> anyhow::Result<PoseReport> {
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

pub fn run(a: Args, quiet: bool) -> anyhow::Result<()> {
    let _ = ctrlc::set_handler(|| {
        // COLMAP and ffmpeg run in their own process groups, which the terminal's Ctrl-C does not reach.
        mvsplat360_pose::stop_children();
        eprintln!("interrupted: nothing was written to the scene folder; the finished stages are kept and a rerun continues from them");
        std::process::exit(130);
    });
    let report = pose_scene(&a.input, &a.out, &a.flags.options(a.min_views), quiet)?;
    if a.json {
        println!("{}", serde_json::to_string(&report)?);
    }
    Ok(())
}
