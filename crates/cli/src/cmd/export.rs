#[derive(clap::Args)]
pub struct Args {}

pub fn run(_args: Args, _quiet: bool) -> anyhow::Result<()> {
    anyhow::bail!("not built yet")
}
