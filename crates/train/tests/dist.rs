//! Data parallelism on the CPU (the `host` backend): the ring's sums, the rendezvous and its errors, the
//! launcher's failure handling, and runs started as torchrun starts them (each rank its own process, a listener
//! held on MASTER_PORT as torchrun's store holds it, rank 0 on 127.0.0.2 and the others reaching it from
//! 127.0.0.1) that equal one process accumulating the same global batch, also across a stop and a resume.
//! The NCCL backend needs GPUs (it is compiled with `--features nccl`; not run here).

mod common;

use std::net::TcpListener;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::AtomicBool;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use candle_core::{Device, Tensor};
use mvsplat360_pipeline::launch::{Launcher, Place};
use mvsplat360_train::dist::{self, Backend, Collective, LaunchSpec, Rank};
use mvsplat360_train::{log, Quiet, RunOptions};
use rand::{Rng, SeedableRng};

/// A port free now on every address: rank 0 listens on all of them (these tests name 127.0.0.2 as its address).
fn free_port() -> u16 {
    TcpListener::bind("0.0.0.0:0").unwrap().local_addr().unwrap().port()
}

fn rank(r: usize, world: usize, port: u16, timeout_s: u64) -> Rank {
    let place = Place { rank: r, world, local_rank: r, local_world: Some(world), launcher: Launcher::Torchrun };
    Rank { rank: r, world, place, rendezvous: format!("127.0.0.2:{port}"), timeout: Duration::from_secs(timeout_s) }
}

fn join(r: usize, world: usize, port: u16, fingerprint: u64) -> mvsplat360_train::Result<Box<dyn Collective>> {
    dist::connect(&rank(r, world, port, 30), Backend::Host, fingerprint, &Device::Cpu)
}

/// What one rank contributes to the long all-reduce: values of mixed magnitudes, so the order of the additions
/// shows in the bits.
fn long_part(rank: usize, n: usize) -> Vec<f32> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(100 + rank as u64);
    (0..n).map(|_| rng.gen_range(-1.0f32..1.0) * 10f32.powi(rng.gen_range(-3..6))).collect()
}

#[test]
fn ring_sums_in_rank_order_identically_and_fails_all_when_a_rank_leaves() {
    // 3 ranks; more than two chunks (2^18 values each) and a ragged last one.
    const W: usize = 3;
    let n = 7 * 85_715;
    let port = free_port();
    let (tx, rx) = mpsc::channel();
    for r in 0..W {
        let tx = tx.clone();
        std::thread::spawn(move || {
            let mut c = join(r, W, port, 7).unwrap();
            let mut v = [r as f64 + 0.5, 10f64.powi(r as i32)];
            c.all_reduce_f64(&mut v).unwrap();
            // f32 sums in rank order: (1e8 + 1) − 1e8 = 0 in f32 (1e8 + 1 rounds to 1e8); any other order gives 1.
            let x = [1e8f32, 1.0, -1e8][r];
            let t: Vec<f32> = c.all_reduce_tensor(&Tensor::new(&[x, r as f32], &Device::Cpu).unwrap()).unwrap().to_vec1().unwrap();
            let long = Tensor::from_vec(long_part(r, n), (n / 7, 7), &Device::Cpu).unwrap();
            let long = c.all_reduce_tensor(&long).unwrap();
            assert_eq!(long.dims(), &[n / 7, 7]);
            let long: Vec<f32> = long.flatten_all().unwrap().to_vec1().unwrap();
            // Rank 2 leaves; the others must get an error naming it or its neighbour, not wait.
            let next = if r == 2 {
                drop(c);
                None
            } else {
                let mut w = vec![1.0; 1000];
                Some(c.all_reduce_f64(&mut w).map_err(|e| e.to_string()))
            };
            tx.send((r, v, t, long, next)).unwrap();
        });
    }
    let mut got: Vec<_> = (0..W).map(|_| rx.recv_timeout(Duration::from_secs(60)).expect("a rank hung")).collect();
    got.sort_by_key(|g| g.0);
    // The reference: one loop adding the parts in rank order.
    let parts: Vec<Vec<f32>> = (0..W).map(|r| long_part(r, n)).collect();
    let want: Vec<f32> = (0..n).map(|i| (parts[0][i] + parts[1][i]) + parts[2][i]).collect();
    for (r, v, t, long, next) in got {
        assert_eq!(v, [0.5 + 1.5 + 2.5, 1.0 + 10.0 + 100.0], "rank {r}");
        assert_eq!(t, vec![0.0, 3.0], "rank {r}: f32 sum not in rank order");
        let bad = long.iter().zip(&want).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        assert_eq!(bad, 0, "rank {r}: {bad} of {} sums differ from the rank-order sum", want.len());
        if r < 2 {
            let e = next.unwrap().unwrap_err();
            assert!(e.contains("left the run") || e.contains("sending to rank"), "rank {r}: {e}");
        }
    }
}

#[test]
fn ranks_with_different_amounts_or_configs_are_refused() {
    let port = free_port();
    let t: Vec<_> = (0..2usize)
        .map(|r| {
            std::thread::spawn(move || {
                let mut c = join(r, 2, port, 1).unwrap();
                let mut v = vec![1.0; r + 1];
                c.all_reduce_f64(&mut v).map_err(|e| e.to_string())
            })
        })
        .collect();
    let errs: Vec<String> = t.into_iter().map(|j| j.join().unwrap().unwrap_err()).collect();
    assert!(errs.iter().any(|e| e.contains("different configs")), "{errs:?}");

    let port = free_port();
    let t: Vec<_> = (0..2usize).map(|r| std::thread::spawn(move || join(r, 2, port, r as u64).map(|_| ()).unwrap_err().to_string())).collect();
    for j in t {
        let e = j.join().unwrap();
        assert!(e.contains("runs another config than rank 0"), "{e}");
    }
}

#[test]
fn an_unreachable_rendezvous_is_named() {
    // Nothing listens there: rank 1 gives up after its timeout, naming the address.
    let port = free_port();
    let t0 = Instant::now();
    let e = dist::connect(&rank(1, 2, port, 1), Backend::Host, 0, &Device::Cpu).map(|_| ()).unwrap_err().to_string();
    assert!(e.contains(&format!("could not reach rank 0 at 127.0.0.2:{port}")) && e.contains("MASTER_ADDR"), "{e}");
    // It gives up (after its connect timeout), not retrying for the launch's 30 minutes: a hang deadline.
    assert!(t0.elapsed() < Duration::from_secs(120), "{:?}", t0.elapsed());
    // Rank 0 alone: it names the ranks that never came.
    let e = dist::connect(&rank(0, 3, port, 1), Backend::Host, 0, &Device::Cpu).map(|_| ()).unwrap_err().to_string();
    assert!(e.contains("rank(s) 1, 2 of 3 did not join"), "{e}");
    // MASTER_ADDR on another machine: rank 0 cannot listen there.
    let mut r0 = rank(0, 2, port, 1);
    r0.rendezvous = format!("192.0.2.1:{port}");
    let e = dist::connect(&r0, Backend::Host, 0, &Device::Cpu).map(|_| ()).unwrap_err().to_string();
    assert!(e.contains("not an address of this machine"), "{e}");
}

#[test]
fn launcher_stops_the_other_ranks_when_one_fails() {
    let spec = LaunchSpec { world: 2, cpu: true };
    let t0 = Instant::now();
    let e = dist::launch(
        &spec,
        |r| {
            let mut c = Command::new("sh");
            // Rank 0 would run for an hour (exec: the killed rank is the sleep itself, no orphan holding the
            // test's output open); rank 1 fails after its place is checked.
            c.args(["-c", if r == 0 { "exec sleep 3600" } else { "test \"$MVSPLAT360_DIST_RANK\" = 1 && test -n \"$MVSPLAT360_DIST_ADDR\" && exit 3" }]);
            c
        },
        &AtomicBool::new(false),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("rank 1") && e.contains('3'), "{e}");
    // Far below rank 0's hour, however busy the machine.
    assert!(t0.elapsed() < Duration::from_secs(600), "rank 0 was not stopped ({:?})", t0.elapsed());
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

/// A run of `world` ranks started as `torchrun --nproc-per-node=world --no-python mvsplat360-train …` starts
/// them: its variables, and its store holding MASTER_PORT (`store`), so the rendezvous takes MASTER_PORT + 1.
struct Torchrun {
    store: TcpListener,
    world: usize,
}

impl Torchrun {
    fn new(world: usize) -> Self {
        // A MASTER_PORT whose successor is free as well (rank 0 listens there on every address).
        loop {
            let store = TcpListener::bind("0.0.0.0:0").unwrap();
            let p = store.local_addr().unwrap().port();
            if p < u16::MAX && TcpListener::bind(("0.0.0.0", p + 1)).is_ok() {
                return Self { store, world };
            }
        }
    }
    fn spawn(&self, args: &[&str]) -> Vec<Child> {
        let port = self.store.local_addr().unwrap().port();
        (0..self.world)
            .map(|r| {
                Command::new(env!("CARGO_BIN_EXE_mvsplat360-train"))
                    .args(args)
                    .env("RANK", r.to_string())
                    .env("LOCAL_RANK", r.to_string())
                    .env("WORLD_SIZE", self.world.to_string())
                    .env("LOCAL_WORLD_SIZE", self.world.to_string())
                    .env("MASTER_ADDR", "127.0.0.2")
                    .env("MASTER_PORT", port.to_string())
                    .env("RAYON_NUM_THREADS", "1")
                    .env_remove("MVSPLAT360_DIST_RANK")
                    .stdout(Stdio::null())
                    .stderr(Stdio::piped())
                    .spawn()
                    .unwrap()
            })
            .collect()
    }
}

/// Waits for every rank; (exit codes, rank 0's stderr).
fn wait_all(children: Vec<Child>) -> (Vec<Option<i32>>, String, String) {
    let outs: Vec<_> = children.into_iter().map(|c| c.wait_with_output().unwrap()).collect();
    let all = outs.iter().enumerate().map(|(r, o)| format!("--- rank {r}:\n{}", String::from_utf8_lossy(&o.stderr))).collect::<String>();
    (outs.iter().map(|o| o.status.code()).collect(), String::from_utf8_lossy(&outs[0].stderr).into_owned(), all)
}

/// One process accumulating `k` micro-batches, as the reference of a `k`-rank run.
fn reference(dir: &std::path::Path, steps: u64, k: u32) -> std::path::PathBuf {
    let out = dir.join(format!("single{k}"));
    let mut cfg = common::tiny_config(&out, steps, "");
    cfg.train.accumulate = k;
    mvsplat360_train::run(&cfg, &RunOptions::default(), &Quiet).unwrap();
    out
}

/// The ranks' config: one micro-batch each, checkpoints only when stopped or done.
fn rank_config(dir: &std::path::Path, out: &std::path::Path, steps: u64) -> std::path::PathBuf {
    let mut cp = common::tiny_config(out, steps, "");
    cp.train.accumulate = 1;
    cp.train.checkpoint_every = 1000;
    let path = dir.join(format!("{}.toml", out.file_name().unwrap().to_string_lossy()));
    std::fs::write(&path, cp.to_toml()).unwrap();
    path
}

/// The ranks' run equals one process with the same global batch: the ring adds the gradients in the order one
/// process accumulates them, so only the float noise of differently threaded kernels can differ (the reference
/// runs on the test's threads, each rank on one). The bound allows each of ≤ 4 steps' weight updates to differ
/// by a few ulp of the weights' scale (≈ 1e-7 each); losing a rank's gradients moves them by > 1e-4.
fn assert_equal_runs(single: &std::path::Path, par: &std::path::Path, steps: u64, control: &std::path::Path) {
    let (a, b) = (log::read(&single.join("log.jsonl")).unwrap(), log::read(&par.join("log.jsonl")).unwrap());
    assert_eq!(b.len() as u64, steps, "rank 0 alone logs, once per step");
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.step, y.step);
        for (what, p, q) in [("loss", x.loss, y.loss), ("mse", x.mse, y.mse), ("grad norm", x.grad_norm, y.grad_norm)] {
            assert!((p - q).abs() <= 1e-6 * p.abs().max(1e-12), "step {}: {what} {p} (one process) vs {q} (ranks)", x.step);
        }
    }
    let (wa, wb, wc) = (weights(single), weights(par), weights(control));
    let d = max_diff(&wa, &wb);
    assert!(d <= 1e-6, "final weights differ by up to {d}");
    // The comparison can tell: a run without the other ranks' gradients gives other weights.
    let dc = max_diff(&wc, &wb);
    assert!(dc > 1e-4, "the ranks ≈ a run with fewer micro-batches ({dc}): some rank did not count");
}

/// Two ranks × 1 micro-batch = one process × 2 micro-batches: same examples, same scaled gradient sum, same
/// clipped Adam step. The ranks are stopped with SIGTERM (torchrun forwards it to each) and resumed on the way.
#[test]
fn torchrun_two_ranks_equal_one_process_accumulating_two_across_a_stop() {
    const STEPS: u64 = 4;
    let dir = tempfile::tempdir().unwrap();
    let (single, single1) = (reference(dir.path(), STEPS, 2), reference(dir.path(), STEPS, 1));
    let par = dir.path().join("par");
    let cfg = rank_config(dir.path(), &par, STEPS);
    let args = ["--config", cfg.to_str().unwrap()];
    let run = Torchrun::new(2);
    let ranks = run.spawn(&args);
    let t0 = Instant::now();
    while log::read(&par.join("log.jsonl")).map(|r| r.len()).unwrap_or(0) < 1 {
        assert!(t0.elapsed() < Duration::from_secs(120), "the two-rank run logged no step");
        std::thread::sleep(Duration::from_millis(20));
    }
    for c in &ranks {
        unsafe {
            libc::kill(c.id() as libc::pid_t, libc::SIGTERM);
        }
    }
    let (codes, _, err) = wait_all(ranks);
    assert_eq!(codes, vec![Some(130); 2], "stopped ranks exit 130: {err}");
    let stopped = log::read(&par.join("log.jsonl")).unwrap().len() as u64;
    assert!(stopped < STEPS, "stopped too late to test the resume ({stopped} steps)");
    assert_eq!(mvsplat360_train::checkpoint::list(&par).unwrap().len(), 1, "the stop wrote one checkpoint: {err}");

    let resumed: Vec<&str> = args.iter().copied().chain(["--resume"]).collect();
    let (codes, err0, err) = wait_all(run.spawn(&resumed));
    assert_eq!(codes, vec![Some(0); 2], "resume: {err}");
    assert!(err0.contains("the 2 ranks' weights are identical"), "{err0}");
    assert_equal_runs(&single, &par, STEPS, &single1);
}

/// Three ranks (an odd ring: rank 1 forwards both the partial sums and the totals) = one process × 3.
#[test]
fn torchrun_three_ranks_equal_one_process_accumulating_three() {
    const STEPS: u64 = 2;
    let dir = tempfile::tempdir().unwrap();
    let (single, single2) = (reference(dir.path(), STEPS, 3), reference(dir.path(), STEPS, 2));
    let par = dir.path().join("par3");
    let cfg = rank_config(dir.path(), &par, STEPS);
    let run = Torchrun::new(3);
    let (codes, err0, err) = wait_all(run.spawn(&["--config", cfg.to_str().unwrap()]));
    assert_eq!(codes, vec![Some(0); 3], "{err}");
    assert!(err0.contains("the 3 ranks' weights are identical"), "{err0}");
    assert_equal_runs(&single, &par, STEPS, &single2);
}

/// A rank whose rank 0 never comes fails with the address it tried, within its timeout.
#[test]
fn a_rank_that_cannot_reach_rank_0_names_the_address() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = rank_config(dir.path(), &dir.path().join("lone"), 2);
    let port = free_port();
    let o = Command::new(env!("CARGO_BIN_EXE_mvsplat360-train"))
        .args(["--config", cfg.to_str().unwrap()])
        .envs([("RANK", "1"), ("LOCAL_RANK", "1"), ("WORLD_SIZE", "2"), ("MASTER_ADDR", "127.0.0.2"), ("MVSPLAT360_DIST_TIMEOUT", "2")])
        .env("MASTER_PORT", (port - 1).to_string())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains(&format!("127.0.0.2:{port}")), "{err}");
}
