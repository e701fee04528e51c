//! The project's scripts that CI can check without their heavy dependencies: `scripts/slurm/eval.sbatch` and
//! `train.sbatch` parse (`bash -n`) and, run as `sbatch` would run them with `srun` and `scontrol` replaced by
//! shims, start one `mvsplat360 eval` (`train`) per task with srun's variables, the rendezvous address of the job's first node and a port
//! derived from the job id, and refuses outside a job; the fixture scripts' stand-in modules answer
//! `importlib.util.find_spec` (no torch needed).

use std::path::Path;
use std::process::Command;

const EVAL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scripts/slurm/eval.sbatch");
const TRAIN: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scripts/slurm/train.sbatch");

/// Written by a child `sh`, not by this process: a write descriptor held here could leak into a process that
/// another test thread forks at that moment, and executing the file would then fail with ETXTBSY.
fn write_exe(path: &Path, text: &str) {
    use std::io::Write;
    let mut c = Command::new("sh").args(["-c", r#"cat > "$1" && chmod +x "$1""#, "sh"]).arg(path).stdin(std::process::Stdio::piped()).spawn().unwrap();
    c.stdin.take().unwrap().write_all(text.as_bytes()).unwrap();
    assert!(c.wait().unwrap().success());
}

/// Runs `script` as sbatch would in job 4242 on nodes gpu-a[01-02] with 3 tasks, `srun` and `scontrol` shimmed and
/// `mvsplat360` a stand-in that logs its rank, rendezvous and arguments: the log's lines, sorted (3 ranks, then
/// srun's own line). Also checks `bash -n` and the refusal outside a job.
fn run_sbatch(script: &str, env: &[(&str, &str)]) -> Vec<String> {
    assert!(Command::new("bash").args(["-n", script]).status().unwrap().success());
    let d = tempfile::tempdir().unwrap();
    let bin = d.path().join("bin");
    std::fs::create_dir(&bin).unwrap();
    let log = d.path().join("ranks.log");
    write_exe(&bin.join("scontrol"), "#!/bin/bash\n[[ \"$1 $2 $3\" == \"show hostnames gpu-a[01-02]\" ]] || exit 3\nprintf 'gpu-a01\\ngpu-a02\\n'\n");
    // srun: one process per task with the variables of a job step (all on this machine).
    write_exe(
        &bin.join("srun"),
        &format!(
            "#!/bin/bash\necho \"srun $*\" >> {log}\n[[ $1 == --kill-on-bad-exit=1 ]] || exit 4\nshift\nfor ((t = 0; t < SLURM_NTASKS; t++)); do\n  \
             SLURM_STEP_ID=0 SLURM_PROCID=$t SLURM_LOCALID=$t SLURM_NODEID=0 \"$@\" &\ndone\nwait\n",
            log = log.display()
        ),
    );
    let fake = d.path().join("mvsplat360");
    write_exe(&fake, &format!("#!/bin/bash\necho \"rank $SLURM_PROCID step $SLURM_STEP_ID at $MASTER_ADDR:$MASTER_PORT: $*\" >> {}\n", log.display()));
    let path = format!("{}:{}", bin.display(), std::env::var("PATH").unwrap());
    let out = Command::new("bash")
        .arg(script)
        .env("PATH", &path)
        .env("SLURM_JOB_ID", "4242")
        .env("SLURM_JOB_NODELIST", "gpu-a[01-02]")
        .env("SLURM_NTASKS", "3")
        .env("MVSPLAT360", &fake)
        .envs(env.iter().copied())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(&log).unwrap();
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    lines.sort();
    assert_eq!(lines.len(), 4, "{text}");
    assert!(lines[3].starts_with("srun --kill-on-bad-exit=1 "), "{}", lines[3]);

    let out = Command::new("bash").arg(script).env("PATH", &path).env_remove("SLURM_JOB_ID").output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("run it with sbatch"));
    lines
}

#[test]
fn the_sbatch_scripts_start_one_process_per_task() {
    let lines = run_sbatch(EVAL, &[("OUT", "/scratch/eval")]);
    let args = "eval --data datasets/dl3dv/test --index assets/dl3dv_evaluation/dl3dv_ctx_5v_tgt_56v.json --ckpt checkpoints/dl3dv_480p.ckpt \
                --device cuda --dtype bf16 --out /scratch/eval --quiet";
    for (k, line) in lines[..3].iter().enumerate() {
        assert_eq!(*line, format!("rank {k} step 0 at gpu-a01:24242: {args}"));
    }
    let lines = run_sbatch(TRAIN, &[("OUT", "/scratch/train"), ("ALLOW_WORLD_CHANGE", "1")]);
    let args = "train --config configs/train/recipe/03-gpu.toml --out /scratch/train --device cuda --resume --quiet --allow-world-change";
    for (k, line) in lines[..3].iter().enumerate() {
        assert_eq!(*line, format!("rank {k} step 0 at gpu-a01:24242: {args}"));
    }
    // The config the script names exists.
    assert!(Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/recipe/03-gpu.toml")).is_file());
}

#[test]
fn fixture_stand_in_modules_have_specs() {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scripts/fixtures/standins.py");
    let o = Command::new("python3").arg(script).output().expect("python3 is needed (Debian: python3)");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("find_spec answers for 7"));
}
