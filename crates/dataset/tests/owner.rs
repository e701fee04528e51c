//! `DirLock` across processes: the kernel lock decides, the record only describes. Helper processes are this test
//! binary run again (`helper` with `OWNER_TEST_HELPER=MODE:PATH`), so that a holder can be killed, leave a child,
//! or race others.
#![cfg(target_os = "linux")]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

use mvsplat360_dataset::atomic::DirLock;
use mvsplat360_dataset::owner::{boot_id, host_name, proc_stat, Owner};

const HELPER: &str = "OWNER_TEST_HELPER";
/// What a helper's line of news starts with.
const MARK: &str = "@@HELPER@@ ";

fn take(p: &Path) -> Result<DirLock, String> {
    DirLock::acquire(p, "render", "choose another --out")
}

/// What a helper does, by `OWNER_TEST_HELPER=MODE:PATH`; it prints one line `@@HELPER@@ <what>` once it has done it.
///  - `hold`: takes the lock and keeps it until its stdin closes.
///  - `hold-empty`: the same, its record emptied (a holder that has not written it yet).
///  - `race`: tries once; `won` keeps it until stdin closes, `lost` exits.
///  - `spawn` / `leak`: takes the lock, starts `sleep 30` (`leak`: with the lock's descriptor made inheritable, the
///    control), prints its pid and exits at once, without unlocking.
#[test]
fn helper() {
    let Ok(spec) = std::env::var(HELPER) else { return };
    let (mode, path) = spec.split_once(':').unwrap();
    let path = Path::new(path);
    // On a line of its own: the harness has written `test helper ... ` without a line end.
    let say = |what: &str| println!("\n{MARK}{what}");
    let wait_stdin = || {
        let _ = std::io::stdin().lines().count();
    };
    match mode {
        "hold" | "hold-empty" => {
            let lock = take(path).unwrap();
            if mode == "hold-empty" {
                std::fs::write(path, "").unwrap();
            }
            say("ready");
            wait_stdin();
            drop(lock);
        }
        "race" => match take(path) {
            Ok(lock) => {
                say("won");
                wait_stdin();
                drop(lock);
            }
            Err(_) => say("lost"),
        },
        "spawn" | "leak" => {
            let lock = take(path).unwrap();
            if mode == "leak" {
                use std::os::fd::AsRawFd;
                // SAFETY: a valid descriptor owned by `lock`.
                assert_eq!(unsafe { libc::fcntl(lock.as_raw_fd(), libc::F_SETFD, 0) }, 0);
            }
            let child = Command::new("sleep").arg("30").stdin(Stdio::null()).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
            say(&child.id().to_string());
            // Gone without unlocking (as a killed process would be); the file and its record stay.
            std::process::exit(0);
        }
        _ => panic!("unknown helper mode {mode}"),
    }
}

/// Starts a helper and waits for its news.
fn helper_process(mode: &str, path: &Path) -> (Child, String) {
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "helper", "--nocapture", "--test-threads", "1"])
        .env(HELPER, format!("{mode}:{}", path.display()))
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let said = lines.find_map(|l| l.ok()?.strip_prefix(MARK).map(str::to_string)).expect("the helper said nothing");
    // The rest (the test harness's summary) goes nowhere, but must not find the pipe closed.
    std::thread::spawn(move || lines.for_each(drop));
    (child, said)
}

/// Lets a helper holding the lock go on to unlock and exit.
fn release(mut child: Child) {
    drop(child.stdin.take());
    assert!(child.wait().unwrap().success());
}

fn kill(pid: u32) {
    // SAFETY: plain syscall.
    unsafe { libc::kill(pid as i32, libc::SIGKILL) };
}

/// Whether the lock's path names the file it holds open.
fn names_locked_file(lock: &DirLock) -> bool {
    use std::os::fd::AsRawFd;
    use std::os::unix::fs::MetadataExt;
    let open = std::fs::metadata(format!("/proc/self/fd/{}", lock.as_raw_fd())).unwrap();
    std::fs::metadata(lock.path()).is_ok_and(|m| m.dev() == open.dev() && m.ino() == open.ino())
}

fn state(pid: u32) -> Option<char> {
    proc_stat(pid).ok().flatten().map(|s| s.state)
}

#[test]
fn a_holder_killed_and_not_reaped_holds_nothing() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("lock");
    let (mut child, _) = helper_process("hold", &p);
    let e = take(&p).unwrap_err();
    assert!(e.contains(&format!("another render (process {}) is writing to this folder", child.id())), "{e}");
    child.kill().unwrap();
    // Not reaped: a zombie, whose /proc entry and record stay (once its last thread is gone: its main thread
    // shows `Z` before the test thread has exited and closed the file).
    let t = Instant::now();
    while proc_stat(child.id()).ok().flatten().map(|s| (s.state, s.threads)) != Some(('Z', 1)) {
        assert!(t.elapsed() < Duration::from_secs(30), "the helper never became a zombie");
        std::thread::sleep(Duration::from_millis(2));
    }
    let record = Owner::parse(&std::fs::read_to_string(&p).unwrap()).unwrap();
    assert_eq!(record.pid, child.id());
    assert!(record.is_dead());
    let lock = take(&p).expect("a zombie holds no lock");
    assert_eq!(std::fs::read_to_string(&p).unwrap(), format!("{}\n", Owner::me().record()));
    drop(lock);
    child.wait().unwrap();
}

#[test]
fn a_child_started_under_the_lock_does_not_hold_it_after_its_parent_is_gone() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("lock");
    let (mut helper, said) = helper_process("spawn", &p);
    let sleep: u32 = said.parse().unwrap();
    assert!(helper.wait().unwrap().success());
    assert!(matches!(state(sleep), Some('S' | 'R')), "the child runs on");
    take(&p).expect("the child does not hold its parent's lock");
    kill(sleep);

    // The control: the same child given the lock's descriptor holds the lock while it runs.
    let p = d.path().join("leaked");
    let (mut helper, said) = helper_process("leak", &p);
    let sleep: u32 = said.parse().unwrap();
    assert!(helper.wait().unwrap().success());
    let e = take(&p).unwrap_err();
    assert!(e.contains(&format!("process {}", helper.id())), "{e}");
    kill(sleep);
    let t = Instant::now();
    while let Err(e) = take(&p) {
        assert!(t.elapsed() < Duration::from_secs(30), "{e}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn an_empty_lock_file_of_a_live_holder_is_kept() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("lock");
    // Another process, between its lock and its record.
    let (child, _) = helper_process("hold-empty", &p);
    let e = take(&p).unwrap_err();
    assert!(e.contains("another render is writing to this folder") && e.contains("not recorded yet"), "{e}");
    assert_eq!(std::fs::read(&p).unwrap(), b"", "the holder's file was touched");
    release(child);
    assert!(!p.exists(), "its holder removes it on unlock");
    // Another descriptor of this process: a flock belongs to the open file.
    let first = take(&p).unwrap();
    std::fs::write(&p, "").unwrap();
    assert!(take(&p).is_err());
    assert_eq!(std::fs::read(&p).unwrap(), b"");
    drop(first);
    // Empty or garbled and unlocked: blocks nothing.
    for text in ["", "garbage ) ( 1 2 3 4\n", "\u{0}\u{1}"] {
        std::fs::write(&p, text).unwrap();
        drop(take(&p).unwrap_or_else(|e| panic!("{text:?}: {e}")));
    }
}

#[test]
fn a_record_naming_a_live_unrelated_process_is_taken_over() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("lock");
    let (h, boot) = (host_name(), boot_id().unwrap());
    let me = Owner::me();
    let parent = std::os::unix::process::parent_id();
    let parent_ticks = proc_stat(parent).unwrap().unwrap().start_ticks;
    for (pid, ticks) in [(me.pid, me.start.as_ref().unwrap().ticks + 1), (parent, parent_ticks + 1), (parent, parent_ticks)] {
        // A killed holder's record, its pid now a live process's (another start time), or even that live
        // process's own record: unlocked, it is information only.
        let record = format!("{pid} {h} {boot}:{ticks}\n");
        std::fs::write(&p, &record).unwrap();
        let lock = take(&p).unwrap_or_else(|e| panic!("{record}: {e}"));
        assert_eq!(std::fs::read_to_string(&p).unwrap(), format!("{}\n", me.record()));
        drop(lock);
    }
    // Another host's record on a file this host can lock: that host's lock may not reach here (see DirLock), so
    // it is refused, naming it.
    std::fs::write(&p, "12 node-b b00t:5\n").unwrap();
    let e = take(&p).unwrap_err();
    assert!(e.contains("a render on node-b (process 12) holds this folder") && e.contains("delete the file"), "{e}");
    assert_eq!(std::fs::read_to_string(&p).unwrap(), "12 node-b b00t:5\n");
}

#[test]
fn of_racers_for_a_dead_lock_one_wins_at_a_time() {
    let d = tempfile::tempdir().unwrap();
    let p: PathBuf = d.path().join("lock");
    let dead = format!("4294967295 {} {}:1\n", host_name(), boot_id().unwrap());

    // 8 processes at once: one winner, holding it while the others try.
    std::fs::write(&p, &dead).unwrap();
    let racers: Vec<(Child, String)> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..8).map(|_| s.spawn(|| helper_process("race", &p))).collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let winners: Vec<&Child> = racers.iter().filter(|(_, said)| said == "won").map(|(c, _)| c).collect();
    assert_eq!(winners.len(), 1, "{:?}", racers.iter().map(|r| &r.1).collect::<Vec<_>>());
    assert_eq!(Owner::parse(&std::fs::read_to_string(&p).unwrap()).unwrap().pid, winners[0].id());
    for (c, _) in racers {
        release(c);
    }
    assert!(!p.exists());

    // 8 threads, each with its own open file: once at the same moment, then over and over while the others
    // unlock and remove the file (a racer may have opened the file just removed: it must notice and start over).
    std::fs::write(&p, &dead).unwrap();
    let holders = Arc::new(AtomicUsize::new(0));
    let (wins, first) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
    let barrier = Arc::new(Barrier::new(8));
    let hs: Vec<_> = (0..8)
        .map(|_| {
            let (p, holders, wins, first, barrier) = (p.clone(), holders.clone(), wins.clone(), first.clone(), barrier.clone());
            std::thread::spawn(move || {
                barrier.wait();
                let lock = take(&p).ok();
                first.fetch_add(lock.is_some() as usize, Ordering::SeqCst);
                barrier.wait();
                drop(lock);
                barrier.wait();
                for _ in 0..300 {
                    if let Ok(lock) = take(&p) {
                        assert_eq!(holders.fetch_add(1, Ordering::SeqCst), 0, "two holders at once");
                        assert!(names_locked_file(&lock), "a holder whose file was removed or replaced");
                        std::thread::yield_now();
                        holders.fetch_sub(1, Ordering::SeqCst);
                        wins.fetch_add(1, Ordering::SeqCst);
                        drop(lock);
                    }
                }
            })
        })
        .collect();
    for h in hs {
        h.join().unwrap();
    }
    assert_eq!(first.load(Ordering::SeqCst), 1);
    assert!(wins.load(Ordering::SeqCst) > 0);
    assert!(!p.exists());
}
