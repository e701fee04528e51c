//! `cargo run --release -p mvsplat360-encoder --example bench_encoder [views height width threads runs]`
fn main() {
    let a: Vec<usize> = std::env::args().skip(1).filter_map(|s| s.parse().ok()).collect();
    let get = |i: usize, d: usize| a.get(i).copied().unwrap_or(d);
    match mvsplat360_encoder::bench::run_encoder_bench(get(0, 5), get(1, 256), get(2, 448), get(3, 0), get(4, 3)) {
        Ok(v) => println!("{v}"),
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
}
