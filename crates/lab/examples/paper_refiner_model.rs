//! A model folder with the tests' tiny encoder (input 128×64) and a paper-size refiner (the official SVD UNet,
//! VAE and CLIP configurations), seeded random weights: about 9 GB, for timing what depends on the refiner's size
//! (loading it) without the official checkpoint. `paper_refiner_model OUT_DIR [SEED]`.

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let out = std::path::PathBuf::from(args.next().ok_or_else(|| anyhow::anyhow!("usage: paper_refiner_model OUT_DIR [SEED]"))?);
    let seed: u64 = args.next().map(|s| s.parse()).transpose()?.unwrap_or(1);
    let mut cfg = mvsplat360_pipeline::model::tiny_config(true);
    cfg.refiner = Some(mvsplat360_pipeline::model::RefinerModelConfig {
        unet: mvsplat360_refiner::unet::VideoUNetConfig::default(),
        vae: mvsplat360_refiner::vae::AutoencoderConfig::default(),
        clip: mvsplat360_refiner::clip::ClipVisionConfig::default(),
    });
    let sd = mvsplat360_pipeline::model::random_state_dict(&cfg, seed)?;
    let n: usize = sd.iter().map(|(_, t)| t.elem_count()).sum();
    mvsplat360_pipeline::model::write_model_dir(&out, &cfg, &sd)?;
    println!("{}: {n} parameters", out.display());
    Ok(())
}
