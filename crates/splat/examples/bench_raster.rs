//! `cargo run --release -p mvsplat360-splat --example bench_raster [gaussians...]`: one JSON line per size.

use mvsplat360_splat::bench::{run_raster_bench, RasterBenchOpts};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let sizes: Vec<usize> = std::env::args().skip(1).filter_map(|a| a.parse().ok()).collect();
    let sizes = if sizes.is_empty() { vec![RasterBenchOpts::default().gaussians] } else { sizes };
    for n in sizes {
        let v = run_raster_bench(&RasterBenchOpts { gaussians: n, ..Default::default() })?;
        println!("{v}");
    }
    Ok(())
}
