//! What the `eval` tests share: the binary with no metric weights in reach, a two-scene `.torch` dataset with a
//! tiny random model and an evaluation index, and the `eval` command on them.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The binary with every metric-weights location pointed at `empty` (a developer's cached weights are not found).
pub fn bin(empty: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_mvsplat360"));
    c.env("MVSPLAT360_METRIC_WEIGHTS", empty).env("XDG_CACHE_HOME", empty).env("HOME", empty);
    c
}

pub fn chunk_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../crates/dataset/tests/data/chunk")
}

/// tmp/{data (chunk + index.json), empty, tiny (model), index.json (evaluation index)}.
pub fn setup(tmp: &Path) -> (PathBuf, PathBuf, PathBuf, PathBuf) {
    let data = tmp.join("data");
    let empty = tmp.join("empty");
    std::fs::create_dir_all(&data).unwrap();
    std::fs::create_dir_all(&empty).unwrap();
    for f in ["000000.torch", "index.json"] {
        std::fs::copy(chunk_dir().join(f), data.join(f)).unwrap();
    }
    let cfg = mvsplat360_pipeline::model::tiny_config(true);
    let sd = mvsplat360_pipeline::model::random_state_dict(&cfg, 11).unwrap();
    let m = tmp.join("tiny");
    mvsplat360_pipeline::model::write_model_dir(&m, &cfg, &sd).unwrap();
    let index = tmp.join("index.json");
    std::fs::write(
        &index,
        r#"{"woodbox_a": {"context": [0, 2], "target": [0, 1, 2], "target_quantify": [1]}, "woodbox_b": {"context": [0, 1], "target": [0, 1]}, "gone": null}"#,
    )
    .unwrap();
    (data, empty, m, index)
}

pub fn eval_cmd(empty: &Path, data: &Path, index: &Path, m: &Path, out: &Path) -> Command {
    let mut c = bin(empty);
    c.arg("eval").arg("--data").arg(data).arg("--index").arg(index).arg("--ckpt").arg(m);
    c.args(["--steps", "1", "--window", "3", "--weights-dir"]).arg(empty).arg("--out").arg(out);
    c
}
