//! End to end against the official evaluation: `eval` on a tiny MVSplat360 checkpoint made and run by the
//! official code (`scripts/fixtures/official-eval`: `ModelWrapper.test_step` on the CPU with the official encoder,
//! sgm sampler/guider/UNet/VAE/embedder, `save_image`, `post_process.py`, `src/evaluation/metrics.py`), with the
//! initial noise the official run drew, must write the official folders and scores.
//!
//! Fixture: `$MVSPLAT360_EVAL_FIXTURE`, default `tests/fixtures/official_eval` (its README says how it was made).
//! Bounds (two official runs that differ only in float summation order — thread count, weights × (1 + 1e-6) —
//! move GSplat / Refined pixels by one level on < 4e-4 of the values; histogram matching turns a one-level
//! change of its input into jumps of up to tens of levels on a few pixels):
//! - `ImagesGT`: identical;
//! - `ImagesGSplat`, `ImagesRefined0`: within 1 level on ≥ 99.9 % of values, never more than 2, and equal on
//!   ≥ 99 % (another 8-bit conversion would change about half of them);
//! - `ImagesPostprocessed0V2`: our matching of the fixture's own PNGs gives its PNGs exactly; end to end
//!   within 1 level on ≥ 99 % of values;
//! - PSNR, SSIM, LPIPS, DISTS of the fixture's own refined PNGs: within 1e-5 relative of the official values;
//!   of our PNGs, every folder: means within 1e-4 relative, each image within 2e-3.

use std::path::{Path, PathBuf};

use mvsplat360_pipeline::eval::{self, EvalRequest};
use mvsplat360_pipeline::model::ModelArgs;
use mvsplat360_pipeline::render::{RefineSettings, Silent};
use serde_json::Value;

const FOLDERS: [&str; 4] = ["ImagesGT", "ImagesGSplat", "ImagesRefined0", "ImagesPostprocessed0V2"];

fn fixture() -> PathBuf {
    let dir = std::env::var_os("MVSPLAT360_EVAL_FIXTURE")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/official_eval"));
    assert!(
        dir.join("model.ckpt").is_file(),
        "no official evaluation fixture at {} (set MVSPLAT360_EVAL_FIXTURE or make one with scripts/fixtures/official-eval)",
        dir.display()
    );
    dir
}

fn json(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

fn png(p: &Path) -> image::RgbImage {
    image::open(p).unwrap_or_else(|e| panic!("{}: {e}", p.display())).to_rgb8()
}

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).filter(|n| n.ends_with(".png")).collect();
    v.sort();
    v
}

/// Level differences of two folders of PNGs: (share of values off by more than 1, largest difference, share of
/// values that differ at all).
fn level_diff(ours: &Path, official: &Path) -> (f64, u8, f64) {
    let (mut over1, mut any, mut total, mut worst) = (0usize, 0usize, 0usize, 0u8);
    for n in names(official) {
        let (a, b) = (png(&ours.join(&n)), png(&official.join(&n)));
        assert_eq!(a.dimensions(), b.dimensions(), "{n}");
        for (x, y) in a.as_raw().iter().zip(b.as_raw()) {
            let d = x.abs_diff(*y);
            over1 += (d > 1) as usize;
            any += (d > 0) as usize;
            worst = worst.max(d);
            total += 1;
        }
    }
    (over1 as f64 / total as f64, worst, any as f64 / total as f64)
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs().max(1e-12)
}

/// The official run's refiner settings (its `architecture.json`).
fn refine_settings(arch: &Value) -> RefineSettings {
    let r = &arch["refiner"];
    RefineSettings { steps: r["svd_num_steps"].as_u64().unwrap() as usize, window: r["svd_num_frames"].as_u64().unwrap() as usize, ..RefineSettings::default() }
}

#[test]
fn eval_reproduces_the_official_evaluation() {
    let fx = fixture();
    let tmp = tempfile::tempdir().unwrap();
    // The checkpoint with its architecture: a model folder holding the official `.ckpt`.
    let model = tmp.path().join("model");
    std::fs::create_dir_all(&model).unwrap();
    std::fs::copy(fx.join("rust_config.json"), model.join("config.json")).unwrap();
    std::fs::copy(fx.join("model.ckpt"), model.join("model.ckpt")).unwrap();
    // The refiner's one-time conversion goes to a private cache.
    std::env::set_var("MVSPLAT360_CACHE", tmp.path().join("cache"));
    let out = tmp.path().join("eval");
    let arch = json(&fx.join("architecture.json"));
    let req = EvalRequest {
        data: fx.join("dl3dv/test"),
        index: fx.join("evaluation_index.json"),
        model: ModelArgs { ckpt: Some(model), ..Default::default() },
        size: None,
        scene_scale: None,
        refine: refine_settings(&arch),
        weights_dir: None,
        lpips: true,
        dists: true,
        fid: false,
        fid_variant: Default::default(),
        scenes: None,
        limit: None,
        out: out.clone(),
        noise: Some(fx.join("noise.safetensors")),
        shard: None,
        merge_only: false,
        exclude: Vec::new(),
        lease: Default::default(),
    };
    let s = eval::run(&req, &Silent).unwrap();
    assert!(s.missing.is_empty() && s.skipped_fov.is_empty(), "{s:?}");

    for d in FOLDERS {
        assert_eq!(names(&out.join(d)), names(&fx.join(d)), "{d}: file names");
    }
    let gt = level_diff(&out.join("ImagesGT"), &fx.join("ImagesGT"));
    assert_eq!(gt, (0.0, 0, 0.0), "ImagesGT: the preprocessed targets must be the official ones");
    for d in ["ImagesGSplat", "ImagesRefined0"] {
        let (share, worst, any) = level_diff(&out.join(d), &fx.join(d));
        println!("{d}: {any:.3e} of values differ, {share:.3e} by more than 1 level, worst {worst}");
        assert!(share <= 1e-3 && worst <= 2, "{d}: {share:e} of values off by more than 1 level, worst {worst}");
        // Float noise flips a level on < 4e-4 of the values; another 8-bit rule (rounding) flips about half.
        assert!(any <= 1e-2, "{d}: {any:e} of values differ from the official PNGs (another 8-bit conversion?)");
    }
    let (share, worst, _) = level_diff(&out.join("ImagesPostprocessed0V2"), &fx.join("ImagesPostprocessed0V2"));
    println!("ImagesPostprocessed0V2: {share:.3e} of values off by more than 1 level, worst {worst}");
    assert!(share <= 1e-2, "ImagesPostprocessed0V2: {share:e} of values off by more than 1 level (worst {worst})");

    // Our post-processing on the official PNGs: the official PNGs, exactly.
    for n in names(&fx.join("ImagesRefined0")) {
        let (r, g) = (png(&fx.join("ImagesRefined0").join(&n)), png(&fx.join("ImagesGSplat").join(&n)));
        let m = mvsplat360_refiner::histogram::match_histograms_u8(r.as_raw(), g.as_raw(), 3).unwrap();
        assert!(m == png(&fx.join("ImagesPostprocessed0V2").join(&n)).into_raw(), "{n}: histogram matching differs from post_process.py");
    }

    // Scores: ours of the official PNGs against the official values, and eval's own against them.
    let official = json(&fx.join("metrics.json"));
    let mine = json(&out.join("metrics.json"));
    let dev = candle_core::Device::Cpu;
    let lpips =
        mvsplat360_metrics::lpips::Lpips::load(None, mvsplat360_metrics::lpips::Net::Vgg, &dev).expect("LPIPS weights: run scripts/metric-weights/fetch");
    let dists = mvsplat360_metrics::dists::Dists::load(None, &dev).expect("DISTS weights: run scripts/metric-weights/fetch");
    let tensor = |p: &Path| {
        let img = mvsplat360_metrics::score::load_rgb(p).unwrap();
        candle_core::Tensor::from_vec(img.data, (1, 3, img.height, img.width), &dev).unwrap()
    };
    let methods = [("ImagesGSplat", "gsplat"), ("ImagesRefined0", "refined"), ("ImagesPostprocessed0V2", "postprocessed")];
    for (dir, key) in methods {
        let per = &official["per_image"][dir];
        // The metric functions on the official PNGs (the paper's column is enough: the networks cost seconds).
        let own_pngs = if dir == "ImagesRefined0" { names(&fx.join(dir)) } else { Vec::new() };
        for n in own_pngs {
            let (p, g) = (tensor(&fx.join(dir).join(&n)), tensor(&fx.join("ImagesGT").join(&n)));
            let flat = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let (pv, gv) = (flat(&p), flat(&g));
            let img = mvsplat360_metrics::score::load_rgb(&fx.join(dir).join(&n)).unwrap();
            let ours = [
                ("psnr", mvsplat360_metrics::psnr::psnr(&pv, &gv)),
                ("ssim", mvsplat360_metrics::ssim::ssim(&pv, &gv, 3, img.height, img.width).unwrap()),
                ("lpips", lpips.distance(&p, &g).unwrap()[0] as f64),
                ("dists", dists.distance(&p, &g).unwrap()[0] as f64),
            ];
            for (m, v) in ours {
                let want = per[&n][m].as_f64().unwrap();
                assert!(rel(v, want) <= 1e-5, "{dir}/{n} {m}: {v} vs official {want}");
            }
        }
        // eval's per-image scores (its scene records) of its own PNGs.
        for scene in official["images"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|n| n.as_str())
            .filter_map(|n| n.rsplit_once('_').map(|(s, _)| s.to_string()))
            .collect::<std::collections::BTreeSet<_>>()
        {
            let rec = json(&out.join("scenes").join(format!("{scene}.json")));
            for img in rec["methods"][key].as_array().unwrap() {
                let n = img["name"].as_str().unwrap();
                for m in ["psnr", "ssim", "lpips", "dists"] {
                    let (got, want) = (img[m].as_f64().unwrap(), per[n][m].as_f64().unwrap());
                    assert!(rel(got, want) <= 2e-3, "{dir}/{n} {m}: eval {got} vs official {want}");
                }
            }
        }
        for m in ["psnr", "ssim", "lpips", "dists"] {
            let (got, want) = (mine["methods"][key][m].as_f64().unwrap(), official["mean"][dir][m].as_f64().unwrap());
            println!("{dir} {m}: ours {got:.6}, official {want:.6}, relative {:.2e}", rel(got, want));
            assert!(rel(got, want) <= 1e-4, "{dir} mean {m}: {got} vs official {want}");
        }
    }

    // A merge renders nothing, so it converts nothing: a fresh cache stays empty.
    let merge_cache = tmp.path().join("merge-cache");
    std::env::set_var("MVSPLAT360_CACHE", &merge_cache);
    let merged = eval::run(&EvalRequest { merge_only: true, ..req.clone() }, &Silent).unwrap();
    assert_eq!(merged.resumed.len(), s.resumed.len() + s.rendered.len());
    assert!(!merge_cache.join("converted").exists(), "eval --merge converted the refiner");

    // Processes sharing a cache convert a checkpoint once: the others wait for it and take its file.
    std::env::set_var("MVSPLAT360_CACHE", tmp.path().join("shared-cache"));
    let w = mvsplat360_pipeline::model::RefinerWeights::Ckpt(fx.join("model.ckpt"));
    let notes = std::sync::Mutex::new(Vec::<String>::new());
    let paths: Vec<PathBuf> = std::thread::scope(|sc| {
        let hs: Vec<_> =
            (0..3).map(|_| sc.spawn(|| mvsplat360_pipeline::model::refiner_safetensors(&w, &|m| notes.lock().unwrap().push(m.to_string())).unwrap())).collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let notes = notes.into_inner().unwrap();
    assert_eq!(notes.iter().filter(|n| n.starts_with("converting")).count(), 1, "{notes:?}");
    assert!(paths.iter().all(|p| p == &paths[0] && p.is_file()), "{paths:?}");

    // The refiner in bf16 on the CPU (`--dtype bf16`; here in one test, as the cache is process-wide), on the
    // first scene (the test's time): the encoder's renders as in f32, the refined frames near the official f32
    // ones (PSNR against them; bf16's 8 bits through the tiny refiner move them by ≈ u·|x|, a few 8-bit levels
    // at most), per-image scores beside the official f32 ones.
    std::env::set_var("MVSPLAT360_CACHE", tmp.path().join("cache"));
    let out16 = tmp.path().join("eval-bf16");
    let compute = mvsplat360_pipeline::compute::Compute { refiner_dtype: candle_core::DType::BF16, ..Default::default() };
    let req16 = EvalRequest { out: out16.clone(), model: ModelArgs { compute, ..req.model.clone() }, limit: Some(1), ..req.clone() };
    let s16 = eval::run(&req16, &Silent).unwrap();
    assert!(s16.missing.is_empty() && s16.rendered.len() == 1, "{s16:?}");
    assert_eq!(json(&out16.join("eval.json"))["refiner_dtype"].as_str(), Some("bf16"), "eval.json must say bf16");
    let done = names(&out16.join("ImagesRefined0"));
    assert!(!done.is_empty());
    for n in names(&out16.join("ImagesGSplat")) {
        assert!(png(&out16.join("ImagesGSplat").join(&n)) == png(&out.join("ImagesGSplat").join(&n)), "{n}: the bf16 refiner changed the 3DGS render");
    }
    let psnrs: Vec<f64> = done
        .iter()
        .map(|n| {
            let (a, b) = (png(&out16.join("ImagesRefined0").join(n)), png(&fx.join("ImagesRefined0").join(n)));
            let to = |im: &image::RgbImage| im.as_raw().iter().map(|&v| v as f32 / 255.0).collect::<Vec<f32>>();
            mvsplat360_metrics::psnr::psnr(&to(&a), &to(&b))
        })
        .collect();
    let mean = psnrs.iter().sum::<f64>() / psnrs.len() as f64;
    let low = psnrs.iter().cloned().fold(f64::INFINITY, f64::min);
    println!("bf16 refiner: {} refined frames against the official f32 ones: PSNR mean {mean:.2} dB, worst {low:.2} dB", psnrs.len());
    assert!(mean >= 35.0 && low >= 30.0, "bf16 refined frames: PSNR against f32 mean {mean:.2} dB, worst {low:.2} dB");
    let scene = done[0].rsplit_once('_').unwrap().0.to_string();
    let rec = json(&out16.join("scenes").join(format!("{scene}.json")));
    for (dir, key) in methods {
        for m in ["psnr", "ssim", "lpips", "dists"] {
            let imgs = rec["methods"][key].as_array().unwrap();
            let b16 = imgs.iter().map(|i| i[m].as_f64().unwrap()).sum::<f64>() / imgs.len() as f64;
            let f32v = imgs.iter().map(|i| official["per_image"][dir][i["name"].as_str().unwrap()][m].as_f64().unwrap()).sum::<f64>() / imgs.len() as f64;
            println!("{scene} {dir} {m}: bf16 {b16:.6}, official f32 {f32v:.6}, relative {:.2e}", rel(b16, f32v));
        }
    }
}
