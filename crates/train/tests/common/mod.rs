//! A tiny training config on generated scenes, shared by the training tests.

#![allow(dead_code)]

use std::path::Path;

use mvsplat360_train::TrainConfig;

pub fn tiny_config(out: &Path, steps: u64, extra_train: &str) -> TrainConfig {
    let text = format!(
        r#"
[model]
width = 64
height = 64
[model.encoder]
d_feature = 32
num_depth_candidates = 16
costvolume_unet_feat_dim = 32
costvolume_unet_channel_mult = [1, 1]
costvolume_unet_attn_res = [2]
depth_unet_feat_dim = 32
depth_unet_channel_mult = [1, 1]
depth_unet_attn_res = []
num_transformer_layers = 1

[data]
sources = [{{ kind = "procedural", count = 4, seed = 7, views = 12 }}]
num_context = 3
num_target = 2

[train]
steps = {steps}
lr = 1e-3
accumulate = 2
seed = 5
lpips_weight = 0.0
checkpoint_every = 2
out = "{}"
{extra_train}
"#,
        out.display()
    );
    TrainConfig::from_toml(&text, Path::new("tiny.toml")).expect("tiny config parses")
}
