//! Multi-view Swin-style transformer (`multiview_transformer.py`): per block, windowed self-attention, then
//! windowed cross-attention whose keys/values are the block inputs of each view's nearest views, then an FFN on
//! `concat(source, message)`. Single head, bias-free projections, LayerNorm after each message.

use candle_core::{Device, Module, Result, Tensor};
use candle_nn::VarBuilder;

use crate::backbone::nn::{LayerNorm, LinearNoBias};
use crate::backbone::unimatch::utils::{shifted_window_labels, shifted_window_mask};
use mvsplat360_nn::activation::gelu;
use mvsplat360_nn::attention::{fused_attention, RegionMask};
use mvsplat360_nn::attention_bf16::fused_attention_bf16;
use mvsplat360_nn::softmax::masked_softmax;

/// Shifted-window mask for `m` key views: region labels for the fused inference kernel, and the dense additive
/// mask `[K·K, Lw, m·Lw]` (built only if the differentiable path asks for it).
#[derive(Debug)]
pub struct ShiftMask {
    region: RegionMask,
    geom: (usize, usize, usize, usize),
    device: Device,
    dense: std::sync::OnceLock<Tensor>,
}

impl ShiftMask {
    pub fn new(h: usize, w: usize, k: usize, m: usize, device: &Device) -> Self {
        let (q_labels, k_labels) = shifted_window_labels(h, w, k, m);
        Self { region: RegionMask { q_labels, k_labels, p: k * k }, geom: (h, w, k, m), device: device.clone(), dense: Default::default() }
    }

    fn dense(&self) -> Result<&Tensor> {
        if let Some(t) = self.dense.get() {
            return Ok(t);
        }
        let (h, w, k, m) = self.geom;
        let t = shifted_window_mask(h, w, k, m, &self.device)?;
        Ok(self.dense.get_or_init(|| t))
    }
}

/// Largest attention-score tensor (elements) materialised at once; bigger inputs are processed in view chunks.
const SCORE_CHUNK_ELEMS: usize = 48 << 20;

#[derive(Debug, Clone)]
pub struct TransformerLayer {
    q_proj: LinearNoBias,
    k_proj: LinearNoBias,
    v_proj: LinearNoBias,
    merge: LinearNoBias,
    norm1: LayerNorm,
    /// `mlp.0`, `mlp.2`, `norm2` (absent in the self-attention layer of a block).
    ffn: Option<(LinearNoBias, LinearNoBias, LayerNorm)>,
    with_shift: bool,
}

/// Geometry of one windowed attention call.
#[derive(Debug, Clone, Copy)]
pub struct WindowGeom {
    pub h: usize,
    pub w: usize,
    pub splits: usize,
}

impl TransformerLayer {
    pub fn new(vb: VarBuilder, d: usize, ffn_expansion: usize, with_ffn: bool, with_shift: bool) -> Result<Self> {
        let ffn = if with_ffn {
            let d_in = 2 * d;
            Some((
                LinearNoBias::new(vb.pp("mlp").pp("0"), d_in, d_in * ffn_expansion)?,
                LinearNoBias::new(vb.pp("mlp").pp("2"), d_in * ffn_expansion, d)?,
                LayerNorm::new(vb.pp("norm2"), d)?,
            ))
        } else {
            None
        };
        Ok(Self {
            q_proj: LinearNoBias::new(vb.pp("q_proj"), d, d)?,
            k_proj: LinearNoBias::new(vb.pp("k_proj"), d, d)?,
            v_proj: LinearNoBias::new(vb.pp("v_proj"), d, d)?,
            merge: LinearNoBias::new(vb.pp("merge"), d, d)?,
            norm1: LayerNorm::new(vb.pp("norm1"), d)?,
            ffn,
            with_shift,
        })
    }

    /// The projections and the MLP packed in bf16 (CPU inference); attention then multiplies in bf16, norms stay f32.
    pub fn pack_bf16(&mut self) -> Result<()> {
        for l in [&mut self.q_proj, &mut self.k_proj, &mut self.v_proj, &mut self.merge] {
            l.pack_bf16()?;
        }
        if let Some((fc1, fc2, _)) = &mut self.ffn {
            fc1.pack_bf16()?;
            fc2.pack_bf16()?;
        }
        Ok(())
    }

    /// `source [N, L, C]` queries; keys/values come from `kv_source [N', L, C]`: for self-attention `kv_source` is
    /// `source` and `rows` is `None`; for cross-attention `rows = (indices, m)` picks m key rows per query row
    /// (the projections are computed once per view and then gathered, which equals projecting the gathered
    /// features). `mask` is the shifted-window mask for this `m` (used only by shifted layers).
    pub fn forward(&self, source: &Tensor, kv_source: &Tensor, rows: Option<(&Tensor, usize)>, g: WindowGeom, mask: Option<&ShiftMask>) -> Result<Tensor> {
        let (n, l, c) = source.dims3()?;
        let prof = mvsplat360_nn::prof::scope("encoder.transformer.qkv");
        // Scale q rather than the scores (fewer elements; same value up to f32 rounding).
        let q = (self.q_proj.forward(source)? * (1.0 / (c as f64).sqrt()))?;
        let k = self.k_proj.forward(kv_source)?;
        let v = self.v_proj.forward(kv_source)?;
        drop(prof);
        let (k, v) = match rows {
            Some((idx, m)) => (k.index_select(idx, 0)?.reshape((n, m, l, c))?, v.index_select(idx, 0)?.reshape((n, m, l, c))?),
            None => (k.unsqueeze(1)?, v.unsqueeze(1)?),
        };
        let mask = if self.with_shift { mask } else { None };
        if self.with_shift && mask.is_none() {
            candle_core::bail!("shifted-window layer called without its attention mask");
        }
        let prof = mvsplat360_nn::prof::scope("encoder.transformer.attention");
        // Packed layers multiply attention in bf16 too (f32 where the CPU lacks the feature).
        let message = window_attention_as(&q, &k, &v, g, self.with_shift, mask, self.q_proj.weight.is_bf16())?;
        drop(prof);
        let prof = mvsplat360_nn::prof::scope("encoder.transformer.merge+norm");
        let message = self.norm1.forward(&self.merge.forward(&message)?)?;
        drop(prof);
        let _prof = mvsplat360_nn::prof::scope("encoder.transformer.mlp");
        let message = match &self.ffn {
            Some((fc1, fc2, norm2)) => {
                let h = fc1.forward(&Tensor::cat(&[source, &message], 2)?)?;
                let prof = mvsplat360_nn::prof::scope("encoder.transformer.mlp.gelu");
                let g = gelu(&h)?;
                drop((prof, h));
                norm2.forward(&fc2.forward(&g)?)?
            }
            None => message,
        };
        source + message
    }
}

/// Single-head windowed attention. `q [N, L, C]`, `k, v [N, m, L, C]`, L = h·w row-major.
pub fn window_attention(q: &Tensor, k: &Tensor, v: &Tensor, g: WindowGeom, shift: bool, mask: Option<&ShiftMask>) -> Result<Tensor> {
    window_attention_as(q, k, v, g, shift, mask, false)
}

/// [`window_attention`], its products in bf16 when `bf16` (inference: `attention_bf16::fused_attention_bf16`).
fn window_attention_as(q: &Tensor, k: &Tensor, v: &Tensor, g: WindowGeom, shift: bool, mask: Option<&ShiftMask>, bf16: bool) -> Result<Tensor> {
    let (n, l, c) = q.dims3()?;
    let m = k.dim(1)?;
    if ![q, k, v].iter().any(|t| t.track_op()) {
        return window_attention_fused(q, k, v, g, shift, mask, bf16);
    }
    let mask = match mask {
        Some(mk) if shift => Some(mk.dense()?),
        _ => None,
    };
    let (kw, lw) = (g.splits, l / (g.splits * g.splits));
    let rows_per_chunk = (SCORE_CHUNK_ELEMS / (kw * kw * lw * m * lw).max(1)).clamp(1, n.max(1));
    let mut outs = Vec::new();
    let mut start = 0;
    while start < n {
        let len = rows_per_chunk.min(n - start);
        outs.push(window_attention_chunk(&q.narrow(0, start, len)?, &k.narrow(0, start, len)?, &v.narrow(0, start, len)?, g, shift, mask)?);
        start += len;
    }
    let out = if outs.len() == 1 { outs.remove(0) } else { Tensor::cat(&outs, 0)? };
    debug_assert_eq!(out.dims(), &[n, l, c]);
    Ok(out)
}

/// Source row of every window-ordered token: destination order `(n, window, view, pos)`, source order
/// `(n, view, y, x)`, after rolling the map by `(-sh, -sw)` (Swin's cyclic shift). One row gather replaces
/// roll + split (and its inverse replaces merge + roll back).
fn window_rows(n: usize, m: usize, g: WindowGeom, sh: usize, sw: usize) -> Vec<u32> {
    let WindowGeom { h, w, splits: k } = g;
    let (hs, ws) = (h / k, w / k);
    let mut rows = Vec::with_capacity(n * m * h * w);
    for ni in 0..n {
        for wy in 0..k {
            for wx in 0..k {
                for vi in 0..m {
                    for py in 0..hs {
                        let y = (wy * hs + py + sh) % h;
                        for px in 0..ws {
                            let x = (wx * ws + px + sw) % w;
                            rows.push((((ni * m + vi) * h + y) * w + x) as u32);
                        }
                    }
                }
            }
        }
    }
    rows
}

fn invert(perm: &[u32]) -> Vec<u32> {
    let mut inv = vec![0u32; perm.len()];
    for (i, &p) in perm.iter().enumerate() {
        inv[p as usize] = i as u32;
    }
    inv
}

/// Inference path: the same window gathers, then one fused attention call (no score tensor).
fn window_attention_fused(q: &Tensor, k: &Tensor, v: &Tensor, g: WindowGeom, shift: bool, mask: Option<&ShiftMask>, bf16: bool) -> Result<Tensor> {
    let (n, l, c) = q.dims3()?;
    let m = k.dim(1)?;
    let WindowGeom { h, w, splits } = g;
    let (sh, sw) = if shift { (h / splits / 2, w / splits / 2) } else { (0, 0) };
    let kk = splits * splits;
    let lw = l / kk;
    let dev = q.device();
    let q_rows = window_rows(n, 1, g, sh, sw);
    let q_inv = Tensor::from_vec(invert(&q_rows), n * l, dev)?;
    let q_rows = Tensor::from_vec(q_rows, n * l, dev)?;
    let kv_rows = Tensor::from_vec(window_rows(n, m, g, sh, sw), n * m * l, dev)?;
    let qw = q.reshape((n * l, c))?.index_select(&q_rows, 0)?.reshape((n * kk, lw, c))?;
    let kw = k.reshape((n * m * l, c))?.index_select(&kv_rows, 0)?.reshape((n * kk, m * lw, c))?;
    let vw = v.reshape((n * m * l, c))?.index_select(&kv_rows, 0)?.reshape((n * kk, m * lw, c))?;
    let region = if shift { mask.map(|mk| &mk.region) } else { None };
    let _prof = mvsplat360_nn::prof::scope("encoder.transformer.attention.kernel");
    let out = if bf16 { fused_attention_bf16(&qw, &kw, &vw, region)? } else { fused_attention(&qw, &kw, &vw, region)? };
    out.reshape((n * l, c))?.index_select(&q_inv, 0)?.reshape((n, l, c))
}

fn window_attention_chunk(q: &Tensor, k: &Tensor, v: &Tensor, g: WindowGeom, shift: bool, mask: Option<&Tensor>) -> Result<Tensor> {
    let (n, l, c) = q.dims3()?;
    let m = k.dim(1)?;
    let WindowGeom { h, w, splits } = g;
    let (sh, sw) = if shift { (h / splits / 2, w / splits / 2) } else { (0, 0) };
    let kk = splits * splits;
    let lw = l / kk;
    let dev = q.device();
    let q_rows = window_rows(n, 1, g, sh, sw);
    let q_inv = Tensor::from_vec(invert(&q_rows), n * l, dev)?;
    let q_rows = Tensor::from_vec(q_rows, n * l, dev)?;
    let kv_rows = Tensor::from_vec(window_rows(n, m, g, sh, sw), n * m * l, dev)?;
    let qw = q.reshape((n * l, c))?.index_select(&q_rows, 0)?.reshape((n * kk, lw, c))?;
    // Keys of all m views for one window side by side: [n·kk, m·lw, c], view-major.
    let kw = k.reshape((n * m * l, c))?.index_select(&kv_rows, 0)?.reshape((n * kk, m * lw, c))?;
    let vw = v.reshape((n * m * l, c))?.index_select(&kv_rows, 0)?.reshape((n * kk, m * lw, c))?;
    // q arrives pre-scaled by 1/√c.
    let scores = qw.matmul(&kw.t()?)?;
    let attn = masked_softmax(&scores, if shift { mask } else { None })?;
    let out = attn.matmul(&vw)?; // [n·kk, lw, c]
    out.reshape((n * l, c))?.index_select(&q_inv, 0)?.reshape((n, l, c))
}

#[derive(Debug, Clone)]
pub struct TransformerBlock {
    pub self_attn: TransformerLayer,
    pub cross_attn_ffn: TransformerLayer,
}

#[derive(Debug, Clone)]
pub struct MultiViewFeatureTransformer {
    pub layers: Vec<TransformerBlock>,
    d_model: usize,
}

/// Row indices for the cross-attention keys: rows are `(v b)`; for row `v·B + b` the key rows are the nearest views
/// `nn[b, v, 1..]` of the same batch element (all other views in order when `nn` is `None`).
pub fn key_view_rows(b: usize, v: usize, nn: Option<&[Vec<Vec<u32>>]>) -> Result<(Vec<u32>, usize)> {
    let mut idx = Vec::new();
    let m = match nn {
        Some(nn) => nn.first().and_then(|r| r.first()).map(|r| r.len().saturating_sub(1)).unwrap_or(0),
        None => v.saturating_sub(1),
    };
    if m == 0 {
        candle_core::bail!("the multi-view transformer needs at least 2 views");
    }
    for vi in 0..v {
        for bi in 0..b {
            match nn {
                Some(nn) => {
                    let row = &nn[bi][vi];
                    for &o in &row[1..] {
                        idx.push(o * b as u32 + bi as u32);
                    }
                }
                None => {
                    for o in (0..v).filter(|&o| o != vi) {
                        idx.push((o * b + bi) as u32);
                    }
                }
            }
        }
    }
    Ok((idx, m))
}

impl MultiViewFeatureTransformer {
    /// `vb` = `encoder.backbone.transformer`.
    pub fn new(vb: VarBuilder, num_layers: usize, d_model: usize, ffn_expansion: usize) -> Result<Self> {
        let mut layers = Vec::with_capacity(num_layers);
        for i in 0..num_layers {
            let lvb = vb.pp("layers").pp(i);
            let shift = i % 2 == 1;
            layers.push(TransformerBlock {
                self_attn: TransformerLayer::new(lvb.pp("self_attn"), d_model, ffn_expansion, false, shift)?,
                cross_attn_ffn: TransformerLayer::new(lvb.pp("cross_attn_ffn"), d_model, ffn_expansion, true, shift)?,
            });
        }
        Ok(Self { layers, d_model })
    }

    /// Every block's projections and MLP packed in bf16 (CPU inference; see [`crate::bf16`]).
    pub fn pack_bf16(&mut self) -> Result<()> {
        for b in &mut self.layers {
            b.self_attn.pack_bf16()?;
            b.cross_attn_ffn.pack_bf16()?;
        }
        Ok(())
    }

    /// `features [B, V, C, h, w]` → `[B, V, C, h, w]`; also returns each block's output `[(v b), h·w, C]`.
    /// `nn` is `cameras_dist_index[b][v][..n]` (column 0 = the view itself).
    pub fn forward(&self, features: &Tensor, splits: usize, nn: Option<&[Vec<Vec<u32>>]>, keep_block_outputs: bool) -> Result<(Tensor, Vec<Tensor>)> {
        let (b, v, c, h, w) = features.dims5()?;
        if c != self.d_model {
            candle_core::bail!("transformer expects {} channels, got {c}", self.d_model);
        }
        let splits = splits.max(1);
        if h % splits != 0 || w % splits != 0 || (splits > 1 && (h / splits < 2 || w / splits < 2)) {
            candle_core::bail!("feature map {h}x{w} cannot be split into {splits}x{splits} shifted windows");
        }
        let g = WindowGeom { h, w, splits };
        let device = features.device();
        // (v b) rows of h·w tokens.
        let mut x = features.permute((1, 0, 3, 4, 2))?.reshape((v * b, h * w, c))?;
        let (rows, m) = key_view_rows(b, v, nn)?;
        let rows = Tensor::from_vec(rows, v * b * m, device)?;
        let self_mask = ShiftMask::new(h, w, splits, 1, device);
        let cross_mask = ShiftMask::new(h, w, splits, m, device);
        let mut kept = Vec::new();
        for block in &self.layers {
            let s = block.self_attn.forward(&x, &x, None, g, Some(&self_mask))?;
            // Keys/values: the block *input* of the nearest views (the official code gathers before self-attn).
            x = block.cross_attn_ffn.forward(&s, &x, Some((&rows, m)), g, Some(&cross_mask))?;
            if keep_block_outputs {
                kept.push(x.clone());
            }
        }
        let out = x.reshape((v, b, h, w, c))?.permute((1, 0, 4, 2, 3))?.contiguous()?;
        Ok((out, kept))
    }
}

/// Camera-centre distances `[B, V, V]` and, per row, the views sorted by distance (`torch.argsort`, ascending;
/// column 0 is the view itself). Computed on the host from the c2w translations.
pub fn camera_distances(extrinsics: &Tensor) -> Result<(Tensor, Vec<Vec<Vec<u32>>>)> {
    let (b, v, _, _) = extrinsics.dims4()?;
    let t = extrinsics.narrow(2, 0, 3)?.narrow(3, 3, 1)?.squeeze(3)?.to_dtype(candle_core::DType::F32)?;
    let t: Vec<Vec<Vec<f32>>> = t.to_vec3()?;
    let mut dist = vec![0f32; b * v * v];
    let mut index = Vec::with_capacity(b);
    for bi in 0..b {
        let mut rows = Vec::with_capacity(v);
        for i in 0..v {
            let mut d = vec![0f32; v];
            for j in 0..v {
                let s: f32 = (0..3).map(|k| (t[bi][i][k] - t[bi][j][k]).powi(2)).sum();
                d[j] = s.sqrt();
                dist[(bi * v + i) * v + j] = d[j];
            }
            let mut order: Vec<u32> = (0..v as u32).collect();
            // Ties (coincident cameras) keep the lower index, and the view itself always comes first.
            order.sort_by(|&a, &c| {
                let (a_, c_) = (a as usize, c as usize);
                (a_ != i).cmp(&(c_ != i)).then(d[a_].total_cmp(&d[c_])).then(a.cmp(&c))
            });
            rows.push(order);
        }
        index.push(rows);
    }
    Ok((Tensor::from_vec(dist, (b, v, v), &Device::Cpu)?.to_device(extrinsics.device())?, index))
}

/// `[B, V, K]` u32 tensor of a nested index (rows of equal length K).
pub fn index_tensor(index: &[Vec<Vec<u32>>], device: &Device) -> Result<Tensor> {
    let b = index.len();
    let v = index.first().map(|r| r.len()).unwrap_or(0);
    let k = index.first().and_then(|r| r.first()).map(|c| c.len()).unwrap_or(0);
    let flat: Vec<u32> = index.iter().flatten().flatten().copied().collect();
    Tensor::from_vec(flat, (b, v, k), device)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backbone::unimatch::utils::{merge_windows, split_windows};

    /// The row-gather window layout equals the literal roll → split (and merge → roll back) formulation.
    #[test]
    fn window_rows_equal_roll_and_split() -> Result<()> {
        let dev = Device::Cpu;
        let (n, m, h, w, c, k) = (2, 3, 8, 12, 5, 2);
        let g = WindowGeom { h, w, splits: k };
        let (sh, sw) = (h / k / 2, w / k / 2);
        let x = Tensor::arange(0f32, (n * m * h * w * c) as f32, &dev)?.reshape((n, m, h, w, c))?;
        let rows = Tensor::from_vec(window_rows(n, m, g, sh, sw), n * m * h * w, &dev)?;
        let got = x.reshape((n * m * h * w, c))?.index_select(&rows, 0)?.reshape((n * k * k, m * (h / k) * (w / k), c))?;
        let rolled = x.reshape((n * m, h, w, c))?.roll(-(sh as i32), 1)?.roll(-(sw as i32), 2)?;
        let lw = h * w / (k * k);
        let want = split_windows(&rolled, k)?.reshape((n, m, k * k, lw, c))?.transpose(1, 2)?.reshape((n * k * k, m * lw, c))?;
        let d = (got - &want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert_eq!(d, 0.0);
        // Inverse for a single view.
        let q = x.narrow(1, 0, 1)?.squeeze(1)?;
        let q_rows = window_rows(n, 1, g, sh, sw);
        let inv = Tensor::from_vec(invert(&q_rows), n * h * w, &dev)?;
        let qw = split_windows(&q.roll(-(sh as i32), 1)?.roll(-(sw as i32), 2)?, k)?;
        let back_lit = merge_windows(&qw, k, h, w)?.roll(sh as i32, 1)?.roll(sw as i32, 2)?;
        let back = qw.reshape((n * h * w, c))?.index_select(&inv, 0)?.reshape((n, h, w, c))?;
        let d = (back - &back_lit)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert_eq!(d, 0.0);
        let d = (back_lit - &q)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert_eq!(d, 0.0);
        Ok(())
    }

    /// The region labels used by the fused kernel give exactly the dense shifted-window mask (m = 1 and 2).
    #[test]
    fn shift_labels_equal_dense_mask() -> Result<()> {
        let (h, w, k) = (8, 12, 2);
        for m in [1usize, 2] {
            let dense: Vec<f32> = shifted_window_mask(h, w, k, m, &Device::Cpu)?.flatten_all()?.to_vec1()?;
            let (ql, kl) = shifted_window_labels(h, w, k, m);
            let lw = h * w / (k * k);
            let mut want = Vec::with_capacity(dense.len());
            for win in 0..k * k {
                for i in 0..lw {
                    for j in 0..m * lw {
                        want.push(if ql[win * lw + i] != kl[win * m * lw + j] { -100.0f32 } else { 0.0 });
                    }
                }
            }
            assert_eq!(dense, want, "m = {m}");
            assert!(dense.iter().any(|&x| x != 0.0));
        }
        Ok(())
    }

    /// Swin mask for one view: tokens of one region see each other (0), other regions get −100; unshifted
    /// windows in the top-left are all one region.
    #[test]
    fn shifted_mask_regions() -> Result<()> {
        let m = shifted_window_mask(8, 8, 2, 1, &Device::Cpu)?;
        let v: Vec<Vec<Vec<f32>>> = m.to_vec3()?;
        assert!(v[0].iter().flatten().all(|&x| x == 0.0));
        // Last window (bottom-right) has 4 regions of 2x2 tokens: token 0 (y0,x0) vs token 3 (y0,x3) differ.
        assert_eq!(v[3][0][3], -100.0);
        assert_eq!(v[3][0][1], 0.0);
        Ok(())
    }
}
