//! `mvsplat360 bench <what>`: each benchmark lives in the crate it measures; this only dispatches.

use clap::Subcommand;

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {}

pub fn run(args: Args) -> anyhow::Result<()> {
    match args.what {}
}
