//! `eval` end to end on a two-scene `.torch` dataset (the committed test chunk) with a tiny random model: the
//! official folder layout and file names (target view index, scored = `target_quantify`), the tables, resume
//! without recomputation, and the settings guard; `eval-index` against closed-form camera layouts.

use std::path::{Path, PathBuf};
use std::time::SystemTime;

use mvsplat360_dataset::index::IndexOptions;
use mvsplat360_pipeline::eval::{self, EvalRequest, Method};
use mvsplat360_pipeline::model::{self, ModelArgs};
use mvsplat360_pipeline::preprocess::{InputSize, Preprocess};
use mvsplat360_pipeline::render::{RefineSettings, Silent};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn chunk_dir() -> PathBuf {
    root().join("crates/dataset/tests/data/chunk")
}

/// A dataset folder: the committed chunk (scenes woodbox_a: 3 views, woodbox_b: 2 views) and its index.json.
fn dataset(dir: &Path) -> PathBuf {
    let d = dir.join("data");
    std::fs::create_dir_all(&d).unwrap();
    for f in ["000000.torch", "index.json"] {
        std::fs::copy(chunk_dir().join(f), d.join(f)).unwrap();
    }
    d
}

fn tiny_model(dir: &Path) -> PathBuf {
    let cfg = model::tiny_config(true);
    let sd = model::random_state_dict(&cfg, 7).unwrap();
    let m = dir.join("tiny");
    model::write_model_dir(&m, &cfg, &sd).unwrap();
    m
}

/// An RE10K-style entry with `target_quantify` (unsorted on purpose), a DL3DV-style one without, a scene the
/// data lacks, and a null entry.
const INDEX: &str = r#"{
  "woodbox_a": {"context": [2, 0], "target": [2, 1, 0], "target_quantify": [2, 1]},
  "woodbox_b": [{"context": [0, 1], "target": [1, 0]}],
  "zz_absent": {"context": [0, 1], "target": [0]},
  "nulled": null
}"#;

fn request(data: &Path, index: &Path, m: &Path, out: &Path) -> EvalRequest {
    EvalRequest {
        data: data.to_path_buf(),
        index: index.to_path_buf(),
        model: ModelArgs { ckpt: Some(m.to_path_buf()), ..Default::default() },
        size: None,
        scene_scale: Default::default(),
        // guidance 0.1: an f32 that prints shorter than its f64 value (eval.json must still compare equal).
        refine: RefineSettings { steps: 1, window: 3, guidance_min: 0.1, ..RefineSettings::default() },
        weights_dir: None,
        // Network metrics off: a developer's installed weights must not change what is checked here (the CLI
        // test covers missing weights → nulls).
        lpips: false,
        dists: false,
        fid: false,
        fid_variant: Default::default(),
        scenes: None,
        limit: None,
        out: out.to_path_buf(),
        noise: None,
        shard: None,
        merge_only: false,
        exclude: Vec::new(),
        lease: Default::default(),
    }
}

fn mtimes(dir: &Path) -> Vec<(PathBuf, SystemTime)> {
    let mut v = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            v.extend(mtimes(&p));
        } else if !p.ends_with("metrics.json") && !p.ends_with("metrics.md") {
            v.push((p.clone(), e.metadata().unwrap().modified().unwrap()));
        }
    }
    v.sort();
    v
}

fn png(p: &Path) -> image::RgbImage {
    image::open(p).unwrap_or_else(|e| panic!("{}: {e}", p.display())).to_rgb8()
}

#[test]
fn eval_writes_official_layout_tables_and_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let data = dataset(tmp.path());
    let index = tmp.path().join("index_eval.json");
    std::fs::write(&index, INDEX).unwrap();
    let m = tiny_model(tmp.path());
    let out = tmp.path().join("eval");
    let req = request(&data, &index, &m, &out);

    let s = eval::run(&req, &Silent).unwrap();
    assert_eq!((s.selected, s.null_entries), (3, 1));
    assert_eq!(s.rendered, ["woodbox_a", "woodbox_b"]);
    assert!(s.resumed.is_empty() && s.rescored.is_empty());
    assert_eq!(s.missing, ["zz_absent"]);
    assert_eq!(s.images, 4);

    // Official names: {scene}_{view index:06}.png; only target_quantify views for woodbox_a.
    let expect = ["woodbox_a_000001.png", "woodbox_a_000002.png", "woodbox_b_000000.png", "woodbox_b_000001.png"];
    for d in ["ImagesGT", "ImagesGSplat", "ImagesRefined0", "ImagesPostprocessed0V2"] {
        let mut names: Vec<String> = std::fs::read_dir(out.join(d)).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
        names.sort();
        assert_eq!(names, expect, "{d}");
        for n in &names {
            assert_eq!(png(&out.join(d).join(n)).dimensions(), (128, 64), "{d}/{n}");
        }
    }
    // The GT image of a name is that view's photo, preprocessed as the model sees it.
    let scene = mvsplat360_dataset::read_scene_with(&data.join("000000.torch"), Some("woodbox_a")).unwrap();
    let pre = Preprocess { size: InputSize::Fixed { width: 128, height: 64 }, multiple: 64 };
    for v in [1usize, 2] {
        let (img, _) = pre.view(&scene.image(v).unwrap(), &scene.cameras[v]).unwrap();
        assert_eq!(png(&out.join(format!("ImagesGT/woodbox_a_{v:06}.png"))).as_raw(), img.to_rgb8().as_raw(), "view {v}");
    }

    // Per-scene record: sorted context/targets, scored = quantify, scores from the saved PNGs.
    let rec: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("scenes/woodbox_a.json")).unwrap()).unwrap();
    assert_eq!(rec["context"], serde_json::json!([0, 2]));
    assert_eq!(rec["targets"], serde_json::json!([0, 1, 2]));
    assert_eq!(rec["scored"], serde_json::json!([1, 2]));
    let r0 = &rec["methods"]["refined"][0];
    assert_eq!(r0["name"], "woodbox_a_000001.png");
    let load = |d: &str| mvsplat360_metrics::score::load_rgb(&out.join(d).join("woodbox_a_000001.png")).unwrap();
    let psnr = mvsplat360_metrics::psnr::psnr(&load("ImagesRefined0").data, &load("ImagesGT").data);
    assert!((r0["psnr"].as_f64().unwrap() - psnr).abs() < 1e-9);
    assert!(r0["lpips"].is_null());

    // metrics.json: every method, the paper's columns, per scene; FID and the network metrics null here.
    let mj: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(mj["primary"], "refined");
    assert_eq!(mj["columns"], serde_json::json!(["psnr", "ssim", "lpips", "dists", "fid"]));
    assert_eq!(mj["images"], 4);
    assert_eq!(mj["scenes"]["missing_from_data"], serde_json::json!(["zz_absent"]));
    for m in Method::ALL {
        let x = &mj["methods"][m.key()];
        assert_eq!(x["folder"], m.dir());
        assert_eq!(x["images"], 4);
        let (p, q) = (x["psnr"].as_f64().unwrap(), x["ssim"].as_f64().unwrap());
        assert!(p > 0.0 && p < 60.0 && q > -1.0 && q < 1.0, "{x}");
        assert!(x["lpips"].is_null() && x["dists"].is_null() && x["fid"].is_null());
    }
    // The overall mean is over images: (2·mean_a + 2·mean_b) / 4.
    let pa = mj["per_scene"]["woodbox_a"]["refined"]["psnr"].as_f64().unwrap();
    let pb = mj["per_scene"]["woodbox_b"]["refined"]["psnr"].as_f64().unwrap();
    assert!((mj["methods"]["refined"]["psnr"].as_f64().unwrap() - (pa + pb) / 2.0).abs() < 1e-9);
    let md = std::fs::read_to_string(out.join("metrics.md")).unwrap();
    assert!(md.contains("| Method | Folder | Images | PSNR↑ | SSIM↑ | LPIPS↓ | DISTS↓ | FID↓ |"), "{md}");
    let rows: Vec<&str> = md.lines().filter(|l| l.starts_with("| ") && l.contains("`Images")).collect();
    assert_eq!(rows.len(), 3, "{md}");
    assert!(rows[0].contains("`ImagesRefined0`") && rows[1].contains("`ImagesPostprocessed0V2`") && rows[2].contains("`ImagesGSplat`"));
    assert!(md.contains(&format!("| woodbox_a | 2 | {pa:.2} |")), "{md}");

    // Re-run: nothing recomputed (no file rewritten), same tables.
    let before = mtimes(&out);
    let s2 = eval::run(&req, &Silent).unwrap();
    assert_eq!(s2.resumed, ["woodbox_a", "woodbox_b"]);
    assert!(s2.rendered.is_empty() && s2.rescored.is_empty());
    assert_eq!(mtimes(&out), before);
    assert_eq!(s2.methods, s.methods);

    // A lost image: only that scene is rendered again.
    std::fs::remove_file(out.join("ImagesRefined0/woodbox_b_000000.png")).unwrap();
    let s3 = eval::run(&req, &Silent).unwrap();
    assert_eq!(s3.rendered, ["woodbox_b"]);
    assert_eq!(s3.resumed, ["woodbox_a"]);
    assert!(out.join("ImagesRefined0/woodbox_b_000000.png").is_file());

    // Other settings into the same folder are refused, naming what differs.
    let mut other = req.clone();
    other.refine.steps = 2;
    let err = eval::run(&other, &Silent).unwrap_err().to_string();
    assert!(err.contains("--out") && err.contains("other settings") && err.contains("refine"), "{err}");

    // --limit / --scenes select in index order.
    let mut one = req.clone();
    one.scenes = Some(vec!["woodbox_b".into()]);
    let s4 = eval::run(&one, &Silent).unwrap();
    assert_eq!((s4.selected, s4.images), (1, 2));
    assert_eq!(s4.resumed, ["woodbox_b"]);
}

fn line(n: usize) -> Vec<[f64; 3]> {
    (0..n).map(|i| [i as f64, 0.0, 0.0]).collect()
}

/// Cameras on a line at x = 0..299: the official farthest-point sampling starts at the end farthest from the
/// barycentre (x = 0 and x = 299 tie; torch.max takes the first), then 299, then the midpoints (first on ties):
/// 149, then 224 (gap 75 beats 74), then 74. Targets: every `len(rest) // 56`-th non-context view.
#[test]
fn index_entry_closed_form_on_a_line() {
    let e = mvsplat360_dataset::index::index_entry(&line(300), &IndexOptions::default()).unwrap();
    assert_eq!(e.context, vec![0, 74, 149, 224, 299]);
    assert_eq!(
        mvsplat360_camera::select::farthest_points(&line(300), 5, mvsplat360_camera::select::FpsStart::FarthestFromCentroid),
        vec![0, 299, 149, 224, 74]
    );
    let rest: Vec<usize> = (0..300).filter(|x| !e.context.contains(x)).collect();
    assert_eq!(rest.len(), 295);
    let expect: Vec<usize> = (0..56).map(|i| rest[i * (295 / 56)]).collect();
    assert_eq!(e.target, expect);
    // Closed form of rest[5i]: 1..=73, 75..=148, 150..=223, 225..=298.
    assert_eq!((e.target[0], e.target[1], e.target[14], e.target[15], e.target[55]), (1, 6, 71, 77, 279));
    assert!(e.target_quantify.is_none());

    // The n150 variant (ratio 0.5): the first 150 views, context 0, 37, 74, 111, 149, every 2nd remaining view.
    let o = IndexOptions { view_selection_ratio: 0.5, ..IndexOptions::default() };
    assert_eq!(o.official_file_name(), "dl3dv_ctx_5v_tgt_56v_n150.json");
    assert_eq!(IndexOptions::default().official_file_name(), "dl3dv_ctx_5v_tgt_56v.json");
    let e = mvsplat360_dataset::index::index_entry(&line(300), &o).unwrap();
    assert_eq!(e.context, vec![0, 37, 74, 111, 149]);
    assert_eq!((e.target[0], e.target[1], e.target[18], e.target[55]), (1, 3, 38, 114));
    assert!(e.target.iter().all(|&t| t < 150));

    // Too few views: no entry (the official script stops with an error).
    assert!(mvsplat360_dataset::index::index_entry(&line(40), &IndexOptions::default()).unwrap_err().contains("fewer than the 56 target views"));
    assert!(mvsplat360_dataset::index::index_entry(&line(4), &IndexOptions::default()).unwrap_err().contains("context"));
}

/// On the committed chunk: scene order is chunk order, views come from the decoded cameras.
#[test]
fn generate_index_from_chunks() {
    let o = IndexOptions { num_context: 2, num_target: 1, view_selection_ratio: 1.0 };
    let g = eval::generate_index(&chunk_dir(), &o, &Silent).unwrap();
    assert_eq!(g.chunks, 1);
    let keys: Vec<&str> = g.entries.iter().map(|(k, _)| k.as_str()).collect();
    assert_eq!(keys, ["woodbox_a", "woodbox_b"]);
    // woodbox_b has 2 views: both are context, none left for a target → null with a warning.
    assert!(g.entries[1].1.is_none());
    assert!(g.warnings.iter().any(|w| w.contains("woodbox_b")), "{:?}", g.warnings);
    let a = g.entries[0].1.as_ref().unwrap();
    let chunk = mvsplat360_dataset::torch_chunk::read_chunk(&chunk_dir().join("000000.torch")).unwrap();
    let centres = mvsplat360_dataset::index::chunk_centres(&chunk[0]);
    assert_eq!(a, &mvsplat360_dataset::index::index_entry(&centres, &o).unwrap());
    // The centres are the scene's camera centres.
    let scene = mvsplat360_dataset::read_scene_with(&chunk_dir().join("000000.torch"), Some("woodbox_a")).unwrap();
    for (c, cam) in centres.iter().zip(&scene.cameras) {
        let d = cam.center();
        assert!((c[0] - d.x).abs() < 1e-5 && (c[1] - d.y).abs() < 1e-5 && (c[2] - d.z).abs() < 1e-5);
    }
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("sub/index.json");
    eval::write_index(&p, &g).unwrap();
    let back = mvsplat360_dataset::read_evaluation_index(&p).unwrap();
    assert_eq!(back["woodbox_a"].as_ref(), Some(a));
    assert!(back["woodbox_b"].is_none());
}

/// With the metric networks (weights from `scripts/metric-weights/fetch`, located through
/// `$MVSPLAT360_METRIC_WEIGHTS` or the default folder; without them this test FAILS naming the file and the fetch
/// command): a folder scored without them is re-scored from its saved images — nothing re-rendered — and the
/// scores equal the networks applied to the PNGs; FID is over the whole image set (both scenes).
#[test]
fn eval_rescores_saved_images_with_metric_networks() {
    use mvsplat360_metrics::weights::{files, locate};
    for f in [files::VGG16, files::LPIPS_HEADS, files::DISTS, files::FID_INCEPTION] {
        if let Err(e) = locate(None, f) {
            panic!("{e}");
        }
    }
    let tmp = tempfile::tempdir().unwrap();
    let data = dataset(tmp.path());
    let index = tmp.path().join("index_eval.json");
    std::fs::write(&index, INDEX).unwrap();
    let cfg = model::tiny_config(false);
    let m = tmp.path().join("tiny-3dgs");
    model::write_model_dir(&m, &cfg, &model::random_state_dict(&cfg, 7).unwrap()).unwrap();
    let out = tmp.path().join("eval");
    let mut req = request(&data, &index, &m, &out);
    let s = eval::run(&req, &Silent).unwrap();
    assert_eq!(s.methods.len(), 1);
    assert_eq!(s.methods[0].0, Method::GSplat);
    assert!(s.methods[0].1.lpips.is_none() && s.methods[0].1.fid.is_none());
    assert!(!out.join("ImagesRefined0").exists());

    let images: Vec<PathBuf> = ["ImagesGT", "ImagesGSplat"].iter().flat_map(|d| std::fs::read_dir(out.join(d)).unwrap().flatten().map(|e| e.path())).collect();
    let stamp = |ps: &[PathBuf]| ps.iter().map(|p| std::fs::metadata(p).unwrap().modified().unwrap()).collect::<Vec<_>>();
    let before = stamp(&images);
    (req.lpips, req.dists, req.fid) = (true, true, true);
    let s = eval::run(&req, &Silent).unwrap();
    assert_eq!(s.rescored, ["woodbox_a", "woodbox_b"]);
    assert!(s.rendered.is_empty() && s.resumed.is_empty());
    assert_eq!(stamp(&images), before, "images were rewritten");
    let sc = &s.methods[0].1;
    let (lp, di, fid) = (sc.lpips.unwrap(), sc.dists.unwrap(), sc.fid.unwrap());

    // The same networks on the saved PNGs.
    let dev = candle_core::Device::Cpu;
    let names = ["woodbox_a_000001.png", "woodbox_a_000002.png", "woodbox_b_000000.png", "woodbox_b_000001.png"];
    let stack = |d: &str| {
        let v: Vec<candle_core::Tensor> = names
            .iter()
            .map(|n| {
                let im = mvsplat360_metrics::score::load_rgb(&out.join(d).join(n)).unwrap();
                candle_core::Tensor::from_vec(im.data, (3, im.height, im.width), &dev).unwrap()
            })
            .collect();
        candle_core::Tensor::stack(&v, 0).unwrap()
    };
    let (pred, gt) = (stack("ImagesGSplat"), stack("ImagesGT"));
    let lpips = mvsplat360_metrics::lpips::Lpips::load(None, mvsplat360_metrics::lpips::Net::Vgg, &dev).unwrap().distance(&pred, &gt).unwrap();
    let dists = mvsplat360_metrics::dists::Dists::load(None, &dev).unwrap().distance(&pred, &gt).unwrap();
    let mean = |v: &[f32]| v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
    assert!((lp - mean(&lpips)).abs() < 1e-5, "{lp} vs {lpips:?}");
    assert!((di - mean(&dists)).abs() < 1e-5, "{di} vs {dists:?}");
    let inc = mvsplat360_metrics::inception::FidInception::load(None, &dev).unwrap();
    let feats =
        |t: &candle_core::Tensor| inc.features(t).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap().into_iter().map(f64::from).collect::<Vec<_>>();
    let d = mvsplat360_metrics::inception::DIM;
    let expect = mvsplat360_metrics::frechet::frechet_from_features(&feats(&pred), 4, &feats(&gt), 4, d).unwrap();
    assert!((fid - expect).abs() <= 1e-6 * expect.abs().max(1.0), "FID {fid} vs {expect}");
    let md = std::fs::read_to_string(out.join("metrics.md")).unwrap();
    assert!(md.contains(&format!("| {lp:.3} | {di:.3} | {fid:.2} |")), "{md}");

    // Now complete: a third run does nothing.
    let s = eval::run(&req, &Silent).unwrap();
    assert_eq!(s.resumed.len(), 2);
    assert!(s.rescored.is_empty() && s.rendered.is_empty());
}

/// With a learned blender, `ImagesGSplat` holds the blended frames, and the table's row says so.
#[test]
fn table_names_blended_frames() {
    let sc = eval::MethodScores { folder: "ImagesGSplat".into(), images: 2, psnr: Some(20.0), ssim: None, lpips: None, dists: None, fid: None };
    let rows = [(Method::GSplat, sc.clone())];
    let scenes = [("a".to_string(), sc)];
    let plain = eval::markdown("x", &rows, &scenes, Method::GSplat, false);
    let blended = eval::markdown("x", &rows, &scenes, Method::GSplat, true);
    assert!(plain.contains("| 3DGS render | `ImagesGSplat` | 2 | 20.00 |"), "{plain}");
    assert!(blended.contains("| 3DGS render + learned blending | `ImagesGSplat` | 2 | 20.00 |"), "{blended}");
}
