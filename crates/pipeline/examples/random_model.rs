//! Write a model folder with seeded random weights: `tiny` (tests, smoke runs) or `full` (the official
//! DL3DV architecture, ~9 GB; for measuring time and memory of a paper-size run without the real weights).
//!
//! cargo run --release -p mvsplat360-pipeline --example random_model -- tiny|full OUT_DIR [--no-refiner]

use mvsplat360_pipeline::model::{self, DataConfig, ModelConfig, RefinerModelConfig, MODEL_FORMAT};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: random_model tiny|full OUT_DIR [--no-refiner]");
        std::process::exit(2);
    }
    let refiner = !args.iter().any(|a| a == "--no-refiner");
    let cfg = match args[1].as_str() {
        "tiny" => model::tiny_config(refiner),
        "full" => {
            let data = DataConfig::dl3dv();
            ModelConfig {
                format: MODEL_FORMAT.into(),
                fit: None,
                blend: None,
                scene_scale: None,
                encoder: model::experiment_encoder(&data),
                data,
                refiner: refiner.then(RefinerModelConfig::default),
            }
        }
        other => {
            eprintln!("unknown size `{other}` (tiny or full)");
            std::process::exit(2);
        }
    };
    let out = std::path::Path::new(&args[2]);
    let sd = match model::random_state_dict(&cfg, 0) {
        Ok(sd) => sd,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    };
    if let Err(e) = model::write_model_dir(out, &cfg, &sd) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
    eprintln!("wrote {} tensors to {}", sd.len(), out.display());
}
