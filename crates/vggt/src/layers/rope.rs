//! `RotaryPositionEmbedding2D` and `PositionGetter`: the first half of each head's features rotates with the
//! token's row (y), the second with its column (x), base frequency 100. Special tokens (camera, registers)
//! sit at (0, 0) and patch (i, j) at (i + 1, j + 1), as the aggregator sets them.

use candle_core::{Device, Result, Tensor};

/// Positions of one frame's tokens: `special` tokens at (0, 0), then the `h × w` patches row-major at
/// (i + 1, j + 1).
pub fn frame_positions(special: usize, h: usize, w: usize) -> Vec<(u32, u32)> {
    let mut p = vec![(0, 0); special];
    for i in 0..h {
        for j in 0..w {
            p.push((i as u32 + 1, j as u32 + 1));
        }
    }
    p
}

/// The rotation tables `(cos, sin)`, `(L, head_dim)` each, for a sequence of positions.
pub struct RopeTables {
    pub cos: Tensor,
    pub sin: Tensor,
}

impl RopeTables {
    pub fn new(positions: &[(u32, u32)], head_dim: usize, base: f64, dev: &Device) -> Result<Self> {
        let (cos, sin) = mvsplat360_nn::rope::rope2d_tables(positions, head_dim, base);
        let l = positions.len();
        Ok(Self { cos: Tensor::from_vec(cos, (l, head_dim), dev)?, sin: Tensor::from_vec(sin, (l, head_dim), dev)? })
    }

    pub fn as_arg(&self) -> mvsplat360_nn::rope::Rope2dTables<'_> {
        mvsplat360_nn::rope::Rope2dTables { cos: &self.cos, sin: &self.sin }
    }
}
