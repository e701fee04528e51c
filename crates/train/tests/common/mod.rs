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

/// One example from `cfg`'s first source: the scene drawn with `seed`, 3 context views by farthest-point
/// sampling on the whole loop, `num_target` targets, a random flip when `flip`; at `cfg`'s near/far.
pub fn example(cfg: &TrainConfig, seed: u64, num_target: usize, flip: bool) -> mvsplat360_train::trainer::Example {
    use rand::SeedableRng;
    let mut src = mvsplat360_train::scenes::SceneSource::open(&cfg.data.sources[0], cfg.model.width, cfg.model.height, 64).unwrap();
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let scene = src.draw(&mut rng, 0, 0).unwrap();
    let s = mvsplat360_train::sampler::SamplerSettings { num_context: 3, num_target, gap: None, gap_initial: None, warm_up: 0.0, closed_loop: true, flip };
    mvsplat360_train::trainer::make_example(&scene, &s, cfg.model.near, cfg.model.far, &mut rng).unwrap().unwrap()
}

/// The tiny refiner of `pipeline::model::tiny_config`, as TOML (unspecified fields = MVSplat360's).
pub const TINY_REFINER: &str = r#"
[model.refiner.unet]
model_channels = 32
num_res_blocks = 1
attention_resolutions = [1, 2]
channel_mult = [1, 2]
num_head_channels = 16
context_dim = 32
adm_in_channels = 32
[model.refiner.vae]
ch = 32
ch_mult = [1, 1, 2, 2]
num_res_blocks = 1
[model.refiner.clip]
width = 32
layers = 2
heads = 2
mlp_width = 64
patch_size = 8
image_size = 32
output_dim = 32
"#;

pub fn with_refiner(out: &std::path::Path, steps: u64, extra_train: &str) -> TrainConfig {
    let base = tiny_config(out, steps, extra_train);
    let text = base.to_toml().replacen("[data]", &format!("{TINY_REFINER}\n[data]"), 1);
    TrainConfig::from_toml(&text, std::path::Path::new("tiny-refiner.toml")).expect("refiner config parses")
}
