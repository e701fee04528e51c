//! transformers `CLIPVisionModelWithProjection` names → open_clip `VisionTransformer` names (our layout).
//!
//! | transformers | open_clip |
//! |---|---|
//! | `vision_model.embeddings.patch_embedding.weight` | `conv1.weight` (no bias in either) |
//! | `vision_model.embeddings.class_embedding` | `class_embedding` |
//! | `vision_model.embeddings.position_embedding.weight` | `positional_embedding` |
//! | `vision_model.pre_layrnorm` / `post_layernorm` | `ln_pre` / `ln_post` |
//! | `vision_model.encoder.layers.N.layer_norm{1,2}` | `transformer.resblocks.N.ln_{1,2}` |
//! | `….self_attn.{q,k,v}_proj.{weight,bias}` | `….attn.in_proj_{weight,bias}` = concat(q, k, v) along dim 0 |
//! | `….self_attn.out_proj` | `….attn.out_proj` |
//! | `….mlp.fc1` / `mlp.fc2` | `….mlp.c_fc` / `mlp.c_proj` |
//! | `visual_projection.weight` (out, in) | `proj` (in, out) = its transpose |
//!
//! `vision_model.embeddings.position_ids` (a buffer in older files) is ignored. Verified against the
//! transformers-layout fixture (`svd_clip_vision.safetensors`: every key maps, every model key is found,
//! embeddings match) and against open_clip `transformer.py` module names for the official layout.

use crate::weights::Piece;

/// `Some(Some((open_clip name, piece)))`, `Some(None)` for a buffer to ignore, `None` if unknown.
pub fn transformers_to_open_clip(name: &str) -> Option<Option<(String, Piece)>> {
    let whole = |s: &str| Some(Some((s.to_string(), Piece::Whole)));
    match name {
        "visual_projection.weight" => return Some(Some(("proj".into(), Piece::Transpose))),
        "vision_model.embeddings.patch_embedding.weight" => return whole("conv1.weight"),
        "vision_model.embeddings.class_embedding" => return whole("class_embedding"),
        "vision_model.embeddings.position_embedding.weight" => return whole("positional_embedding"),
        "vision_model.embeddings.position_ids" => return Some(None),
        _ => {}
    }
    let rest = name.strip_prefix("vision_model.")?;
    for (t, o) in [("pre_layrnorm.", "ln_pre."), ("post_layernorm.", "ln_post.")] {
        if let Some(p) = rest.strip_prefix(t) {
            return Some(Some((format!("{o}{p}"), Piece::Whole)));
        }
    }
    let (i, r) = rest.strip_prefix("encoder.layers.")?.split_once('.')?;
    let i: usize = i.parse().ok()?;
    let (module, param) = r.rsplit_once('.')?;
    let block = format!("transformer.resblocks.{i}");
    let qkv = |index: usize| Some(Some((format!("{block}.attn.in_proj_{param}"), Piece::Concat { index, of: 3 })));
    let leaf = match module {
        "self_attn.q_proj" => return qkv(0),
        "self_attn.k_proj" => return qkv(1),
        "self_attn.v_proj" => return qkv(2),
        "layer_norm1" => "ln_1",
        "layer_norm2" => "ln_2",
        "self_attn.out_proj" => "attn.out_proj",
        "mlp.fc1" => "mlp.c_fc",
        "mlp.fc2" => "mlp.c_proj",
        _ => return None,
    };
    Some(Some((format!("{block}.{leaf}.{param}"), Piece::Whole)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vit_h_names_follow_open_clip() {
        let m = |n: &str| transformers_to_open_clip(n).flatten();
        assert_eq!(
            m("vision_model.encoder.layers.31.self_attn.v_proj.bias"),
            Some(("transformer.resblocks.31.attn.in_proj_bias".into(), Piece::Concat { index: 2, of: 3 }))
        );
        assert_eq!(m("vision_model.encoder.layers.0.mlp.fc2.weight"), Some(("transformer.resblocks.0.mlp.c_proj.weight".into(), Piece::Whole)));
        assert_eq!(m("vision_model.encoder.layers.4.self_attn.out_proj.weight"), Some(("transformer.resblocks.4.attn.out_proj.weight".into(), Piece::Whole)));
        assert_eq!(m("vision_model.pre_layrnorm.bias"), Some(("ln_pre.bias".into(), Piece::Whole)));
        assert_eq!(m("visual_projection.weight"), Some(("proj".into(), Piece::Transpose)));
        assert_eq!(transformers_to_open_clip("vision_model.embeddings.position_ids"), Some(None));
        assert_eq!(transformers_to_open_clip("vision_model.encoder.layers.0.self_attn.qkv.weight"), None);
        assert_eq!(transformers_to_open_clip("text_model.final_layer_norm.weight"), None);
    }
}
