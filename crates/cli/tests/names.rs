//! Weights and data by name in the commands (issue 71): `hf:` addresses, short names and same-spelled local paths
//! in `render`, `export`, `eval` and `train`'s inits, fetched from a Hub stand-in on 127.0.0.1 (`HF_ENDPOINT`) into
//! a temporary Hugging Face cache; `eval --data` on a zip of `.torch` chunks without `--index` takes the index
//! `eval-index` makes; `weights list` / `weights get`.

#[allow(dead_code)]
mod common;
#[path = "../../train/tests/common/mod.rs"]
mod train_common;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use mvsplat360_testkit::hub_standin::{StandIn, COMMIT};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The binary against the stand-in: its own Hugging Face cache and project cache under `tmp`, no token, online.
fn bin(s: &StandIn, tmp: &Path) -> Command {
    let empty = tmp.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let mut c = common::bin(&empty);
    c.env("HF_ENDPOINT", &s.endpoint).env("HF_HUB_CACHE", tmp.join("hf")).env("MVSPLAT360_CACHE", tmp.join("cache"));
    for k in ["HF_TOKEN", "HUGGING_FACE_HUB_TOKEN", "HF_TOKEN_PATH", "HF_HOME", "HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"] {
        c.env_remove(k);
    }
    c
}

fn ok(o: &Output) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "{err}");
    err
}

/// A tiny model folder (no refiner: 3DGS only, fast) at `dir`.
fn tiny_model(dir: &Path, seed: u64) -> PathBuf {
    let cfg = mvsplat360_pipeline::model::tiny_config(false);
    let sd = mvsplat360_pipeline::model::random_state_dict(&cfg, seed).unwrap();
    mvsplat360_pipeline::model::write_model_dir(dir, &cfg, &sd).unwrap();
    dir.to_path_buf()
}

/// Serves a model folder's files as the repository `repo` (weights as LFS files, config as a small one).
fn serve_folder(s: &StandIn, repo: &str, dir: &Path) {
    let files: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .filter(|e| e.path().is_file())
        .map(|e| (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap()))
        .collect();
    let list: Vec<(&str, &[u8], bool)> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice(), !n.ends_with(".json"))).collect();
    s.add(repo, &list);
}

fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap().flatten() {
        std::fs::copy(e.path(), dst.join(e.file_name())).unwrap();
    }
}

fn requests_for(s: &StandIn, repo: &str) -> usize {
    s.log().iter().filter(|r| r.path.contains(repo)).count()
}

#[test]
fn render_takes_an_hf_name_a_short_name_and_a_same_spelled_folder() {
    let s = StandIn::start();
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(&tmp.path().join("tiny"), 5);
    serve_folder(&s, "owner/tiny", &m);
    let render = |ckpt: &str, cwd: &Path, out: &Path| {
        let mut c = bin(&s, tmp.path());
        c.current_dir(cwd).arg("render").arg(root().join("assets/woodbox")).args(["--ckpt", ckpt]);
        c.args(["--context", "0,6,12", "--targets", "3,9", "--no-video", "--no-metrics", "--out"]).arg(out);
        c.output().unwrap()
    };

    // hf:OWNER/REPO = the repository as a model folder, in the Python cache layout.
    let a = tmp.path().join("a");
    let err = ok(&render("hf:owner/tiny", tmp.path(), &a));
    let snap = tmp.path().join(format!("hf/models--owner--tiny/snapshots/{COMMIT}"));
    assert!(snap.join("config.json").is_file() && snap.join("model.safetensors").is_file());
    assert!(err.contains(&format!("--ckpt hf:owner/tiny: {}", snap.display())), "{err}");

    // A folder literally named `hf:owner/tiny` in the working directory wins: no request.
    let spelled = tmp.path().join("spelled");
    copy_dir(&m, &spelled.join("hf:owner/tiny"));
    s.clear_log();
    let b = tmp.path().join("b");
    ok(&render("hf:owner/tiny", &spelled, &b));
    assert!(s.log().is_empty(), "{:?}", s.log());
    for f in ["frames/gsplat/0000.png", "frames/gsplat/0001.png"] {
        assert_eq!(std::fs::read(a.join(f)).unwrap(), std::fs::read(b.join(f)).unwrap(), "{f}");
    }

    // `default`: the shipped model, nothing fetched.
    let d = tmp.path().join("d");
    let err = ok(&render("default", tmp.path(), &d));
    assert!(err.contains("--ckpt default: ") && err.contains("assets/models/default"), "{err}");
    assert!(s.log().is_empty(), "{:?}", s.log());
    assert!(d.join("frames/gsplat/0001.png").is_file());

    // The Hub's answers surface with their message and exit 1, before any work.
    let o = render("hf:owner/absent", tmp.path(), &tmp.path().join("e"));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("--ckpt hf:owner/absent") && err.contains("owner/absent"), "{err}");
    let o = render("no-such-name", tmp.path(), &tmp.path().join("e"));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("neither an existing file or folder nor a name") && err.contains("dl3dv"), "{err}");
    // A missing file spelled as a path keeps the command's own message.
    let o = render("weights/absent.ckpt", tmp.path(), &tmp.path().join("e"));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("weights/absent.ckpt: no such file or folder") && !err.contains("nor a name"), "{err}");
}

#[test]
fn export_takes_names_and_a_local_folder_named_default_wins() {
    let s = StandIn::start();
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(&tmp.path().join("tiny"), 6);
    serve_folder(&s, "owner/tiny", &m);
    let export = |ckpt: &Path, cwd: &Path, ply: &Path| {
        let mut c = bin(&s, tmp.path());
        c.current_dir(cwd).args(["export", "--num-context", "3", "--ckpt"]).arg(ckpt).arg(root().join("assets/woodbox")).arg("--out").arg(ply);
        c.output().unwrap()
    };
    let by_path = tmp.path().join("path.ply");
    ok(&export(&m, tmp.path(), &by_path));
    let by_name = tmp.path().join("name.ply");
    ok(&export(Path::new("hf:owner/tiny"), tmp.path(), &by_name));
    assert_eq!(std::fs::read(&by_path).unwrap(), std::fs::read(&by_name).unwrap());

    // `default` names the shipped model, unless the working directory has a `default` of its own.
    let cwd = tmp.path().join("cwd");
    copy_dir(&m, &cwd.join("default"));
    s.clear_log();
    let local = tmp.path().join("local.ply");
    ok(&export(Path::new("default"), &cwd, &local));
    assert_eq!(std::fs::read(&by_path).unwrap(), std::fs::read(&local).unwrap());
    let shipped = tmp.path().join("shipped.ply");
    let err = ok(&export(Path::new("default"), tmp.path(), &shipped));
    assert!(err.contains("assets/models/default"), "{err}");
    assert_ne!(std::fs::read(&by_path).unwrap(), std::fs::read(&shipped).unwrap());
    assert!(s.log().is_empty(), "{:?}", s.log());
}

fn make_zip(path: &Path, entries: &[(&str, &Path)]) {
    let mut w = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    let opt = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (name, src) in entries {
        w.start_file(*name, opt).unwrap();
        w.write_all(&std::fs::read(src).unwrap()).unwrap();
    }
    w.finish().unwrap();
}

#[test]
fn eval_takes_data_by_name_or_zip_and_makes_the_index_as_eval_index_does() {
    let s = StandIn::start();
    let tmp = tempfile::tempdir().unwrap();
    let (_, empty, _, index) = common::setup(tmp.path());
    let m = tiny_model(&tmp.path().join("tiny3dgs"), 7);
    serve_folder(&s, "owner/tiny", &m);
    // The chunks under one top-level folder with a test split, as a dataset zip may hold them.
    let zip = tmp.path().join("dl3dv_tiny.zip");
    let chunks = common::chunk_dir();
    make_zip(&zip, &[("dl3dv_tiny/test/000000.torch", &chunks.join("000000.torch")), ("dl3dv_tiny/test/index.json", &chunks.join("index.json"))]);
    let zip_bytes = std::fs::read(&zip).unwrap();
    s.add("donydchen/mvsplat360", &[("dl3dv_tiny.zip", &zip_bytes, true)]);
    let eval = |data: &str, index: Option<&Path>, ckpt: &str, cwd: &Path, out: &Path| {
        let mut c = bin(&s, tmp.path());
        c.current_dir(cwd).args(["eval", "--data", data, "--ckpt", ckpt, "--steps", "1", "--window", "3", "--weights-dir"]).arg(&empty);
        if let Some(i) = index {
            c.arg("--index").arg(i);
        }
        c.arg("--out").arg(out).output().unwrap()
    };

    // A short name for the data, an hf: name for the model, no --index.
    let out1 = tmp.path().join("e1");
    let err = ok(&eval("dl3dv-tiny", None, "hf:owner/tiny", tmp.path(), &out1));
    let sha = mvsplat360_testkit::hub_standin::sha256_hex(&zip_bytes);
    let unpacked = tmp.path().join("cache/data").join(&sha).join("dl3dv_tiny/test");
    assert!(unpacked.join("000000.torch").is_file(), "{err}");
    assert!(err.contains("the test split"), "{err}");
    let made = unpacked.join("dl3dv_ctx_5v_tgt_56v.json");
    let by_eval_index = tmp.path().join("eval-index.json");
    ok(&bin(&s, tmp.path()).args(["eval-index", "--data"]).arg(&unpacked).arg("--out").arg(&by_eval_index).output().unwrap());
    assert_eq!(std::fs::read_to_string(&made).unwrap(), std::fs::read_to_string(&by_eval_index).unwrap());
    let mj: serde_json::Value = serde_json::from_slice(&std::fs::read(out1.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(mj["index"], made.display().to_string());
    // The tiny scenes have 3 and 2 views: the official 5 + 56 views make both null (as eval-index writes them).
    assert_eq!(mj["scenes"]["null_in_index"], 2, "{mj}");

    // The same zip given as a local file: the same folder (unpacked once), with an index given; the model by a
    // same-spelled local folder (no request for it).
    let cwd = tmp.path().join("cwd");
    copy_dir(&m, &cwd.join("hf:owner/tiny"));
    s.clear_log();
    let out2 = tmp.path().join("e2");
    ok(&eval(zip.to_str().unwrap(), Some(&index), "hf:owner/tiny", &cwd, &out2));
    assert!(s.log().is_empty(), "{:?}", s.log());
    let mj: serde_json::Value = serde_json::from_slice(&std::fs::read(out2.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(mj["data"], unpacked.display().to_string());
    assert_eq!(mj["scenes"]["evaluated"], 2, "{mj}");
    assert_eq!(std::fs::read_dir(tmp.path().join("cache/data")).unwrap().count(), 1, "unpacked once");

    // Ranks this command starts take the cached zip without asking the Hub again.
    s.clear_log();
    let mut c = bin(&s, tmp.path());
    c.args(["eval", "--data", "dl3dv-tiny", "--ckpt", "hf:owner/tiny", "--steps", "1", "--window", "3", "--world-size", "2", "--weights-dir"]);
    let out4 = tmp.path().join("e4");
    ok(&c.arg(&empty).arg("--index").arg(&index).arg("--out").arg(&out4).env("RAYON_NUM_THREADS", "1").output().unwrap());
    let zip_heads = s.log().iter().filter(|r| r.method == "HEAD" && r.path.ends_with("dl3dv_tiny.zip")).count();
    assert_eq!(zip_heads, 1, "{:?}", s.log());
    let mj: serde_json::Value = serde_json::from_slice(&std::fs::read(out4.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(mj["scenes"]["evaluated"], 2, "{mj}");

    // An hf: file name for the data; without --index the index made before is found beside the chunks.
    let out3 = tmp.path().join("e3");
    let err = ok(&eval("hf:donydchen/mvsplat360/dl3dv_tiny.zip", None, "hf:owner/tiny", tmp.path(), &out3));
    assert!(err.contains("found"), "{err}");
}

#[test]
fn train_inits_take_names() {
    let s = StandIn::start();
    let tmp = tempfile::tempdir().unwrap();
    let cfg_file = |name: &str, out: &Path, extra: &str| {
        let mut c = train_common::with_refiner(out, 1, "");
        c.train.accumulate = 1;
        let text = c.to_toml().replacen("[train]\n", &format!("[train]\n{extra}"), 1);
        let p = tmp.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let train = |cfg: &Path, cwd: &Path, token: Option<&str>| {
        let mut c = bin(&s, tmp.path());
        c.current_dir(cwd).args(["train", "--config"]).arg(cfg);
        if let Some(t) = token {
            c.env("HF_TOKEN", t);
        }
        c.output().unwrap()
    };
    // A first run gives a model folder for `init` and the refiner's random initial weights, served as the gated
    // `svd` (keys without `refiner.`, as Stability's file).
    let first = tmp.path().join("first");
    ok(&train(&cfg_file("first.toml", &first, ""), tmp.path(), None));
    serve_folder(&s, "owner/trained", &first.join("model"));
    let init = candle_core::safetensors::load(first.join(mvsplat360_train::refiner::RANDOM_INIT), &candle_core::Device::Cpu).unwrap();
    let svd: std::collections::HashMap<String, candle_core::Tensor> =
        init.iter().map(|(k, t)| (k.strip_prefix("refiner.").unwrap().to_string(), t.clone())).collect();
    let svd_file = tmp.path().join("svd.safetensors");
    candle_core::safetensors::save(&svd, &svd_file).unwrap();
    s.add_repo(
        "stabilityai/stable-video-diffusion-img2vid",
        mvsplat360_testkit::hub_standin::Repo {
            commit: COMMIT.into(),
            files: vec![("svd.safetensors".into(), mvsplat360_testkit::hub_standin::File { content: std::fs::read(&svd_file).unwrap(), lfs: true })],
            gated: Some(vec!["tok".into()]),
            ..Default::default()
        },
    );

    // Gated without a token: the message, exit 1, nothing trained.
    let second = tmp.path().join("second");
    let cfg = cfg_file("second.toml", &second, "init = \"hf:owner/trained\"\nrefiner_init = \"svd\"\n");
    let o = train(&cfg, tmp.path(), None);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("train.refiner_init svd") && err.contains("HF_TOKEN"), "{err}");
    assert!(!second.join("log.jsonl").exists());

    // With a token: both fetched; the run starts from them.
    let err = ok(&train(&cfg, tmp.path(), Some("tok")));
    assert!(err.contains("train.init hf:owner/trained: ") && err.contains("train.refiner_init svd: "), "{err}");
    let got = candle_core::safetensors::load(second.join("model-step0/model.safetensors"), &candle_core::Device::Cpu).unwrap();
    let want = candle_core::safetensors::load(first.join("model/model.safetensors"), &candle_core::Device::Cpu).unwrap();
    let same = |k: &str| (&got[k] - &want[k]).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap() == 0.0;
    let enc: Vec<&String> = want.keys().filter(|k| k.starts_with("encoder.")).collect();
    assert!(!enc.is_empty() && enc.iter().all(|k| same(k)), "the encoder starts from init");
    assert!(!second.join(mvsplat360_train::refiner::RANDOM_INIT).exists(), "the refiner starts from refiner_init");

    // A same-spelled local folder for `init`: no request for that repository.
    let cwd = tmp.path().join("cwd");
    copy_dir(&first.join("model"), &cwd.join("hf:owner/trained"));
    s.clear_log();
    let third = tmp.path().join("third");
    ok(&train(&cfg_file("third.toml", &third, "init = \"hf:owner/trained\"\nrefiner_init = \"svd\"\n"), &cwd, Some("tok")));
    assert_eq!(requests_for(&s, "owner/trained"), 0, "{:?}", s.log());
}

#[test]
fn weights_list_and_get() {
    let s = StandIn::start();
    let tmp = tempfile::tempdir().unwrap();
    s.add("facebook/VGGT-1B", &[("model.pt", b"not really vggt", true)]);
    let list = |tmp: &Path| {
        let o = bin(&s, tmp).args(["weights", "list", "--json"]).output().unwrap();
        ok(&o);
        let rows: Vec<serde_json::Value> = String::from_utf8_lossy(&o.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        rows
    };
    let rows = list(tmp.path());
    let names: Vec<&str> = rows.iter().map(|r| r["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["default", "dl3dv", "dl3dv-tiny", "vggt-1b", "vggt-1b-commercial", "svd"]);
    let vggt = rows.iter().find(|r| r["name"] == "vggt-1b").unwrap();
    assert_eq!(vggt["address"], "hf:facebook/VGGT-1B/model.pt");
    assert!(vggt["cached"].is_null() && vggt["licence"].as_str().unwrap().contains("CC BY-NC"));
    assert!(s.log().is_empty(), "list asks the Hub nothing");

    let o = bin(&s, tmp.path()).args(["weights", "get", "vggt-1b"]).output().unwrap();
    ok(&o);
    let p = PathBuf::from(String::from_utf8_lossy(&o.stdout).trim());
    assert_eq!(std::fs::read(&p).unwrap(), b"not really vggt");
    let vggt = list(tmp.path()).into_iter().find(|r| r["name"] == "vggt-1b").unwrap();
    assert_eq!(vggt["cached"], p.display().to_string());
    assert_eq!(vggt["size"], 15);
    let text = bin(&s, tmp.path()).args(["weights", "list"]).output().unwrap();
    let text = String::from_utf8_lossy(&text.stdout);
    assert!(text.contains("vggt-1b") && text.contains("cached, 15 B") && text.contains("not cached"), "{text}");

    // Offline: the cached file without a request; a name not cached fails with the message, before any work.
    s.clear_log();
    let o = bin(&s, tmp.path()).env("HF_HUB_OFFLINE", "1").args(["weights", "get", "vggt-1b"]).output().unwrap();
    ok(&o);
    assert!(s.log().is_empty(), "{:?}", s.log());
    let o = bin(&s, tmp.path())
        .env("HF_HUB_OFFLINE", "1")
        .args(["export", "--ckpt", "dl3dv", "--out"])
        .arg(tmp.path().join("x.ply"))
        .arg(root().join("assets/woodbox"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("--ckpt dl3dv") && err.contains("HF_HUB_OFFLINE") && err.contains("dl3dv_480p.ckpt"), "{err}");
    assert!(s.log().is_empty() && !tmp.path().join("x.ply").exists());

    let o = bin(&s, tmp.path()).args(["weights", "get", "vggt-1b-commercial"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("vggt-1b-commercial"), "{err}");
}
