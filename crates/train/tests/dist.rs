//! Data parallelism on the CPU (the `host` backend): the hub's sums, the launcher's failure handling, and a
//! two-rank run that equals one process accumulating two micro-batches, also across a stop and `--resume`.
//! The NCCL backend needs GPUs (it is compiled with `--features nccl`; not run here).

mod common;

use std::net::TcpListener;
use std::process::{Command, Stdio};
use std::sync::atomic::AtomicBool;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use candle_core::{Device, Tensor};
use mvsplat360_train::dist::{self, Backend, Collective, HostCollective, LaunchSpec};
use mvsplat360_train::{log, Quiet, RunOptions};

fn hub(world: usize) -> (String, std::thread::JoinHandle<mvsplat360_train::Result<()>>) {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap().to_string();
    (addr, std::thread::spawn(move || dist::serve_hub(l, world)))
}

#[test]
fn hub_sums_in_rank_order_and_fails_all_when_a_rank_leaves() {
    let (addr, h) = hub(3);
    let (tx, rx) = mpsc::channel();
    for rank in 0..3usize {
        let (addr, tx) = (addr.clone(), tx.clone());
        std::thread::spawn(move || {
            let mut c = HostCollective::connect(&addr, rank, 3).unwrap();
            let mut v = [rank as f64 + 0.5, 10f64.powi(rank as i32)];
            c.all_reduce_f64(&mut v).unwrap();
            // f32 sums in rank order: (1e8 + 1) − 1e8 = 0 in f32 (1e8 + 1 rounds to 1e8); any other order gives 1.
            let x = [1e8f32, 1.0, -1e8][rank];
            let t = c.all_reduce_tensor(&Tensor::new(&[x, rank as f32], &Device::Cpu).unwrap()).unwrap();
            let t: Vec<f32> = t.to_vec1().unwrap();
            // Rank 2 leaves; the others must get an error, not wait forever.
            let next = if rank == 2 {
                drop(c);
                None
            } else {
                let mut w = [1.0];
                Some(c.all_reduce_f64(&mut w).map_err(|e| e.to_string()))
            };
            tx.send((rank, v, t, next)).unwrap();
        });
    }
    let mut got: Vec<_> = (0..3).map(|_| rx.recv_timeout(Duration::from_secs(30)).expect("a rank hung")).collect();
    got.sort_by_key(|g| g.0);
    for (rank, v, t, next) in got {
        assert_eq!(v, [0.5 + 1.5 + 2.5, 1.0 + 10.0 + 100.0], "rank {rank}");
        assert_eq!(t, vec![0.0, 3.0], "rank {rank}: f32 sum not in rank order");
        if rank < 2 {
            let e = next.unwrap().unwrap_err();
            assert!(e.contains("lost the launcher"), "rank {rank}: {e}");
        }
    }
    let e = h.join().unwrap().unwrap_err().to_string();
    assert!(e.contains("rank 2"), "{e}");
}

#[test]
fn hub_refuses_ranks_that_send_different_amounts() {
    let (addr, h) = hub(2);
    let t: Vec<_> = (0..2usize)
        .map(|rank| {
            let addr = addr.clone();
            std::thread::spawn(move || {
                let mut c = HostCollective::connect(&addr, rank, 2).unwrap();
                let mut v = vec![1.0; rank + 1];
                c.all_reduce_f64(&mut v).map_err(|e| e.to_string())
            })
        })
        .collect();
    for j in t {
        assert!(j.join().unwrap().is_err());
    }
    let e = h.join().unwrap().unwrap_err().to_string();
    assert!(e.contains("different amounts"), "{e}");
}

#[test]
fn launcher_stops_the_other_ranks_when_one_fails() {
    let spec = LaunchSpec { world: 2, backend: Backend::Host, cpu: true };
    let t0 = Instant::now();
    let e = dist::launch(
        &spec,
        |r| {
            let mut c = Command::new("sh");
            // Rank 0 would run for a minute; rank 1 fails after its place is checked.
            c.args(["-c", if r == 0 { "sleep 60" } else { "test \"$MVSPLAT360_DIST_RANK\" = 1 && test -n \"$MVSPLAT360_DIST_HUB\" && exit 3" }]);
            c
        },
        &AtomicBool::new(false),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("rank 1") && e.contains('3'), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(20), "rank 0 was not stopped ({:?})", t0.elapsed());
}

#[test]
fn backend_errors_name_the_fix() {
    let e = Backend::Nccl.resolve(false).unwrap_err().to_string();
    assert!(e.contains("--dist-backend host"), "{e}");
    assert_eq!(Backend::Auto.resolve(false).unwrap(), Backend::Host);
    if !cfg!(feature = "nccl") {
        let e = Backend::Auto.resolve(true).unwrap_err().to_string();
        assert!(e.contains("--features nccl"), "{e}");
    }
}

fn weights(dir: &std::path::Path) -> std::collections::HashMap<String, Tensor> {
    candle_core::safetensors::load(dir.join("model/model.safetensors"), &Device::Cpu).unwrap()
}

fn max_diff(a: &std::collections::HashMap<String, Tensor>, b: &std::collections::HashMap<String, Tensor>) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().map(|(k, ta)| (ta - &b[k]).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()).fold(0.0, f32::max)
}

/// Two ranks × 1 micro-batch = one process × 2 micro-batches: same examples, same scaled gradient sum, same
/// clipped Adam step. The two-rank run is stopped with SIGTERM (to the launcher) and resumed on the way.
#[test]
fn two_ranks_equal_one_process_accumulating_two_across_a_stop() {
    const STEPS: u64 = 4;
    let bin = env!("CARGO_BIN_EXE_mvsplat360-train");
    let dir = tempfile::tempdir().unwrap();
    let (single, single1, par) = (dir.path().join("single"), dir.path().join("single1"), dir.path().join("par"));

    // Reference: one process, accumulate 2.
    let cfg = common::tiny_config(&single, STEPS, "");
    assert_eq!(cfg.train.accumulate, 2);
    mvsplat360_train::run(&cfg, &RunOptions::default(), &Quiet).unwrap();
    // Control: one process, accumulate 1 (what the run would be if rank 1's gradients were lost).
    let mut c1 = common::tiny_config(&single1, STEPS, "");
    c1.train.accumulate = 1;
    mvsplat360_train::run(&c1, &RunOptions::default(), &Quiet).unwrap();

    // Two ranks, accumulate 1, checkpoints only when stopped or done.
    let mut cp = common::tiny_config(&par, STEPS, "");
    cp.train.accumulate = 1;
    cp.train.checkpoint_every = 1000;
    let cfg_path = dir.path().join("par.toml");
    std::fs::write(&cfg_path, cp.to_toml()).unwrap();
    let args = ["--config", cfg_path.to_str().unwrap(), "--world-size", "2"];
    let mut child = Command::new(bin).args(args).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
    let t0 = Instant::now();
    while log::read(&par.join("log.jsonl")).map(|r| r.len()).unwrap_or(0) < 1 {
        assert!(t0.elapsed() < Duration::from_secs(120), "the two-rank run logged no step");
        assert!(child.try_wait().unwrap().is_none(), "the two-rank run ended early: {:?}", child.wait_with_output());
        std::thread::sleep(Duration::from_millis(20));
    }
    unsafe {
        libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
    }
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "a stopped run exits 130: {err}");
    let stopped = log::read(&par.join("log.jsonl")).unwrap().len() as u64;
    assert!(stopped < STEPS, "stopped too late to test the resume ({stopped} steps)");
    assert!(mvsplat360_train::checkpoint::list(&par).unwrap().len() == 1, "the stop wrote one checkpoint: {err}");

    let out = Command::new(bin).args(args).arg("--resume").stdout(Stdio::null()).stderr(Stdio::piped()).output().unwrap();
    assert!(out.status.success(), "resume: {}", String::from_utf8_lossy(&out.stderr));

    let (a, b) = (log::read(&single.join("log.jsonl")).unwrap(), log::read(&par.join("log.jsonl")).unwrap());
    assert_eq!(b.len() as u64, STEPS, "rank 0 alone logs, once per step");
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.step, y.step);
        for (what, p, q) in [("loss", x.loss, y.loss), ("mse", x.mse, y.mse), ("grad norm", x.grad_norm, y.grad_norm)] {
            assert!((p - q).abs() <= 1e-6 * p.abs().max(1e-12), "step {}: {what} {p} (one process) vs {q} (two ranks)", x.step);
        }
    }
    let (wa, wb, w1) = (weights(&single), weights(&par), weights(&single1));
    let d = max_diff(&wa, &wb);
    assert!(d <= 1e-6, "final weights differ by up to {d}");
    // The comparison can tell: losing rank 1's half would give the accumulate-1 run's weights.
    let d1 = max_diff(&w1, &wb);
    assert!(d1 > 1e-4, "two ranks ≈ one process with one micro-batch ({d1}): rank 1 did not count");
}
