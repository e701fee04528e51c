//! `mvsplat360 eval` and `mvsplat360 eval-index` as a user runs them: the official folders and tables on a
//! two-scene `.torch` dataset with a tiny random model, missing metric weights → nulls and warnings, a re-run that
//! resumes without rewriting anything, bad inputs rejected before any work; the generated index is the pipeline's.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::SystemTime;

mod common;
use common::{bin, eval_cmd, setup};

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

#[test]
fn eval_writes_official_folders_tables_and_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, m, index) = setup(tmp.path());
    let out = tmp.path().join("eval");
    let o = eval_cmd(&empty, &data, &index, &m, &out).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    // Missing metric weights: a warning naming the fetch command, the metric null, exit 0.
    for what in ["LPIPS", "DISTS", "FID"] {
        assert!(err.lines().any(|l| l.starts_with(&format!("warning: {what}")) && l.contains("scripts/metric-weights/fetch")), "{err}");
    }
    assert!(err.contains("rendered 2, resumed 0"), "{err}");
    let names = ["woodbox_a_000001.png", "woodbox_b_000000.png", "woodbox_b_000001.png"];
    for d in ["ImagesGT", "ImagesGSplat", "ImagesRefined0", "ImagesPostprocessed0V2"] {
        let mut found: Vec<String> = std::fs::read_dir(out.join(d)).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
        found.sort();
        assert_eq!(found, names, "{d}");
    }
    for f in ["scenes/woodbox_a.json", "scenes/woodbox_b.json", "eval.json", "metrics.json", "metrics.md"] {
        assert!(out.join(f).is_file(), "{f}");
    }
    let mj: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(mj["images"], 3);
    assert_eq!(mj["scenes"]["null_in_index"], 1);
    let r = &mj["methods"]["refined"];
    assert!(r["psnr"].is_number() && r["ssim"].is_number(), "{r}");
    assert!(r["lpips"].is_null() && r["dists"].is_null() && r["fid"].is_null(), "{r}");
    assert!(mj["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().starts_with("FID")));
    let md = std::fs::read_to_string(out.join("metrics.md")).unwrap();
    assert!(md.contains("| PSNR↑ | SSIM↑ | LPIPS↓ | DISTS↓ | FID↓ |") && md.contains("| woodbox_b | 2 |"), "{md}");

    // Re-run: both scenes resumed, no image or record rewritten.
    let before = mtimes(&out);
    let o = eval_cmd(&empty, &data, &index, &m, &out).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("rendered 0, resumed 2"), "{err}");
    assert_eq!(mtimes(&out), before);

    // Other settings into the same folder: refused, naming --out and the difference.
    let o = eval_cmd(&empty, &data, &index, &m, &out).args(["--seed", "3"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("--out") && err.contains("other settings") && err.contains("seed"), "{err}");
}

/// `--world-size 2`: two ranks render a scene each, the launcher merges; the same images and tables as one
/// process (one thread per process on both sides, so the float sums run in the same order).
#[test]
fn eval_on_two_ranks_gives_the_single_process_results() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, m, index) = setup(tmp.path());
    let (one, two) = (tmp.path().join("one"), tmp.path().join("two"));
    let o = eval_cmd(&empty, &data, &index, &m, &one).env("RAYON_NUM_THREADS", "1").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = eval_cmd(&empty, &data, &index, &m, &two).env("RAYON_NUM_THREADS", "1").args(["--world-size", "2"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    // Each rank rendered one scene; the launcher's pass found both complete.
    for r in 0..2 {
        assert!(err.contains(&format!("[rank {r}] rendered 1, resumed 0")), "{err}");
    }
    assert!(err.contains("rendered 0, resumed 2"), "{err}");
    let json = |d: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(d.join("metrics.json")).unwrap()).unwrap() };
    let (a, b) = (json(&one), json(&two));
    for k in ["methods", "per_scene", "images", "scenes", "settings"] {
        assert_eq!(a[k], b[k], "{k}");
    }
    for d in ["ImagesGT", "ImagesGSplat", "ImagesRefined0", "ImagesPostprocessed0V2"] {
        for e in std::fs::read_dir(one.join(d)).unwrap().flatten() {
            let other = two.join(d).join(e.file_name());
            assert_eq!(std::fs::read(e.path()).unwrap(), std::fs::read(&other).unwrap(), "{}", other.display());
        }
    }
}

/// Three processes started as `srun` starts them (its variables, no launcher of ours; the third a few seconds
/// later) on one --out: each scene rendered once, the last to finish writes the tables, which are those of one
/// process, as are the images; `eval --merge` rewrites the same table without rendering.
#[test]
fn eval_ranks_started_by_srun_share_one_out() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, m, index) = setup(tmp.path());
    let (one, three) = (tmp.path().join("one"), tmp.path().join("three"));
    let o = eval_cmd(&empty, &data, &index, &m, &one).env("RAYON_NUM_THREADS", "1").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let rank = |k: usize| {
        let mut c = eval_cmd(&empty, &data, &index, &m, &three);
        c.env("RAYON_NUM_THREADS", "1").env("SLURM_JOB_ID", "9").env("SLURM_STEP_ID", "0").env("SLURM_NTASKS", "3");
        c.env("SLURM_PROCID", k.to_string()).env("SLURM_LOCALID", k.to_string()).env("SLURM_NODEID", "0");
        c.stderr(std::process::Stdio::piped()).spawn().unwrap()
    };
    let (r0, r1) = (rank(0), rank(1));
    std::thread::sleep(std::time::Duration::from_secs(3));
    let r2 = rank(2);
    let mut err = String::new();
    for c in [r0, r1, r2] {
        let o = c.wait_with_output().unwrap();
        let e = String::from_utf8_lossy(&o.stderr).into_owned();
        assert!(o.status.success(), "{e}");
        err.push_str(&e);
    }
    // Two scenes, three ranks: each scene rendered once in all; one of the ranks wrote the tables.
    let rendered: usize = err.lines().filter_map(|l| l.split("] rendered ").nth(1)?.split(',').next()?.parse::<usize>().ok()).sum();
    assert_eq!(rendered, 2, "{err}");
    assert!(err.contains("via srun"), "{err}");
    assert!(err.contains("every scene is complete: wrote"), "{err}");
    let json = |d: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(d.join("metrics.json")).unwrap()).unwrap() };
    let (a, b) = (json(&one), json(&three));
    for k in ["methods", "per_scene", "images", "scenes", "settings"] {
        assert_eq!(a[k], b[k], "{k}");
    }
    for d in ["ImagesGT", "ImagesGSplat", "ImagesRefined0", "ImagesPostprocessed0V2"] {
        for e in std::fs::read_dir(one.join(d)).unwrap().flatten() {
            let other = three.join(d).join(e.file_name());
            assert_eq!(std::fs::read(e.path()).unwrap(), std::fs::read(&other).unwrap(), "{}", other.display());
        }
    }
    // --merge: the same table from the records, nothing rendered, whatever --dtype asks.
    std::fs::remove_file(three.join("metrics.json")).unwrap();
    let before = mtimes(&three);
    let o = eval_cmd(&empty, &data, &index, &m, &three).args(["--merge", "--dtype", "bf16"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(json(&three)["methods"], a["methods"]);
    assert_eq!(mtimes(&three), before, "--merge rewrote scene files");
    // Records of a bf16 run (edited, to keep the test short): a merge takes them, and the table says bf16.
    let settings = three.join("eval.json");
    let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&settings).unwrap()).unwrap();
    v["refiner_dtype"] = "bf16".into();
    std::fs::write(&settings, serde_json::to_string(&v).unwrap()).unwrap();
    let set = |scene: &str, key: &str, dtype: &str| {
        let p = three.join("scenes").join(format!("{scene}.json"));
        let mut r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        assert!(r["rendered_by"]["pid"].as_u64().is_some(), "the record names its process: {r}");
        assert_eq!(r["rendered_by"]["encoder_dtype"], "f32", "the record names the encoder's precision: {r}");
        r["rendered_by"][key] = dtype.into();
        std::fs::write(&p, serde_json::to_string(&r).unwrap()).unwrap();
    };
    let set_dtype = |scene: &str, dtype: &str| set(scene, "refiner_dtype", dtype);
    set_dtype("woodbox_a", "bf16");
    set_dtype("woodbox_b", "bf16");
    let o = eval_cmd(&empty, &data, &index, &m, &three).arg("--merge").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(json(&three)["settings"]["refiner_dtype"], "bf16");
    assert_eq!(json(&three)["methods"], a["methods"]);
    // One record of another precision: the merge refuses, naming it.
    set_dtype("woodbox_b", "f16");
    let o = eval_cmd(&empty, &data, &index, &m, &three).arg("--merge").output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("woodbox_b (refiner f16") && !e.contains("woodbox_a ("), "{e}");
    // A record whose encoder ran in another precision is refused too.
    set_dtype("woodbox_b", "bf16");
    set("woodbox_a", "encoder_dtype", "bf16");
    let o = eval_cmd(&empty, &data, &index, &m, &three).arg("--merge").output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("woodbox_a (refiner bf16, encoder bf16)") && !e.contains("woodbox_b ("), "{e}");
    // --merge on an out with a scene missing names it and writes nothing.
    let part = tmp.path().join("part");
    let o = eval_cmd(&empty, &data, &index, &m, &part).args(["--scenes", "woodbox_a"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    std::fs::remove_file(part.join("metrics.json")).unwrap();
    let o = eval_cmd(&empty, &data, &index, &m, &part).arg("--merge").output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("woodbox_b") && e.contains("no complete record"), "{e}");
    assert!(!part.join("metrics.json").exists());
}

/// Two processes started as `mpirun` starts them (`OMPI_COMM_WORLD_*`, no MASTER_ADDR/MASTER_PORT: evaluation
/// needs no rendezvous) on one --out: both run, each scene rendered once, the tables written.
#[test]
fn eval_ranks_started_by_mpirun_need_no_rendezvous_address() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, m, index) = setup(tmp.path());
    let out = tmp.path().join("out");
    let rank = |k: usize| {
        let mut c = eval_cmd(&empty, &data, &index, &m, &out);
        c.env("RAYON_NUM_THREADS", "1").env_remove("MASTER_ADDR").env_remove("MASTER_PORT");
        c.env("OMPI_COMM_WORLD_RANK", k.to_string()).env("OMPI_COMM_WORLD_SIZE", "2").env("OMPI_COMM_WORLD_LOCAL_RANK", k.to_string());
        c.env("OMPI_COMM_WORLD_LOCAL_SIZE", "2").stderr(std::process::Stdio::piped()).spawn().unwrap()
    };
    let (r0, r1) = (rank(0), rank(1));
    let mut err = String::new();
    for c in [r0, r1] {
        let o = c.wait_with_output().unwrap();
        let e = String::from_utf8_lossy(&o.stderr).into_owned();
        assert!(o.status.success(), "{e}");
        err.push_str(&e);
    }
    assert!(err.contains("via mpirun"), "{err}");
    let rendered: usize = err.lines().filter_map(|l| l.split("] rendered ").nth(1)?.split(',').next()?.parse::<usize>().ok()).sum();
    assert_eq!(rendered, 2, "{err}");
    assert!(out.join("metrics.json").is_file());
}

fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut v = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            v.extend(files_under(&p));
        } else {
            v.push(p);
        }
    }
    v
}

/// A corrupt chunk holding one scene of the index: the others are scored and the tables written, the failure is
/// recorded and named, the exit code is non-zero; a rerun with `--exclude` it resumes the others and exits 0.
#[test]
fn eval_goes_on_past_a_corrupt_scene() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, m, _) = setup(tmp.path());
    std::fs::write(data.join("000001.torch"), b"PK\x03\x04 not a torch archive").unwrap();
    std::fs::write(data.join("index.json"), r#"{"woodbox_a": "000000.torch", "broken": "000001.torch", "woodbox_b": "000000.torch"}"#).unwrap();
    let index = tmp.path().join("index3.json");
    std::fs::write(
        &index,
        r#"{"woodbox_a": {"context": [0, 2], "target": [0, 1, 2]}, "broken": {"context": [0, 1], "target": [1]}, "woodbox_b": {"context": [0, 1], "target": [0, 1]}}"#,
    )
    .unwrap();
    let out = tmp.path().join("out");
    let o = eval_cmd(&empty, &data, &index, &m, &out).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(err.contains("1 scene(s) could not be evaluated") && err.contains("broken: ") && err.contains("--exclude broken"), "{err}");
    assert!(err.contains("000001.torch"), "the error names the file: {err}");
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(v["scenes"]["evaluated"], 2);
    assert_eq!(v["scenes"]["failed"][0]["scene"], "broken");
    assert!(v["scenes"]["failed"][0]["error"].as_str().unwrap().contains("000001.torch"));
    assert!(out.join("scenes/broken.error.json").is_file());
    let o = eval_cmd(&empty, &data, &index, &m, &out).args(["--exclude", "broken"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("rendered 0, resumed 2"), "{err}");
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(v["scenes"]["excluded"][0], "broken");
    assert_eq!(v["scenes"]["failed"].as_array().unwrap().len(), 0);
}

/// A process killed (SIGKILL) while it renders a scene: the next process on the same --out takes the dead
/// owner's lease over at once, finishes every scene with the single-process results, and leaves no temporary
/// file behind (the dead process's included).
#[test]
fn a_killed_process_scene_is_taken_over_at_once() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, m, index) = setup(tmp.path());
    let (one, out) = (tmp.path().join("one"), tmp.path().join("out"));
    let o = eval_cmd(&empty, &data, &index, &m, &one).env("RAYON_NUM_THREADS", "1").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut a = eval_cmd(&empty, &data, &index, &m, &out).env("RAYON_NUM_THREADS", "1").stderr(std::process::Stdio::null()).spawn().unwrap();
    let t = std::time::Instant::now();
    let leased = || out.join("scenes").is_dir() && files_under(&out.join("scenes")).iter().any(|p| p.to_string_lossy().contains(".lease-"));
    while !leased() {
        assert!(a.try_wait().unwrap().is_none(), "the first process ended before it took a scene");
        assert!(t.elapsed().as_secs() < 50, "no lease after 50 s");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    a.kill().unwrap();
    a.wait().unwrap();
    let o = eval_cmd(&empty, &data, &index, &m, &out).env("RAYON_NUM_THREADS", "1").output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(!err.contains("waiting for it"), "it waited for the dead process: {err}");
    let left: Vec<PathBuf> =
        files_under(&out).into_iter().filter(|p| p.to_string_lossy().ends_with(".partial") || p.to_string_lossy().contains(".lease-")).collect();
    assert!(left.is_empty(), "{left:?}");
    let json = |d: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(d.join("metrics.json")).unwrap()).unwrap() };
    assert_eq!(json(&one)["methods"], json(&out)["methods"]);
    assert_eq!(json(&one)["per_scene"], json(&out)["per_scene"]);
}

fn signal(child: &std::process::Child, sig: &str) {
    assert!(Command::new("kill").args([sig, &child.id().to_string()]).status().unwrap().success());
}

/// A process frozen (SIGSTOP: its heartbeat stops too) while it renders a scene: another process waits for it
/// only as long as `--lease-stale`, takes the scene over and finishes the run; the frozen one, once thawed, finds
/// its lease gone and writes nothing for the scene.
#[test]
fn a_frozen_process_loses_its_scene_and_writes_nothing_for_it() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, m, index) = setup(tmp.path());
    let (one, out) = (tmp.path().join("one"), tmp.path().join("out"));
    let o = eval_cmd(&empty, &data, &index, &m, &one).env("RAYON_NUM_THREADS", "1").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let run = || {
        let mut c = eval_cmd(&empty, &data, &index, &m, &out);
        c.args(["--lease-stale", "2"]).env("RAYON_NUM_THREADS", "1");
        c
    };
    let mut a = run().stderr(std::process::Stdio::piped()).spawn().unwrap();
    let leases = || -> Vec<String> {
        let names = if out.join("scenes").is_dir() { files_under(&out.join("scenes")) } else { Vec::new() };
        names.iter().filter_map(|p| Some(p.file_name()?.to_str()?.split_once(".lease-")?.0.to_string())).collect()
    };
    let t = std::time::Instant::now();
    let key = loop {
        assert!(a.try_wait().unwrap().is_none(), "the first process ended before it was frozen holding a scene");
        assert!(t.elapsed().as_secs() < 120, "no lease after 120 s");
        if !leases().is_empty() {
            signal(&a, "-STOP");
            // Still holding it once frozen (else it finished that scene meanwhile: try the next).
            if let Some(k) = leases().pop() {
                break k;
            }
            signal(&a, "-CONT");
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    };
    let o = run().output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains(&format!("scene {key}: being rendered by pid {}", a.id())), "{err}");
    assert!(err.contains(&format!("scene {key} (")), "the second process did not render the frozen one's scene: {err}");
    let json = |d: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(d.join("metrics.json")).unwrap()).unwrap() };
    assert_eq!(json(&one)["per_scene"], json(&out)["per_scene"]);
    let before = mtimes(&out);
    signal(&a, "-CONT");
    let o = a.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains(&format!("scene {key}: another process took it over")), "{err}");
    assert_eq!(mtimes(&out), before, "the thawed process wrote files");
    assert_eq!(json(&one)["methods"], json(&out)["methods"]);
    let left: Vec<PathBuf> =
        files_under(&out).into_iter().filter(|p| p.to_string_lossy().ends_with(".partial") || p.to_string_lossy().contains(".lease-")).collect();
    assert!(left.is_empty(), "{left:?}");
}

#[test]
fn eval_bad_inputs_fail_before_any_work() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, m, index) = setup(tmp.path());
    let out = tmp.path().join("eval");
    let cases: Vec<(Command, &str)> = vec![
        (eval_cmd(&empty, &tmp.path().join("nope"), &index, &m, &out), "--data"),
        (eval_cmd(&empty, &data, &tmp.path().join("nope.json"), &m, &out), "nope.json"),
        (
            {
                let mut c = eval_cmd(&empty, &data, &index, &m, &out);
                c.args(["--scenes", "woodbox_z"]);
                c
            },
            "--scenes",
        ),
        (
            {
                let mut c = eval_cmd(&empty, &data, &index, &m, &out);
                c.args(["--vae-chunk", "0"]);
                c
            },
            "--vae-chunk",
        ),
    ];
    for (mut c, what) in cases {
        let o = c.output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{what}: {err}");
        assert!(err.contains(what), "{what}: {err}");
        assert!(!out.exists(), "{what}: wrote {}", out.display());
    }
}

#[test]
fn eval_index_matches_the_pipeline_generator() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, empty, _, _) = setup(tmp.path());
    let out = tmp.path().join("idx/ctx2.json");
    let o = bin(&empty).args(["eval-index", "--num-context", "2", "--num-target", "1", "--data"]).arg(&data).arg("--out").arg(&out).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    // woodbox_b has only its 2 context views: null, with a warning.
    assert!(err.lines().any(|l| l.starts_with("warning: scene woodbox_b")), "{err}");
    assert!(err.contains("wrote 2 scenes (1 null) from 1 chunks"), "{err}");
    let opts = mvsplat360_dataset::index::IndexOptions { num_context: 2, num_target: 1, view_selection_ratio: 1.0 };
    let g = mvsplat360_pipeline::eval::generate_index(&data, &opts, &mvsplat360_pipeline::render::Silent).unwrap();
    assert_eq!(std::fs::read_to_string(&out).unwrap(), mvsplat360_dataset::index::index_json(&g.entries));
    let idx = mvsplat360_dataset::read_evaluation_index(&out).unwrap();
    let a = idx["woodbox_a"].as_ref().unwrap();
    assert_eq!((a.context.len(), a.target.len()), (2, 1));
    assert!(idx["woodbox_b"].is_none());

    // --n and --view-selection-ratio are the same setting; an empty folder names --data.
    let o = bin(&empty).args(["eval-index", "--n", "150", "--view-selection-ratio", "0.5", "--data"]).arg(&data).arg("--out").arg(&out).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
    let o = bin(&empty).args(["eval-index", "--data"]).arg(&empty).arg("--out").arg(tmp.path().join("x.json")).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("--data") && err.contains("no .torch chunks"), "{err}");
    assert!(!tmp.path().join("x.json").exists());
}
