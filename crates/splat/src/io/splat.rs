//! antimatter15/splat's `.splat`: 32 bytes per Gaussian — position 3×f32, scale 3×f32 (linear),
//! RGBA 4×u8 (colour = 0.5 + C0·dc), rotation 4×u8 ((w, x, y, z) normalised, q·128 + 128) — sorted by
//! decreasing volume × opacity like its converter.

use std::io::Write;
use std::path::Path;

use super::ExportGaussians;
use crate::error::{Result, SplatError};
use crate::sh::C0;

/// Encode to bytes.
pub fn encode_splat(g: &ExportGaussians) -> Vec<u8> {
    let n = g.len();
    let mut order: Vec<usize> = (0..n).collect();
    let key = |i: usize| -((g.scales[i][0] * g.scales[i][1] * g.scales[i][2]) as f64 * g.opacities[i] as f64);
    order.sort_by(|&a, &b| key(a).total_cmp(&key(b)));
    let k = g.sh_coeffs;
    let to_u8 = |v: f32| (v * 255.0).round().clamp(0.0, 255.0) as u8;
    let mut out = Vec::with_capacity(32 * n);
    for i in order {
        for v in g.means[i].iter().chain(g.scales[i].iter()) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for ch in 0..3 {
            out.push(to_u8(0.5 + C0 * g.sh[(i * k) * 3 + ch]));
        }
        out.push(to_u8(g.opacities[i]));
        let q = g.quats[i];
        let nrm = q.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
        for v in q {
            out.push((v / nrm * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8);
        }
    }
    out
}

/// Write a `.splat` file.
pub fn write_splat(path: &Path, g: &ExportGaussians) -> Result<()> {
    let err = |e| SplatError::File { path: path.display().to_string(), source: e };
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).map_err(err)?);
    f.write_all(&encode_splat(g)).map_err(err)?;
    f.flush().map_err(err)
}
