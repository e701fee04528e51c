//! `mvsplat360 view`: a render's results in the browser (3D Gaussians, video, frame comparison, run settings).

use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;

#[derive(clap::Args)]
pub struct Args {
    /// The --out folder of `mvsplat360 render` (needs gaussians.ply, cameras.json and run.json; refined frames,
    /// ground truth, video and metrics.json are shown when present).
    pub out_dir: PathBuf,
    /// Port to listen on (0: any free port; the address is printed).
    #[arg(long, default_value_t = 8080)]
    pub port: u16,
    /// Address to listen on. The default serves this machine only; for a remote machine prefer an SSH tunnel
    /// (`ssh -L 8080:127.0.0.1:8080 HOST`, then open http://127.0.0.1:8080/ locally) over another address, which
    /// every machine that can reach it may read.
    #[arg(long, default_value = "127.0.0.1", conflicts_with = "static_dir")]
    pub host: std::net::IpAddr,
    /// Also answer requests whose `Host` is NAME (a tunnel's or reverse proxy's name; repeatable). Other names
    /// than IP addresses and localhost are refused, so that no web page can read the render through DNS rebinding.
    #[arg(long = "allow-host", value_name = "NAME", conflicts_with = "static_dir")]
    pub allow_host: Vec<String>,
    /// Open the page in the default web browser.
    #[arg(long)]
    pub open: bool,
    /// Instead of serving, write the page and a copy of the folder's files to DIR, a self-contained site for
    /// any static web host (DIR must be new, empty or an earlier export).
    #[arg(long = "static", value_name = "DIR", conflicts_with_all = ["port", "open"])]
    pub static_dir: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    // A render swapped in halfway when it was killed: finish it (under the render lock), so the viewer shows one
    // whole run. While a render holds the lock it is swapping its run in itself: show the folder as it is.
    use mvsplat360_pipeline::txn::Recovery;
    match mvsplat360_pipeline::txn::recover_if_free(&args.out_dir) {
        Ok(Recovery::Nothing) => {}
        Ok(Recovery::Finished) => eprintln!("note: {}: finished swapping in the render that was interrupted while being swapped in", args.out_dir.display()),
        Ok(Recovery::Busy(why)) => eprintln!(
            "note: {why}\n  a render is being swapped into {}: showing the folder read-only as it is now, without finishing the swap; \
             reload the page when the render is done",
            args.out_dir.display()
        ),
        Err(e) => eprintln!("warning: {}: a render was interrupted while being swapped in, and finishing it failed: {e}", args.out_dir.display()),
    }
    let out = mvsplat360_viewer::OutDir::open(&args.out_dir).context("cannot view this folder")?;
    if let Some(dest) = &args.static_dir {
        mvsplat360_viewer::write_static(&out, dest).context("cannot write the static site")?;
        println!("wrote {} (serve it with any static web server; opening index.html from disk does not work)", dest.display());
        return Ok(());
    }
    if !args.host.is_loopback() {
        eprintln!(
            "warning: serving on {}: any machine that reaches this address can read the render's files (photos, Gaussians, paths); \
             an SSH tunnel to 127.0.0.1 keeps them private",
            args.host
        );
    }
    let server = mvsplat360_viewer::Server::bind_on(out, &args.host.to_string(), args.port, args.allow_host.clone())?;
    let url = server.url().to_string();
    // One line on stdout (flushed at once): scripts and tests read the address from it.
    println!("serving {} at {url} (Ctrl-C to stop)", args.out_dir.display());
    std::io::stdout().flush().ok();
    if args.open {
        if let Err(e) = open::that_detached(&url) {
            eprintln!("warning: could not open a browser ({e}); open {url} yourself");
        }
    }
    server.serve();
    Ok(())
}
