//! `cargo run --release -p mvsplat360-encoder --example bench_encoder [views height width threads runs [bf16]]`
fn main() {
    let a: Vec<usize> = std::env::args().skip(1).filter_map(|s| s.parse().ok()).collect();
    let get = |i: usize, d: usize| a.get(i).copied().unwrap_or(d);
    let dtype = if std::env::args().any(|s| s == "bf16") { candle_core::DType::BF16 } else { candle_core::DType::F32 };
    match mvsplat360_encoder::bench::run_encoder_bench(get(0, 5), get(1, 256), get(2, 448), get(3, 0), get(4, 3), dtype) {
        Ok(v) => println!("{v}"),
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
}
