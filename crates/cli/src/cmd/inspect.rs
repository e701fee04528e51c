//! `mvsplat360 inspect`: what a scene holds and which views the model would take as context.

use std::path::PathBuf;

use anyhow::Context;
use mvsplat360_camera::select::{baseline_stats, nearest_k};
use mvsplat360_pipeline::views::{ContextSpec, TargetSpec};

use super::views::ContextArgs;
use serde_json::json;

#[derive(clap::Args)]
pub struct Args {
    /// Scene: a folder with transforms.json, a transforms*.json file, a COLMAP folder (sparse/0 + images/),
    /// or a .torch chunk.
    pub scene: PathBuf,
    #[command(flatten)]
    pub views: ContextArgs,
    /// Print one JSON object on stdout instead of the human summary.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let scene = mvsplat360_dataset::read_scene_with(&args.scene, args.views.scene_key.as_deref())
        .with_context(|| format!("cannot read scene {}", args.scene.display()))?;
    // The same checks `render` does before any heavy work: every image decodes and matches its camera.
    mvsplat360_pipeline::render::check_scene_images(&scene).with_context(|| format!("checking scene {}", args.scene.display()))?;
    // A suggestion, so a count larger than the scene is clamped rather than refused.
    let spec = match args.views.spec() {
        ContextSpec::Count(n) => ContextSpec::Count(n.min(scene.len())),
        s => s,
    };
    let choice = mvsplat360_pipeline::views::choose(&scene, &spec, &TargetSpec::Views(vec![]))?;
    let context = choice.context;
    let cams = &scene.cameras;
    let c0 = &cams[0];
    let shared = cams.iter().all(|c| (c.fx, c.fy, c.cx, c.cy) == (c0.fx, c0.fy, c0.cx, c0.cy));
    let centres: Vec<[f64; 3]> = cams.iter().map(|c| c.center().into()).collect();
    let (bmin, bmax) = baseline_stats(cams);
    let groups = nearest_k(cams, 2);
    if args.json {
        let out = json!({
            "name": scene.name,
            "views": scene.len(),
            "width": c0.width,
            "height": c0.height,
            "sizes": cams.iter().map(|c| [c.width, c.height]).collect::<Vec<_>>(),
            "shared_intrinsics": shared,
            "intrinsics": cams.iter().map(|c| [c.fx, c.fy, c.cx, c.cy]).collect::<Vec<_>>(),
            "view_names": scene.view_names,
            "camera_centres": centres,
            "baseline_min": bmin,
            "baseline_max": bmax,
            "context": context,
            "suggested_context": context,
            "context_local_groups": context.iter().map(|&i| &groups[i]).collect::<Vec<_>>(),
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!("scene      {} ({})", scene.name, args.scene.display());
    println!("views      {}", scene.len());
    // Views may differ in size (photos from several cameras): every distinct size, with its view count.
    let mut sizes: Vec<((u32, u32), usize)> = Vec::new();
    for c in cams {
        match sizes.iter_mut().find(|(s, _)| *s == (c.width, c.height)) {
            Some((_, n)) => *n += 1,
            None => sizes.push(((c.width, c.height), 1)),
        }
    }
    if sizes.len() == 1 {
        println!("image      {}x{}", c0.width, c0.height);
    } else {
        let list: Vec<String> = sizes.iter().map(|((w, h), n)| format!("{w}x{h} ({n} views)")).collect();
        println!("image      sizes differ: {}", list.join(", "));
    }
    println!(
        "intrinsics fx {:.2} fy {:.2} cx {:.2} cy {:.2}{}",
        c0.fx,
        c0.fy,
        c0.cx,
        c0.cy,
        if shared { " (shared by all views)" } else { " (view 0; views differ)" }
    );
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for c in &centres {
        for k in 0..3 {
            lo[k] = lo[k].min(c[k]);
            hi[k] = hi[k].max(c[k]);
        }
    }
    println!("centres    x [{:.3}, {:.3}]  y [{:.3}, {:.3}]  z [{:.3}, {:.3}]", lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]);
    println!("baseline   min {bmin:.4}  max {bmax:.4} (pairwise centre distance)");
    println!("context    {:?}", context);
    for &i in &context {
        let c = centres[i];
        println!("  view {i:>4} {:<24} centre ({:.3}, {:.3}, {:.3})  nearest {:?}", scene.view_names[i], c[0], c[1], c[2], &groups[i][1..]);
    }
    Ok(())
}
