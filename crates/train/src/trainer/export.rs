//! A checkpoint written out as a model folder (`--export`).

use super::*;

/// Whether a checkpoint was written with `cfg`, compared as parsed configs, so that a field added later with its
/// default value does not block a resume or an export.
pub(super) fn written_with(ck: &checkpoint::Loaded, cfg: &TrainConfig) -> bool {
    ck.state.config == cfg.to_toml() || TrainConfig::from_toml(&ck.state.config, &ck.path).is_ok_and(|c| c == *cfg)
}

/// Write the checkpoint of `step` (the newest when `None`) in `cfg`'s `train.out` as a model folder: `to`, or
/// `<out>/model-<step>`. The checkpoint must have been written with `cfg` (as for `--resume`). Returns the step
/// and the folder.
pub fn export_checkpoint(cfg: &TrainConfig, step: Option<u64>, to: Option<&std::path::Path>) -> Result<(u64, PathBuf)> {
    let out = &cfg.train.out;
    let ck = checkpoint::load_step(out, step)?;
    if !written_with(&ck, cfg) {
        return Err(TrainError::Checkpoint(format!(
            "{} was written with a different config; export with the config the run was started with",
            ck.path.display()
        )));
    }
    let model = Model::new(cfg)?;
    model.load_state_dict(&ck.model)?;
    let dir = to.map(PathBuf::from).unwrap_or_else(|| out.join(format!("model-{}", ck.state.step)));
    mvsplat360_pipeline::model::write_model_dir(&dir, &model.model_config(), &model.model_tensors()?)?;
    Ok((ck.state.step, dir))
}
