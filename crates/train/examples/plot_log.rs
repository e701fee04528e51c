//! Plot a training log: `plot_log LOG.jsonl OUT.png` (the loss curve `train` writes, for logs brought back from
//! another machine).

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(a.len() == 3, "usage: plot_log LOG.jsonl OUT.png");
    let records = mvsplat360_train::log::read(a[1].as_ref())?;
    mvsplat360_train::log::plot(&records, a[2].as_ref())?;
    Ok(())
}
