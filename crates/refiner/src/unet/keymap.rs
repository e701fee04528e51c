//! diffusers `UNetSpatioTemporalConditionModel` names → sgm `VideoUNet` names (the names our model uses).
//!
//! One table of module prefixes, built from the config (block layout), plus per-module leaf renames.
//! Verified against the diffusers-layout fixture (`svd_unet.safetensors`: every key maps, every model key is
//! found) and, for sgm names, by construction from sgm `video_model.py` (input_blocks / middle_block /
//! output_blocks numbering; Stability's `svd.safetensors` and the MVSplat360 checkpoint use these names).

use crate::unet::VideoUNetConfig;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModuleKind {
    /// Identical leaf names (convs, norms).
    Plain,
    /// diffusers `TimestepEmbedding` (`linear_1`, `linear_2`) → sgm `Sequential` (`0`, `2`).
    Mlp,
    /// `SpatioTemporalResBlock` → `VideoResBlock`.
    ResBlock,
    /// `TransformerSpatioTemporalModel` → `SpatialVideoTransformer`.
    Transformer,
}

/// (diffusers module prefix, sgm module prefix, kind) for every module of the UNet.
pub fn unet_module_table(cfg: &VideoUNetConfig) -> Vec<(String, String, ModuleKind)> {
    use ModuleKind::*;
    let mut t: Vec<(String, String, ModuleKind)> = vec![
        ("conv_in".into(), "input_blocks.0.0".into(), Plain),
        ("time_embedding".into(), "time_embed".into(), Mlp),
        ("add_embedding".into(), "label_emb.0".into(), Mlp),
        ("conv_norm_out".into(), "out.0".into(), Plain),
        ("conv_out".into(), "out.2".into(), Plain),
        ("mid_block.resnets.0".into(), "middle_block.0".into(), ResBlock),
        ("mid_block.attentions.0".into(), "middle_block.1".into(), Transformer),
        ("mid_block.resnets.1".into(), "middle_block.2".into(), ResBlock),
    ];
    let levels = cfg.channel_mult.len();
    let nrb = cfg.num_res_blocks;
    let mut ds = 1;
    let mut idx = 1;
    for l in 0..levels {
        for j in 0..nrb {
            t.push((format!("down_blocks.{l}.resnets.{j}"), format!("input_blocks.{idx}.0"), ResBlock));
            if cfg.attention_resolutions.contains(&ds) {
                t.push((format!("down_blocks.{l}.attentions.{j}"), format!("input_blocks.{idx}.1"), Transformer));
            }
            idx += 1;
        }
        if l != levels - 1 {
            t.push((format!("down_blocks.{l}.downsamplers.0.conv"), format!("input_blocks.{idx}.0.op"), Plain));
            idx += 1;
            ds *= 2;
        }
    }
    let mut idx = 0;
    for (i, level) in (0..levels).rev().enumerate() {
        let attn = cfg.attention_resolutions.contains(&ds);
        for j in 0..=nrb {
            t.push((format!("up_blocks.{i}.resnets.{j}"), format!("output_blocks.{idx}.0"), ResBlock));
            if attn {
                t.push((format!("up_blocks.{i}.attentions.{j}"), format!("output_blocks.{idx}.1"), Transformer));
            }
            if level > 0 && j == nrb {
                let k = if attn { 2 } else { 1 };
                t.push((format!("up_blocks.{i}.upsamplers.0.conv"), format!("output_blocks.{idx}.{k}.conv"), Plain));
            }
            idx += 1;
        }
        if level > 0 {
            ds /= 2;
        }
    }
    t
}

/// Leaf rename inside a `SpatioTemporalResBlock` (`spatial_res_block`/`temporal_res_block` halves).
fn resblock_leaf(rest: &str) -> Option<String> {
    if rest == "time_mixer.mix_factor" {
        return Some(rest.into());
    }
    let (half, leaf) = if let Some(r) = rest.strip_prefix("spatial_res_block.") {
        ("", r)
    } else if let Some(r) = rest.strip_prefix("temporal_res_block.") {
        ("time_stack.", r)
    } else {
        return None;
    };
    let (module, param) = leaf.rsplit_once('.')?;
    let sgm = match module {
        "norm1" => "in_layers.0",
        "conv1" => "in_layers.2",
        "time_emb_proj" => "emb_layers.1",
        "norm2" => "out_layers.0",
        "conv2" => "out_layers.3",
        "conv_shortcut" => "skip_connection",
        _ => return None,
    };
    Some(format!("{half}{sgm}.{param}"))
}

fn mlp_leaf(rest: &str) -> Option<String> {
    let (module, param) = rest.rsplit_once('.')?;
    let i = match module {
        "linear_1" => "0",
        "linear_2" => "2",
        _ => return None,
    };
    Some(format!("{i}.{param}"))
}

fn transformer_leaf(rest: &str) -> Option<String> {
    if let Some(r) = rest.strip_prefix("temporal_transformer_blocks.") {
        return Some(format!("time_stack.{r}"));
    }
    if let Some(r) = rest.strip_prefix("time_pos_embed.") {
        return mlp_leaf(r).map(|s| format!("time_pos_embed.{s}"));
    }
    Some(rest.to_string())
}

/// sgm name for a diffusers UNet key, or None when the key is not part of the table (→ unexpected).
pub fn diffusers_to_sgm(name: &str, cfg: &VideoUNetConfig) -> Option<String> {
    for (d, s, kind) in unet_module_table(cfg) {
        let Some(rest) = name.strip_prefix(d.as_str()).and_then(|r| r.strip_prefix('.')) else { continue };
        let leaf = match kind {
            ModuleKind::Plain => Some(rest.to_string()),
            ModuleKind::Mlp => mlp_leaf(rest),
            ModuleKind::ResBlock => resblock_leaf(rest),
            ModuleKind::Transformer => transformer_leaf(rest),
        };
        return leaf.map(|l| format!("{s}.{l}"));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn real_svd_names_follow_sgm_numbering() {
        let cfg = VideoUNetConfig::default();
        let m = |n: &str| diffusers_to_sgm(n, &cfg);
        assert_eq!(m("conv_in.weight").as_deref(), Some("input_blocks.0.0.weight"));
        assert_eq!(m("down_blocks.0.downsamplers.0.conv.weight").as_deref(), Some("input_blocks.3.0.op.weight"));
        assert_eq!(m("down_blocks.3.resnets.1.spatial_res_block.conv1.bias").as_deref(), Some("input_blocks.11.0.in_layers.2.bias"));
        assert_eq!(m("down_blocks.1.resnets.0.temporal_res_block.time_emb_proj.weight").as_deref(), Some("input_blocks.4.0.time_stack.emb_layers.1.weight"));
        assert_eq!(m("up_blocks.0.upsamplers.0.conv.weight").as_deref(), Some("output_blocks.2.1.conv.weight"));
        assert_eq!(m("up_blocks.1.upsamplers.0.conv.weight").as_deref(), Some("output_blocks.5.2.conv.weight"));
        assert_eq!(
            m("up_blocks.3.attentions.2.temporal_transformer_blocks.0.ff_in.net.0.proj.weight").as_deref(),
            Some("output_blocks.11.1.time_stack.0.ff_in.net.0.proj.weight")
        );
        assert_eq!(m("mid_block.attentions.0.time_pos_embed.linear_2.bias").as_deref(), Some("middle_block.1.time_pos_embed.2.bias"));
        assert_eq!(m("add_embedding.linear_1.weight").as_deref(), Some("label_emb.0.0.weight"));
        assert_eq!(m("conv_norm_out.weight").as_deref(), Some("out.0.weight"));
        assert_eq!(m("down_blocks.3.attentions.0.norm.weight"), None);
        assert_eq!(m("nonsense.weight"), None);
    }
}
