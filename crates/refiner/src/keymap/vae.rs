//! diffusers `AutoencoderKLTemporalDecoder` names → sgm `AutoencodingEngine` names (the names our VAE uses).
//!
//! | diffusers | sgm |
//! |---|---|
//! | `encoder.down_blocks.{i}.resnets.{j}.*` | `encoder.down.{i}.block.{j}.*` |
//! | `encoder.down_blocks.{i}.downsamplers.0.conv` | `encoder.down.{i}.downsample.conv` |
//! | `{en,de}coder.mid_block.resnets.{0,1}` | `{en,de}coder.mid.block_{1,2}` |
//! | `{en,de}coder.mid_block.attentions.0.{group_norm,to_q,to_k,to_v,to_out.0}` | `….mid.attn_1.{norm,q,k,v,proj_out}` (Linear → 1×1 conv) |
//! | `decoder.up_blocks.{i}.resnets.{j}` | `decoder.up.{L-1-i}.block.{j}` |
//! | `decoder.up_blocks.{i}.upsamplers.0.conv` | `decoder.up.{L-1-i}.upsample.conv` |
//! | `….conv_shortcut` (ResnetBlock) | `….nin_shortcut` |
//! | `spatial_res_block.{norm1,conv1,norm2,conv2}` | same leaf on the block |
//! | `temporal_res_block.{norm1,conv1,norm2,conv2}` | `time_stack.{in_layers.0,in_layers.2,out_layers.0,out_layers.3}` |
//! | `time_mixer.mix_factor` | `mix_factor` |
//! | `{en,de}coder.conv_norm_out` | `{en,de}coder.norm_out` |
//! | `decoder.time_conv_out` | `decoder.conv_out.time_mix_conv` |
//! | `quant_conv` | `quant_conv` (sgm `AutoencodingEngine` has none: config `use_quant_conv`) |
//!
//! Verified against the diffusers-layout fixture (`svd_vae.safetensors`: every key maps, every model key is
//! found, decoded/encoded outputs match). The sgm side follows sgm `model.py` / `temporal_ae.py` module names
//! (what `first_stage_model.*` in svd.safetensors and the MVSplat360 checkpoint hold).

use crate::weights::Piece;

fn resnet_leaf(module: &str) -> Option<&'static str> {
    Some(match module {
        "norm1" => "norm1",
        "conv1" => "conv1",
        "norm2" => "norm2",
        "conv2" => "conv2",
        "conv_shortcut" => "nin_shortcut",
        _ => return None,
    })
}

/// `ResnetBlock2D` leaf (`norm1.weight`, `conv_shortcut.bias`, …) → sgm `ResnetBlock` leaf.
fn resnet(rest: &str) -> Option<String> {
    let (module, param) = rest.rsplit_once('.')?;
    Some(format!("{}.{param}", resnet_leaf(module)?))
}

/// `SpatioTemporalResBlock` leaf → sgm `VideoResBlock` leaf.
fn video_resnet(rest: &str) -> Option<String> {
    if rest == "time_mixer.mix_factor" {
        return Some("mix_factor".into());
    }
    if let Some(r) = rest.strip_prefix("spatial_res_block.") {
        return resnet(r);
    }
    let r = rest.strip_prefix("temporal_res_block.")?;
    let (module, param) = r.rsplit_once('.')?;
    let sgm = match module {
        "norm1" => "in_layers.0",
        "conv1" => "in_layers.2",
        "norm2" => "out_layers.0",
        "conv2" => "out_layers.3",
        _ => return None,
    };
    Some(format!("time_stack.{sgm}.{param}"))
}

/// diffusers VAE `Attention` leaf → sgm `AttnBlock` leaf (Linear weights become 1×1 conv weights).
fn attn(rest: &str) -> Option<(String, Piece)> {
    let (module, param) = rest.rsplit_once('.')?;
    let sgm = match module {
        "group_norm" => return Some((format!("norm.{param}"), Piece::Whole)),
        "to_q" => "q",
        "to_k" => "k",
        "to_v" => "v",
        "to_out.0" => "proj_out",
        _ => return None,
    };
    Some((format!("{sgm}.{param}"), if param == "weight" { Piece::Reshape } else { Piece::Whole }))
}

/// (index, rest) from `"{index}.{rest}"`.
fn split_index(s: &str) -> Option<(usize, &str)> {
    let (i, rest) = s.split_once('.')?;
    Some((i.parse().ok()?, rest))
}

/// sgm name (and how to read it) for a diffusers VAE key; `levels` = `len(block_out_channels)`.
/// None = no sgm counterpart (reported as unexpected).
pub fn diffusers_to_sgm(name: &str, levels: usize) -> Option<(String, Piece)> {
    let whole = |s: String| Some((s, Piece::Whole));
    if let Some(p) = name.strip_prefix("quant_conv.") {
        return whole(format!("quant_conv.{p}"));
    }
    let (part, rest) = if let Some(r) = name.strip_prefix("encoder.") {
        ("encoder", r)
    } else if let Some(r) = name.strip_prefix("decoder.") {
        ("decoder", r)
    } else {
        return None;
    };
    let dec = part == "decoder";
    for (d, s) in [("conv_in.", "conv_in."), ("conv_norm_out.", "norm_out.")] {
        if let Some(p) = rest.strip_prefix(d) {
            return whole(format!("{part}.{s}{p}"));
        }
    }
    if let Some(p) = rest.strip_prefix("conv_out.") {
        return whole(format!("{part}.conv_out.{p}"));
    }
    if let Some(p) = rest.strip_prefix("time_conv_out.") {
        return if dec { whole(format!("decoder.conv_out.time_mix_conv.{p}")) } else { None };
    }
    if let Some(r) = rest.strip_prefix("mid_block.") {
        if let Some(r) = r.strip_prefix("attentions.0.") {
            return attn(r).map(|(s, p)| (format!("{part}.mid.attn_1.{s}"), p));
        }
        let (j, r) = split_index(r.strip_prefix("resnets.")?)?;
        if j > 1 {
            return None;
        }
        let leaf = if dec { video_resnet(r)? } else { resnet(r)? };
        return whole(format!("{part}.mid.block_{}.{leaf}", j + 1));
    }
    if !dec {
        let (i, r) = split_index(rest.strip_prefix("down_blocks.")?)?;
        if i >= levels {
            return None;
        }
        if let Some(p) = r.strip_prefix("downsamplers.0.conv.") {
            return whole(format!("encoder.down.{i}.downsample.conv.{p}"));
        }
        let (j, r) = split_index(r.strip_prefix("resnets.")?)?;
        return whole(format!("encoder.down.{i}.block.{j}.{}", resnet(r)?));
    }
    let (i, r) = split_index(rest.strip_prefix("up_blocks.")?)?;
    if i >= levels {
        return None;
    }
    let level = levels - 1 - i;
    if let Some(p) = r.strip_prefix("upsamplers.0.conv.") {
        return whole(format!("decoder.up.{level}.upsample.conv.{p}"));
    }
    let (j, r) = split_index(r.strip_prefix("resnets.")?)?;
    whole(format!("decoder.up.{level}.block.{j}.{}", video_resnet(r)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn real_svd_vae_names_follow_sgm_modules() {
        let m = |n: &str| diffusers_to_sgm(n, 4).map(|(s, _)| s);
        assert_eq!(m("encoder.down_blocks.1.resnets.0.conv_shortcut.weight").as_deref(), Some("encoder.down.1.block.0.nin_shortcut.weight"));
        assert_eq!(m("encoder.down_blocks.2.downsamplers.0.conv.bias").as_deref(), Some("encoder.down.2.downsample.conv.bias"));
        assert_eq!(m("encoder.mid_block.resnets.1.norm2.weight").as_deref(), Some("encoder.mid.block_2.norm2.weight"));
        assert_eq!(m("encoder.conv_norm_out.bias").as_deref(), Some("encoder.norm_out.bias"));
        assert_eq!(m("decoder.up_blocks.0.resnets.2.temporal_res_block.conv2.weight").as_deref(), Some("decoder.up.3.block.2.time_stack.out_layers.3.weight"));
        assert_eq!(m("decoder.up_blocks.3.resnets.0.spatial_res_block.conv_shortcut.bias").as_deref(), Some("decoder.up.0.block.0.nin_shortcut.bias"));
        assert_eq!(m("decoder.up_blocks.1.upsamplers.0.conv.weight").as_deref(), Some("decoder.up.2.upsample.conv.weight"));
        assert_eq!(m("decoder.mid_block.resnets.0.time_mixer.mix_factor").as_deref(), Some("decoder.mid.block_1.mix_factor"));
        assert_eq!(m("decoder.time_conv_out.weight").as_deref(), Some("decoder.conv_out.time_mix_conv.weight"));
        assert_eq!(diffusers_to_sgm("decoder.mid_block.attentions.0.to_out.0.weight", 4), Some(("decoder.mid.attn_1.proj_out.weight".into(), Piece::Reshape)));
        assert_eq!(diffusers_to_sgm("encoder.mid_block.attentions.0.to_q.bias", 4), Some(("encoder.mid.attn_1.q.bias".into(), Piece::Whole)));
        assert_eq!(m("encoder.time_conv_out.weight"), None);
        assert_eq!(m("decoder.up_blocks.4.resnets.0.spatial_res_block.conv1.weight"), None);
        assert_eq!(m("post_quant_conv.weight"), None);
    }
}
