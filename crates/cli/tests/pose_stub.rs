//! `mvsplat360 pose` against a stub `colmap` (a shell script on `PATH` that prints COLMAP's banner and does just
//! enough of each stage: the mapper and the undistorter copy a prepared model) and stub `ffmpeg`/`ffprobe` (the
//! installed ones, but for a frame extraction told to hang). Ctrl-C in every stage → exit 130 and nothing left of
//! the stage's process group; two runs into one `--out` → the second refused, naming the first; `--colmap-gpu
//! off` and `--matcher` as the commands run show them. Needs Debian's ffmpeg (for the video cases).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use mvsplat360_pose::colmap_writer::{write_binary, PinholeCamera, PosedImage};

mod orbit;
use orbit::orbit_video;

/// Prints the banner; records each command; in the stage `$STUB_HANG` starts a grandchild sleeper, writes its
/// own pid (its process group: pose starts each command in a group of its own) and sleeps.
const COLMAP: &str = r#"#!/bin/sh
if [ "$1" = "-h" ]; then
  echo "COLMAP 3.8 -- Structure-from-Motion and Multi-View Stereo"
  echo "(Commit 43de802 on 2023-01-31 $STUB_BUILD)"
  exit 0
fi
stage=$1
echo "$*" >> "$STUB_DIR/commands.txt"
out=""
prev=""
for a in "$@"; do
  if [ "$prev" = "--output_path" ]; then out=$a; fi
  prev=$a
done
if [ "$stage" = "$STUB_HANG" ]; then
  sleep 1000 &
  echo $$ > "$STUB_DIR/pgid.tmp" && mv "$STUB_DIR/pgid.tmp" "$STUB_DIR/pgid"
  sleep 1000
  exit 0
fi
case $stage in
  mapper) mkdir -p "$out/0" && cp "$STUB_MODEL"/* "$out/0/" ;;
  model_analyzer) echo "Mean reprojection error: 0.5px" ;;
  image_undistorter) mkdir -p "$out/images" "$out/sparse" && cp "$STUB_MODEL"/* "$out/sparse/" ;;
esac
exit 0
"#;

/// The installed ffmpeg, except that the frame extraction (`-map 0:v:0`) hangs when `$STUB_HANG` is `ffmpeg`.
const FFMPEG: &str = r#"#!/bin/sh
case " $* " in
  *" -map "*)
    if [ "$STUB_HANG" = ffmpeg ]; then
      sleep 1000 &
      echo $$ > "$STUB_DIR/pgid.tmp" && mv "$STUB_DIR/pgid.tmp" "$STUB_DIR/pgid"
      sleep 1000
      exit 0
    fi ;;
esac
exec REAL "$@"
"#;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_mvsplat360")
}

fn on_path(name: &str) -> PathBuf {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
        .unwrap_or_else(|| panic!("`{name}` is not installed (scripts/test installs it: apt-get install -y ffmpeg)"))
}

fn script(path: &Path, text: &str) {
    use std::os::unix::fs::PermissionsExt;
    std::fs::write(path, text).unwrap();
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).unwrap();
}

/// A folder of stubs and what they share: the hang's pid file, the commands run, the model the mapper "builds".
struct Stub {
    dir: tempfile::TempDir,
}

impl Stub {
    fn new() -> Stub {
        let dir = tempfile::tempdir().unwrap();
        let bin = dir.path().join("bin");
        std::fs::create_dir_all(&bin).unwrap();
        script(&bin.join("colmap"), COLMAP);
        script(&bin.join("ffmpeg"), &FFMPEG.replace("REAL", &on_path("ffmpeg").display().to_string()));
        script(&bin.join("ffprobe"), &format!("#!/bin/sh\nexec {} \"$@\"\n", on_path("ffprobe").display()));
        Stub { dir }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    /// `mvsplat360 pose INPUT --out OUT ARGS` with the stubs first on PATH, hanging in `hang`.
    fn pose(&self, input: &Path, out: &Path, hang: &str, build: &str, args: &[&str]) -> Command {
        let path =
            std::env::join_paths(std::iter::once(self.path().join("bin")).chain(std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()))).unwrap();
        let mut c = Command::new(bin());
        c.args(["--quiet", "pose"]).arg(input).arg("--out").arg(out).args(args);
        c.env("PATH", path).env("STUB_DIR", self.path()).env("STUB_HANG", hang).env("STUB_BUILD", build).env("STUB_MODEL", self.path().join("model"));
        c.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
        c
    }

    /// The prepared model of `names` (one PINHOLE camera, no points): what the mapper and the undistorter "write".
    fn model(&self, names: &[String]) {
        let cam = PinholeCamera { id: 1, width: 480, height: 270, fx: 400.0, fy: 400.0, cx: 240.0, cy: 135.0 };
        let images: Vec<PosedImage> = names
            .iter()
            .enumerate()
            .map(|(i, n)| {
                let c2w = [[1.0, 0.0, 0.0, i as f64], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
                PosedImage::from_c2w(i as u32 + 1, 1, n.clone(), &c2w).unwrap()
            })
            .collect();
        write_binary(&self.path().join("model"), &[cam], &images, &[]).unwrap();
    }

    /// Waits (up to 60 s) for the stage to hang, and returns its process group.
    fn hanging_group(&self, child: &mut Child, stage: &str) -> i32 {
        let t = Instant::now();
        let f = self.path().join("pgid");
        loop {
            if let Some(g) = std::fs::read_to_string(&f).ok().and_then(|s| s.trim().parse().ok()) {
                return g;
            }
            if let Some(st) = child.try_wait().unwrap() {
                let mut err = String::new();
                use std::io::Read;
                let _ = child.stderr.take().unwrap().read_to_string(&mut err);
                panic!("pose ended ({st}) before {stage} started:\n{err}");
            }
            assert!(t.elapsed() < Duration::from_secs(60), "{stage} did not start within 60 s");
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    fn commands(&self) -> String {
        std::fs::read_to_string(self.path().join("commands.txt")).unwrap_or_default()
    }
}

/// Live (not zombie) processes in process group `pgid`, from /proc/PID/stat (state and group after the last ')').
fn group_members(pgid: i32) -> Vec<(i32, String)> {
    let mut out = vec![];
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<i32>() else { continue };
        let Ok(stat) = std::fs::read_to_string(e.path().join("stat")) else { continue };
        let Some(rest) = stat.rfind(')').map(|i| &stat[i + 1..]) else { continue };
        let f: Vec<&str> = rest.split_whitespace().collect();
        // After ')': state, ppid, pgrp.
        if f.len() > 2 && f[2].parse() == Ok(pgid) && f[0] != "Z" && f[0] != "X" {
            out.push((pid, stat.trim().to_string()));
        }
    }
    out
}

fn sigint(child: &Child) {
    let st = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(st.success());
}

/// Eight photos of the test scene (480×270, no EXIF), and the names pose gives them in `images/`.
fn photos(dir: &Path) -> (PathBuf, Vec<String>) {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/pose-test/orbit24/images");
    let dst = dir.join("photos");
    std::fs::create_dir_all(&dst).unwrap();
    let names = (0..8)
        .map(|k| {
            let f = format!("{:03}.jpg", k * 3);
            std::fs::copy(src.join(&f), dst.join(&f)).unwrap();
            format!("{k:04}_{f}")
        })
        .collect();
    (dst, names)
}

/// Ctrl-C while `stage` runs: exit 130, the stage was the last command started, and within 30 s no live
/// process is left in its group (the stub and its grandchild sleeper).
fn interrupt_in(input: &Path, names: Option<&[String]>, stage: &str, args: &[&str]) {
    let stub = Stub::new();
    if let Some(n) = names {
        stub.model(n);
    }
    let out = stub.path().join("scene");
    let mut child = stub.pose(input, &out, stage, "without CUDA", args).spawn().unwrap();
    let pgid = stub.hanging_group(&mut child, stage);
    assert!(!group_members(pgid).is_empty(), "{stage}: its group {pgid} is already empty");
    sigint(&child);
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{stage}: {stderr}");
    assert!(stderr.contains("interrupted"), "{stage}: {stderr}");
    assert!(!out.exists(), "{stage}: a scene was written");
    if stage != "ffmpeg" {
        let last = stub.commands().lines().last().unwrap_or_default().to_string();
        assert!(last.starts_with(stage), "{stage}: the last command run was {last}");
    }
    let t = Instant::now();
    loop {
        let left = group_members(pgid);
        if left.is_empty() {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "{stage}: 30 s after the interrupt its group still holds {left:#?}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn ctrl_c_in_every_colmap_stage_of_photos_leaves_no_process() {
    let d = tempfile::tempdir().unwrap();
    let (input, names) = photos(d.path());
    for stage in ["feature_extractor", "exhaustive_matcher", "mapper", "model_analyzer", "image_undistorter"] {
        interrupt_in(&input, Some(&names), stage, &[]);
    }
}

#[test]
fn ctrl_c_in_every_stage_of_a_video_leaves_no_process() {
    let d = tempfile::tempdir().unwrap();
    let input = orbit_video(d.path(), &on_path("ffmpeg"));
    // 24 frames: the sequential matcher, then the loop closure's matches_importer.
    for stage in ["ffmpeg", "feature_extractor", "sequential_matcher", "matches_importer"] {
        interrupt_in(&input, None, stage, &["--frames", "24"]);
    }
}

fn ok(o: Output) -> Output {
    assert!(o.status.success(), "exit {:?}\n{}", o.status.code(), String::from_utf8_lossy(&o.stderr));
    o
}

#[test]
fn a_second_run_into_one_out_is_refused_naming_the_first() {
    let stub = Stub::new();
    let (input, names) = photos(stub.path());
    stub.model(&names);
    let out = stub.path().join("scene");
    let mut first = stub.pose(&input, &out, "feature_extractor", "without CUDA", &[]).spawn().unwrap();
    stub.hanging_group(&mut first, "feature_extractor");
    let second = stub.pose(&input, &out, "", "without CUDA", &[]).output().unwrap();
    let err = String::from_utf8_lossy(&second.stderr);
    assert!(!second.status.success(), "the second run went on: {err}");
    for part in [out.display().to_string(), ".scene.pose.lock".into(), format!("process {}", first.id()), "choose another --out".into()] {
        assert!(err.contains(&part), "the refusal does not say `{part}`: {err}");
    }
    assert_eq!(stub.commands().lines().filter(|l| l.starts_with("feature_extractor")).count(), 1, "the second run ran COLMAP");
    sigint(&first);
    assert_eq!(first.wait_with_output().unwrap().status.code(), Some(130));
    // The interrupted run's lock is free: a rerun finishes its work, and leaves no lock file.
    ok(stub.pose(&input, &out, "", "without CUDA", &[]).output().unwrap());
    assert!(out.join("pose.json").is_file());
    assert!(!stub.path().join(".scene.pose.lock").exists(), "the lock file was left");
}

/// The commands pose.json records for a run with `args`, against a COLMAP built with CUDA.
fn recorded(args: &[&str]) -> serde_json::Value {
    let stub = Stub::new();
    let (input, names) = photos(stub.path());
    stub.model(&names);
    let out = stub.path().join("scene");
    let mut a = vec!["--json"];
    a.extend(args);
    let o = ok(stub.pose(&input, &out, "", "with CUDA", &a).output().unwrap());
    serde_json::from_slice(&o.stdout).unwrap()
}

fn argv_of<'a>(report: &'a serde_json::Value, stage: &str) -> Vec<&'a str> {
    let c = report["commands"].as_array().unwrap().iter().find(|c| c["stage"] == stage).unwrap_or_else(|| panic!("no {stage} in {report}"));
    c["argv"].as_array().unwrap().iter().map(|a| a.as_str().unwrap()).collect()
}

fn option<'a>(argv: &[&'a str], name: &str) -> Option<&'a str> {
    argv.iter().position(|a| *a == name).and_then(|i| argv.get(i + 1)).copied()
}

#[test]
fn colmap_gpu_off_and_the_matcher_flag_reach_the_commands() {
    // Default: a CUDA build uses the GPU; 8 photos are matched exhaustively.
    let r = recorded(&[]);
    assert_eq!(option(&argv_of(&r, "feature_extractor"), "--SiftExtraction.use_gpu"), Some("1"));
    assert_eq!(option(&argv_of(&r, "exhaustive_matcher"), "--SiftMatching.use_gpu"), Some("1"));
    assert_eq!(r["settings"]["matcher"], "exhaustive");
    assert_eq!(r["engines"][0][1]["cuda"], true);

    let r = recorded(&["--colmap-gpu", "off", "--matcher", "sequential"]);
    assert_eq!(option(&argv_of(&r, "feature_extractor"), "--SiftExtraction.use_gpu"), Some("0"));
    assert_eq!(option(&argv_of(&r, "sequential_matcher"), "--SiftMatching.use_gpu"), Some("0"));
    assert_eq!(r["settings"]["matcher"], "sequential");
    for c in r["commands"].as_array().unwrap() {
        let argv: Vec<&str> = c["argv"].as_array().unwrap().iter().map(|a| a.as_str().unwrap()).collect();
        assert!(!argv.iter().any(|a| a.contains("use_gpu") && option(&argv, a) != Some("0")), "a GPU option in {argv:?}");
    }

    let o = Command::new(bin()).args(["pose", "x", "--out", "y", "--matcher", "fastest"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("exhaustive") && err.contains("sequential"), "{err}");
}
