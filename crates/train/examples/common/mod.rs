//! Helpers shared by the exploration examples (`tto`, `post`).

use candle_core::Tensor;

/// Removes `flag VALUE` from `args` and returns VALUE, or `default` when the flag is absent.
pub fn take_flag(args: &mut Vec<String>, flag: &str, default: &str) -> String {
    match args.iter().position(|a| a == flag) {
        Some(i) => {
            let v = args.remove(i + 1);
            args.remove(i);
            v
        }
        None => default.to_string(),
    }
}

/// PSNR of a prediction (clamped to [0, 1]) against its photo.
pub fn psnr(a: &Tensor, b: &Tensor) -> anyhow::Result<f64> {
    let a: Vec<f32> = a.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
    let b: Vec<f32> = b.flatten_all()?.to_vec1()?;
    Ok(mvsplat360_metrics::psnr::psnr(&a, &b))
}
