//! Scratch: central differences at several steps for the largest-gradient entry of parameters matching a pattern.
use candle_core::{DType, Tensor};
use mvsplat360_train::config::{RasterGrad, Source};
use mvsplat360_train::trainer::{make_example, render_example, Model};
use rand::SeedableRng;

fn main() -> anyhow::Result<()> {
    let pat = std::env::args().nth(1).unwrap_or("backbone.backbone.conv1.weight".into());
    let grad_mode = std::env::args().nth(2).unwrap_or("exact".into());
    let text = std::fs::read_to_string("/tmp/fdprobe.toml")?;
    let mut cfg = mvsplat360_train::TrainConfig::from_toml(&text, "x".as_ref())?;
    cfg.train.raster_grad = if grad_mode == "exact" { RasterGrad::Exact } else { RasterGrad::Official };
    cfg.data.sources = vec![Source::Folder { path: "assets/woodbox".into() }];
    let model = Model::new(&cfg)?;
    let mut src = mvsplat360_train::scenes::SceneSource::open(&cfg.data.sources[0], 128, 64, 64)?;
    let mut rng = rand::rngs::StdRng::seed_from_u64(2);
    let scene = src.draw(&mut rng)?;
    let s = mvsplat360_train::sampler::SamplerSettings { num_context: 3, num_target: 2, gap: None, closed_loop: true, flip: false };
    let ex = make_example(&scene, &s, 1.0, 100.0, &mut rng)?.unwrap();
    let loss_of = |m: &Model| -> Tensor {
        let (pred, _) = render_example(m, &ex).unwrap();
        mvsplat360_train::loss::mse(&pred, &ex.target_images).unwrap()
    };
    let grads = loss_of(&model).backward()?;
    for (name, var) in model.vars().iter().filter(|(n, _)| n.contains(&pat)).take(3) {
        let g: Vec<f32> = grads.get(var.as_tensor()).unwrap().flatten_all()?.to_vec1()?;
        let i = (0..g.len()).max_by(|&a, &b| g[a].abs().total_cmp(&g[b].abs())).unwrap();
        let orig = var.as_tensor().copy()?;
        let base: Vec<f32> = orig.flatten_all()?.to_vec1()?;
        let f = |v: f32| -> f64 {
            let mut d = base.clone();
            d[i] = v;
            var.set(&Tensor::from_vec(d, orig.dims(), orig.device()).unwrap()).unwrap();
            loss_of(&model).to_dtype(DType::F64).unwrap().to_scalar::<f64>().unwrap()
        };
        let x = base[i];
        let mut line = format!("{name}[{i}] autograd {:.6}", g[i]);
        for h in [3e-2f32, 1e-2, 3e-3, 1e-3, 3e-4] {
            let fd = (f(x + h) - f(x - h)) / (2.0 * h as f64);
            line += &format!(" | h={h:e}: {fd:.6}");
        }
        var.set(&orig)?;
        println!("{line}");
    }
    Ok(())
}
