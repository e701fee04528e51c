//! DETR-style sine position embedding (`PositionEmbeddingSine`, normalised, scale 2π, temperature 10000).

use candle_core::{Device, Result, Tensor};

/// Embedding of one `h × w` map: `[2·num_pos_feats, h, w]`, y-part first; channel 2i is sin, 2i+1 is cos of the
/// same frequency. Computed in f32 in the same operation order as the official code.
pub fn position_embedding_sine(num_pos_feats: usize, h: usize, w: usize, device: &Device) -> Result<Tensor> {
    let scale = 2.0 * std::f32::consts::PI;
    let eps = 1e-6f32;
    let dim_t: Vec<f32> = (0..num_pos_feats).map(|j| 10000f32.powf((2 * (j / 2)) as f32 / num_pos_feats as f32)).collect();
    let embed = |i: usize, n: usize| (i as f32 + 1.0) / (n as f32 + eps) * scale;
    let c = 2 * num_pos_feats;
    let mut out = vec![0f32; c * h * w];
    for y in 0..h {
        for x in 0..w {
            let (ye, xe) = (embed(y, h), embed(x, w));
            for (j, &d) in dim_t.iter().enumerate() {
                let (py, px) = (ye / d, xe / d);
                let (vy, vx) = if j % 2 == 0 { (py.sin(), px.sin()) } else { (py.cos(), px.cos()) };
                out[(j * h + y) * w + x] = vy;
                out[((num_pos_feats + j) * h + y) * w + x] = vx;
            }
        }
    }
    Tensor::from_vec(out, (c, h, w), device)
}

/// The embedding added per attention window (`feature_add_position_list` with `attn_splits` windows per axis):
/// every window gets the embedding of its own `h/K × w/K` grid. Returns `[C, h, w]`.
pub fn windowed_position_embedding(channels: usize, h: usize, w: usize, splits: usize, device: &Device) -> Result<Tensor> {
    let k = splits.max(1);
    if h % k != 0 || w % k != 0 {
        candle_core::bail!("feature map {h}x{w} is not divisible into {k}x{k} attention windows");
    }
    let (hs, ws) = (h / k, w / k);
    let pe = position_embedding_sine(channels / 2, hs, ws, device)?;
    // Tile [C, hs, ws] to [C, K·hs, K·ws].
    let row = Tensor::cat(&vec![&pe; k], 2)?;
    Tensor::cat(&vec![&row; k], 1)
}
