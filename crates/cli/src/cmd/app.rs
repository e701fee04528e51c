//! `mvsplat360 app`: a local page on 127.0.0.1 — drop photos or a video (or name a scene folder), pick the
//! settings, watch the job pose and render, look at the result in the viewer. Jobs are child processes of this
//! binary (`render --progress json`), one at a time; see docs/app.md for the routes and the work folder.

mod jobs;
mod settings;
mod upload;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context;
use mvsplat360_viewer::http::{content_type, Body, EventSource, HttpServer, PageToken, Request, Response, APP_PORT};

use jobs::Jobs;
use settings::Settings;
use upload::Staging;

const PAGE: &str = include_str!("app/page.html");

#[derive(clap::Args)]
pub struct Args {
    /// Port to listen on, on 127.0.0.1 (0: any free port; the address is printed). Not `view`'s 8080, so both
    /// run at once.
    #[arg(long, default_value_t = APP_PORT)]
    pub port: u16,
    /// Open the page in the default web browser.
    #[arg(long)]
    pub open: bool,
    /// Work folder: a folder per job (`jobs/job-0001/`: the upload, the render's output, job.json) and the
    /// uploads under way (`.staging/`). Default: `$MVSPLAT360_CACHE/app`, else `~/.cache/mvsplat360/app`.
    #[arg(long, value_name = "DIR")]
    pub workdir: Option<PathBuf>,
    /// The most one upload (all its files) may hold: bytes, or with K, M, G or T (binary: 2G = 2 GiB).
    #[arg(long, value_name = "SIZE", default_value = "2G", value_parser = parse_size)]
    pub max_upload: u64,
}

/// `2G`, `500M`, `64K`, `1T`, `123` (an optional `B` or `iB` after the letter); binary multiples.
pub fn parse_size(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let t = t.strip_suffix("iB").or_else(|| t.strip_suffix('B')).unwrap_or(t);
    let (num, shift) = match t.chars().last().map(|c| c.to_ascii_uppercase()) {
        Some('K') => (&t[..t.len() - 1], 10),
        Some('M') => (&t[..t.len() - 1], 20),
        Some('G') => (&t[..t.len() - 1], 30),
        Some('T') => (&t[..t.len() - 1], 40),
        _ => (t, 0),
    };
    let n: f64 = num.trim().parse().map_err(|_| format!("{s:?} is not a size (e.g. 2G, 500M, 64K, 1000)"))?;
    if !(n.is_finite() && n > 0.0) {
        return Err(format!("{s:?}: a size must be positive"));
    }
    Ok((n * (1u64 << shift) as f64) as u64)
}

fn default_workdir() -> PathBuf {
    if let Some(c) = std::env::var_os("MVSPLAT360_CACHE") {
        return PathBuf::from(c).join("app");
    }
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("."));
    home.join(".cache/mvsplat360/app")
}

/// What the routes share.
struct App {
    token: PageToken,
    jobs: Arc<Jobs>,
    staging: Staging,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let workdir = args.workdir.clone().unwrap_or_else(default_workdir);
    let token = PageToken::random();
    let server = HttpServer::bind("127.0.0.1", args.port)?.with_token(token.clone());
    let events = EventSource::new(4000);
    let jobs = Jobs::open(workdir.join("jobs"), events).with_context(|| format!("reading the jobs under {}", workdir.display()))?;
    let staging = Staging::new(&workdir, args.max_upload);
    let app = Arc::new(App { token, jobs: jobs.clone(), staging });
    {
        let app = app.clone();
        ctrlc::set_handler(move || {
            eprintln!("stopping: the running job (if any) is interrupted; resume it from the page next time");
            app.jobs.stop_all();
            app.staging.clear();
            std::process::exit(130);
        })
        .context("installing the Ctrl-C handler")?;
    }
    let runner = jobs.clone();
    std::thread::Builder::new().name("app-jobs".into()).spawn(move || runner.run_queue()).context("starting the job runner")?;
    let url = server.url().to_string();
    // One line on stdout (flushed at once): scripts and tests read the address from it.
    println!("serving the app at {url} (work folder {}; Ctrl-C to stop)", workdir.display());
    std::io::stdout().flush().ok();
    if args.open {
        if let Err(e) = open::that_detached(&url) {
            eprintln!("warning: could not open a browser ({e}); open {url} yourself");
        }
    }
    server.serve(move |req: &Request, body: &mut Body<'_>| route(&app, req, body));
    Ok(())
}

/// A job id as the app makes them (`job-0001`); nothing else names a folder.
fn job_id(s: &str) -> Option<&str> {
    let n = s.strip_prefix("job-")?;
    (!n.is_empty() && n.len() <= 9 && n.bytes().all(|b| b.is_ascii_digit())).then_some(s)
}

fn route(app: &App, req: &Request, body: &mut Body<'_>) -> Response {
    let path = req.path().to_string();
    let m = req.method.as_str();
    let get = m == "GET" || m == "HEAD";
    let parts: Vec<&str> = path.trim_start_matches('/').split('/').collect();
    match (m, parts.as_slice()) {
        (_, [""] | ["index.html"]) if get => page(app),
        (_, ["api", "events"]) if get => Response::events(app.jobs.events.subscribe(req.last_event_id())),
        (_, ["api", "jobs"]) if get => job_list(app),
        (_, ["api", "jobs", id]) if get => match job_id(id).and_then(|id| app.jobs.get(id)) {
            Some(j) => Response::json(200, &j),
            None => Response::text(404, "no such job"),
        },
        (_, ["jobs", id, "view", rest @ ..]) if get => job_view(app, req, id, &rest.join("/")),
        ("POST", ["api", "uploads"]) => Response::json(200, &serde_json::json!({"id": app.staging.open()})),
        ("PUT", ["api", "uploads", id, name]) => app.staging.put(id, name, body),
        ("POST", ["api", "jobs"]) => create_job(app, body),
        ("POST", ["api", "jobs", id, action @ ("cancel" | "resume")]) => {
            let Some(id) = job_id(id) else { return Response::text(404, "no such job") };
            let r = if *action == "cancel" { app.jobs.cancel(id) } else { app.jobs.resume(id) };
            match r {
                Ok(j) => Response::json(200, &j.summary()),
                Err((code, msg)) => Response::text(code, &msg),
            }
        }
        _ if get || matches!(m, "POST" | "PUT") => Response::text(404, "not found"),
        _ => Response::text(405, "method not allowed").header("Allow", "GET, HEAD, POST, PUT"),
    }
}

fn page(app: &App) -> Response {
    let html = PAGE.replacen("<!--TOKEN-->", &app.token.meta_tag(), 1);
    Response::bytes(200, "text/html; charset=utf-8", html.into_bytes()).header("Cache-Control", "no-store")
}

fn job_list(app: &App) -> Response {
    // The event id first: a page that opens the stream after it misses nothing between the two.
    let event_id = app.jobs.events.last_id();
    let v = serde_json::json!({
        "event_id": event_id,
        "jobs": app.jobs.list(),
        "defaults": Settings::default(),
        "max_upload": app.staging.max,
    });
    Response::json(200, &v)
}

/// `POST /api/jobs`: `{"upload": ID}` or `{"scene": PATH}`, and `"settings"`.
fn create_job(app: &App, body: &mut Body<'_>) -> Response {
    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct New {
        upload: Option<String>,
        scene: Option<PathBuf>,
        #[serde(default)]
        settings: Settings,
    }
    let bytes = match body.read_to_vec(64 << 10) {
        Ok(b) => b,
        Err(e) => return e.response(),
    };
    let new: New = match serde_json::from_slice(&bytes) {
        Ok(n) => n,
        Err(e) => return Response::text(400, &format!("bad job request: {e}")),
    };
    if let Err(e) = new.settings.check() {
        return Response::text(400, &e);
    }
    let (input, scene, upload) = match (new.upload, new.scene) {
        (Some(u), None) => (String::new(), PathBuf::new(), Some(u)),
        (None, Some(p)) => match scene_path(&p) {
            Ok(p) => (p.display().to_string(), p, None),
            Err(e) => return Response::text(400, &e),
        },
        _ => return Response::text(400, "give either \"upload\" (an upload id) or \"scene\" (a path on this machine)"),
    };
    let (id, dir) = match app.jobs.new_dir() {
        Ok(x) => x,
        Err(e) => return Response::text(500, &format!("cannot create the job's folder: {e}")),
    };
    let (input, scene) = match upload {
        None => (input, scene),
        Some(u) => match app.staging.take(&u, &dir.join("input")) {
            Ok(x) => x,
            Err(e) => {
                let _ = std::fs::remove_dir_all(&dir);
                return Response::text(400, &e);
            }
        },
    };
    let j = app.jobs.add(id, input, scene, new.settings);
    Response::json(201, &j.summary())
}

/// A scene folder or video path on this machine: absolute, existing.
fn scene_path(p: &Path) -> Result<PathBuf, String> {
    if !p.is_absolute() {
        return Err(format!("{}: give an absolute path", p.display()));
    }
    p.canonicalize().map_err(|e| format!("{}: {e}", p.display()))
}

/// The viewer's page for a finished job's output, under `/jobs/ID/view/`.
fn job_view(app: &App, req: &Request, id: &str, rest: &str) -> Response {
    let Some(id) = job_id(id) else { return Response::text(404, "no such job") };
    if app.jobs.get(id).is_none() {
        return Response::text(404, "no such job");
    }
    let out = match mvsplat360_viewer::OutDir::open(&app.jobs.dir(id).join("out")) {
        Ok(o) => o,
        Err(e) => return Response::text(404, &format!("no result yet: {e}")),
    };
    use mvsplat360_viewer::Resolved;
    match mvsplat360_viewer::resolve(&out, &format!("/{rest}")) {
        Resolved::Asset(name) => match mvsplat360_viewer::asset(name) {
            Some((_, bytes)) => Response::bytes(200, content_type(name), bytes),
            None => Response::text(404, "not found"),
        },
        Resolved::Manifest => Response::json(200, &out.manifest()),
        Resolved::File(p) => Response::file(&p, req.header("Range")),
        Resolved::Refused(code, why) => Response::text(code, why),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_size("2G"), Ok(2 << 30));
        assert_eq!(parse_size("500M"), Ok(500 << 20));
        assert_eq!(parse_size("64KiB"), Ok(64 << 10));
        assert_eq!(parse_size("1000"), Ok(1000));
        assert!(parse_size("x").is_err() && parse_size("-1G").is_err() && parse_size("0").is_err());
    }

    #[test]
    fn job_ids_are_plain() {
        assert_eq!(job_id("job-0001"), Some("job-0001"));
        assert!(job_id("job-").is_none() && job_id("job-1/..").is_none() && job_id("..").is_none());
    }
}
