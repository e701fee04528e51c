//! Multi-view backbone (`backbone/backbone_multiview.py`): UniMatch CNN at 1/4 resolution, windowed sine
//! position embedding, multi-view Swin transformer with nearest-view cross-attention.

pub mod multiview_transformer;
pub mod nn;
pub mod unimatch;

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

pub use multiview_transformer::{camera_distances, index_tensor, MultiViewFeatureTransformer};
use unimatch::backbone::CnnEncoder;
use unimatch::position::windowed_position_embedding;

const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

#[derive(Debug, Clone)]
pub struct BackboneMultiview {
    pub backbone: CnnEncoder,
    pub transformer: MultiViewFeatureTransformer,
    feature_channels: usize,
}

/// Backbone outputs (and, on request, the intermediates the parity tests compare).
#[derive(Debug, Clone)]
pub struct BackboneOutput {
    /// `[B, V, C, h, w]` transformer features.
    pub trans_features: Tensor,
    /// `[B, V, C, h, w]` CNN features.
    pub cnn_features: Tensor,
    /// `[B, V, C, h, w]` CNN features + windowed position embedding (present when intermediates were requested).
    pub transformer_input: Option<Tensor>,
    /// Each block's output `[(v b), h·w, C]` (empty unless requested).
    pub block_outputs: Vec<Tensor>,
}

/// `(x − mean) / std` per RGB channel, `x [.., 3, H, W]` in [0, 1].
pub fn normalize_images(images: &Tensor) -> Result<Tensor> {
    let rank = images.rank();
    let mut shape = vec![1usize; rank];
    shape[rank - 3] = 3;
    let dev = images.device();
    let mean = Tensor::new(&IMAGENET_MEAN, dev)?.reshape(shape.clone())?;
    let std = Tensor::new(&IMAGENET_STD, dev)?.reshape(shape)?;
    images.broadcast_sub(&mean)?.broadcast_div(&std)
}

impl BackboneMultiview {
    /// `vb` = `encoder.backbone`; the CNN at the official widths.
    pub fn new(vb: VarBuilder, feature_channels: usize, num_layers: usize, ffn_expansion: usize) -> Result<Self> {
        Self::with_cnn_dims(vb, unimatch::backbone::FEATURE_DIMS, feature_channels, num_layers, ffn_expansion)
    }

    /// [`Self::new`] with other CNN stage widths (`cnn_feature_dims`).
    pub fn with_cnn_dims(vb: VarBuilder, cnn_dims: [usize; 3], feature_channels: usize, num_layers: usize, ffn_expansion: usize) -> Result<Self> {
        Ok(Self {
            backbone: CnnEncoder::new(vb.pp("backbone"), cnn_dims, feature_channels)?,
            transformer: MultiViewFeatureTransformer::new(vb.pp("transformer"), num_layers, feature_channels, ffn_expansion)?,
            feature_channels,
        })
    }

    /// The CNN's and the transformer's weights packed in bf16 (CPU inference; see [`crate::bf16`]).
    pub fn pack_bf16(&mut self) -> Result<()> {
        self.backbone.pack_bf16()?;
        self.transformer.pack_bf16()
    }

    /// `images [B, V, 3, H, W]` in [0, 1]; `nn` = nearest-view index rows (column 0 = self), already cut to
    /// `multiview_trans_nearest_n_views` columns.
    pub fn forward(&self, images: &Tensor, splits: usize, nn: Option<&[Vec<Vec<u32>>]>, intermediates: bool) -> Result<BackboneOutput> {
        let (b, v, c3, hh, ww) = images.dims5()?;
        if c3 != 3 {
            candle_core::bail!("backbone expects RGB images [B,V,3,H,W], got {:?}", images.dims());
        }
        let mut t = std::time::Instant::now();
        let x = normalize_images(images)?.reshape((b * v, 3, hh, ww))?;
        let f = self.backbone.forward(&x)?;
        mvsplat360_nn::prof::lap("encoder.cnn", &mut t);
        let (_, c, h, w) = f.dims4()?;
        let cnn_features = f.reshape((b, v, c, h, w))?;
        let pos = windowed_position_embedding(self.feature_channels, h, w, splits, images.device())?;
        let input = cnn_features.broadcast_add(&pos)?;
        let (trans_features, block_outputs) = self.transformer.forward(&input, splits, nn, intermediates)?;
        mvsplat360_nn::prof::lap("encoder.transformer", &mut t);
        Ok(BackboneOutput { trans_features, cnn_features, transformer_input: if intermediates { Some(input) } else { None }, block_outputs })
    }
}
