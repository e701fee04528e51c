//! Standard 3DGS `.ply` (binary little-endian): x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2
//! rot_0..3, with f_rest channel-major (all R rest coefficients, then G, then B), opacity as a logit,
//! log scales, rotation (w, x, y, z), SH in graphdeco's basis.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use super::ExportGaussians;
use crate::error::{Result, SplatError};
use crate::sh::{fork_to_graphdeco_matrix, graphdeco_to_fork_matrix};

fn fmt_err(path: &Path, msg: impl Into<String>) -> SplatError {
    SplatError::Format { path: path.display().to_string(), msg: msg.into() }
}

/// Apply a 16×16 coefficient map to the first `k` coefficients of each colour channel.
fn map_coeffs(m: &[[f64; 16]; 16], sh: &[f32], k: usize) -> Vec<f32> {
    let mut out = vec![0f32; sh.len()];
    for (src, dst) in sh.chunks_exact(k * 3).zip(out.chunks_exact_mut(k * 3)) {
        for ch in 0..3 {
            for j in 0..k {
                let v: f64 = (0..k).map(|l| m[j][l] * src[l * 3 + ch] as f64).sum();
                dst[j * 3 + ch] = v as f32;
            }
        }
    }
    out
}

/// Write `g` as a graphdeco-layout binary `.ply` (normals written as 0).
pub fn write_ply(path: &Path, g: &ExportGaussians) -> Result<()> {
    let k = g.sh_coeffs.min(16);
    let k = [1usize, 4, 9, 16].into_iter().rev().find(|&c| c <= k).unwrap_or(1);
    let n = g.len();
    let sh: Vec<f32> = (0..n).flat_map(|i| g.sh[i * g.sh_coeffs * 3..(i * g.sh_coeffs + k) * 3].to_vec()).collect();
    let gd = map_coeffs(&fork_to_graphdeco_matrix(), &sh, k);
    let mut header = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"].iter().map(|s| s.to_string()).collect();
    names.extend((0..3 * (k - 1)).map(|i| format!("f_rest_{i}")));
    names.extend(["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"].iter().map(|s| s.to_string()));
    for nm in &names {
        header.push_str(&format!("property float {nm}\n"));
    }
    header.push_str("end_header\n");
    let err = |e| SplatError::File { path: path.display().to_string(), source: e };
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).map_err(err)?);
    f.write_all(header.as_bytes()).map_err(err)?;
    let mut row: Vec<f32> = Vec::with_capacity(names.len());
    for i in 0..n {
        row.clear();
        row.extend_from_slice(&g.means[i]);
        row.extend_from_slice(&[0.0; 3]);
        let c = &gd[i * k * 3..(i + 1) * k * 3];
        row.extend_from_slice(&[c[0], c[1], c[2]]);
        for ch in 0..3 {
            row.extend((1..k).map(|j| c[j * 3 + ch]));
        }
        let o = g.opacities[i].clamp(1e-6, 1.0 - 1e-6);
        row.push((o / (1.0 - o)).ln());
        row.extend(g.scales[i].iter().map(|s| s.max(1e-12).ln()));
        row.extend_from_slice(&g.quats[i]);
        for v in &row {
            f.write_all(&v.to_le_bytes()).map_err(err)?;
        }
    }
    f.flush().map_err(err)
}

#[derive(Clone, Copy)]
enum Ty {
    F32,
    F64,
    U8,
}

impl Ty {
    fn size(self) -> usize {
        match self {
            Ty::F32 => 4,
            Ty::F64 => 8,
            Ty::U8 => 1,
        }
    }
}

/// Read a binary little-endian 3DGS `.ply` (any SH degree, normals optional). SH degree > 3 is dropped
/// (the renderer ignores it); degrees ≤ 3 are mapped from graphdeco's basis to the renderer's.
pub fn read_ply(path: &Path) -> Result<ExportGaussians> {
    let err = |e| SplatError::File { path: path.display().to_string(), source: e };
    let mut r = BufReader::new(std::fs::File::open(path).map_err(err)?);
    let mut line = String::new();
    let mut props: Vec<(String, Ty)> = vec![];
    let mut n: Option<usize> = None;
    let mut in_vertex = false;
    let mut first = true;
    loop {
        line.clear();
        if r.read_line(&mut line).map_err(err)? == 0 {
            return Err(fmt_err(path, "header has no end_header"));
        }
        let l = line.trim();
        if first {
            if l != "ply" {
                return Err(fmt_err(path, "not a PLY file (missing 'ply' magic)"));
            }
            first = false;
            continue;
        }
        let tok: Vec<&str> = l.split_whitespace().collect();
        match tok.as_slice() {
            ["format", fmt, ..] => {
                if *fmt != "binary_little_endian" {
                    return Err(fmt_err(path, format!("format {fmt} unsupported; re-save as binary_little_endian")));
                }
            }
            ["element", name, count] => {
                in_vertex = *name == "vertex";
                if in_vertex {
                    n = Some(count.parse().map_err(|_| fmt_err(path, format!("bad vertex count '{count}'")))?);
                } else if n.is_none() {
                    return Err(fmt_err(path, "elements before 'vertex' are not supported"));
                }
            }
            ["property", ty, name] if in_vertex => {
                let t = match *ty {
                    "float" | "float32" => Ty::F32,
                    "double" | "float64" => Ty::F64,
                    "uchar" | "uint8" => Ty::U8,
                    other => return Err(fmt_err(path, format!("property {name}: type {other} unsupported"))),
                };
                props.push((name.to_string(), t));
            }
            ["end_header"] => break,
            _ => {}
        }
    }
    let n = n.ok_or_else(|| fmt_err(path, "no 'element vertex'"))?;
    let stride: usize = props.iter().map(|p| p.1.size()).sum();
    let mut data = vec![0u8; n.checked_mul(stride).ok_or_else(|| fmt_err(path, "vertex count too large"))?];
    r.read_exact(&mut data).map_err(|_| fmt_err(path, format!("file ends before {n} vertices of {stride} bytes")))?;
    let mut offs = std::collections::HashMap::new();
    let mut o = 0;
    for (name, t) in &props {
        offs.insert(name.clone(), (o, *t));
        o += t.size();
    }
    let col = |name: &str| -> Result<Vec<f32>> {
        let &(off, t) = offs.get(name).ok_or_else(|| fmt_err(path, format!("missing property '{name}'")))?;
        Ok((0..n)
            .map(|i| {
                let b = &data[i * stride + off..];
                match t {
                    Ty::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                    Ty::F64 => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32,
                    Ty::U8 => b[0] as f32 / 255.0,
                }
            })
            .collect())
    };
    let n_rest = (0..).take_while(|i| offs.contains_key(&format!("f_rest_{i}"))).count();
    if n_rest % 3 != 0 {
        return Err(fmt_err(path, format!("{n_rest} f_rest_* properties is not a multiple of 3")));
    }
    let k_file = n_rest / 3 + 1;
    let k = [1usize, 4, 9, 16].into_iter().rev().find(|&c| c <= k_file).unwrap_or(1);
    let (x, y, z) = (col("x")?, col("y")?, col("z")?);
    let dc = [col("f_dc_0")?, col("f_dc_1")?, col("f_dc_2")?];
    let rest: Vec<Vec<f32>> = (0..n_rest).map(|i| col(&format!("f_rest_{i}"))).collect::<Result<_>>()?;
    let op = col("opacity")?;
    let sc = [col("scale_0")?, col("scale_1")?, col("scale_2")?];
    let rot = [col("rot_0")?, col("rot_1")?, col("rot_2")?, col("rot_3")?];
    let per = k_file - 1;
    let mut gd = vec![0f32; n * k * 3];
    for i in 0..n {
        for ch in 0..3 {
            gd[(i * k) * 3 + ch] = dc[ch][i];
            for j in 1..k {
                gd[(i * k + j) * 3 + ch] = rest[ch * per + j - 1][i];
            }
        }
    }
    let sh = map_coeffs(&graphdeco_to_fork_matrix(k), &gd, k);
    Ok(ExportGaussians {
        means: (0..n).map(|i| [x[i], y[i], z[i]]).collect(),
        scales: (0..n).map(|i| [sc[0][i].exp(), sc[1][i].exp(), sc[2][i].exp()]).collect(),
        quats: (0..n)
            .map(|i| {
                let q = [rot[0][i], rot[1][i], rot[2][i], rot[3][i]];
                let nrm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
                if nrm > 0.0 && nrm.is_finite() {
                    q.map(|v| v / nrm)
                } else {
                    [1.0, 0.0, 0.0, 0.0]
                }
            })
            .collect(),
        opacities: op.iter().map(|&l| 1.0 / (1.0 + (-l).exp())).collect(),
        sh,
        sh_coeffs: k,
    })
}
