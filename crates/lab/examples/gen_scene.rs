//! Write the views of a procedural scene as PNGs to look at: `gen_scene SEED OUT_DIR [WIDTH HEIGHT]`; with
//! `--folder` first, as a scene folder (`transforms.json`, 32 views) that `render` and `heldout` read, as
//! `train-blend` writes its procedural scenes.

fn main() -> anyhow::Result<()> {
    let mut a: Vec<String> = std::env::args().collect();
    let folder = a.get(1).is_some_and(|s| s == "--folder");
    if folder {
        a.remove(1);
    }
    anyhow::ensure!(a.len() >= 3, "usage: gen_scene [--folder] SEED OUT_DIR [WIDTH HEIGHT]");
    let seed: u64 = a[1].parse()?;
    let out = std::path::PathBuf::from(&a[2]);
    let (width, height) = if a.len() >= 5 { (a[3].parse()?, a[4].parse()?) } else { (256, 128) };
    if folder {
        return Ok(mvsplat360_train::blend::write_procedural(seed, &out, width, height)?);
    }
    std::fs::create_dir_all(&out)?;
    let t = std::time::Instant::now();
    let opts = mvsplat360_train::data::procedural::GenOptions { width, height, ..Default::default() };
    let s = mvsplat360_train::data::procedural::generate(seed, &opts);
    eprintln!("{}: {} views in {:.2} s", s.name, s.views.len(), t.elapsed().as_secs_f64());
    for (i, v) in s.views.iter().enumerate() {
        let img = mvsplat360_dataset::ImageF32 { width, height, data: v.image.clone() };
        img.to_rgb8().save(out.join(format!("{i:03}.png")))?;
    }
    Ok(())
}
