//! The model being trained: the encoder's variables (seeded or from `train.init`) and, for the refiner and VAE
//! stages, their networks.

use super::*;

/// Everything trainable, built from a config.
pub struct Model {
    pub varmap: VarMap,
    pub encoder: EncoderCostVolume,
    /// Present with `[model.refiner]` (stage `model`).
    pub refiner: Option<TrainRefiner>,
    /// Stage `vae`: the autoencoder being trained (the encoder is then not trained).
    pub vae: Option<crate::vae_stage::TrainVae>,
    pub cfg: TrainConfig,
}

impl Model {
    /// The encoder with seeded initial weights, or `train.init`'s; the refiner (if configured) from
    /// `train.refiner_init` or seeded random weights written to `train.out`.
    pub fn new(cfg: &TrainConfig) -> Result<Self> {
        Self::new_on(cfg, &Device::Cpu)
    }

    /// As [`Model::new`], with the encoder's weights on `dev`. The initial weights are drawn on the host, so a
    /// seed gives the same model on every device.
    pub fn new_on(cfg: &TrainConfig, dev: &Device) -> Result<Self> {
        let ecfg = cfg.encoder();
        let varmap = VarMap::new();
        let encoder = EncoderCostVolume::new(VarBuilder::from_varmap(&varmap, DType::F32, dev).pp("encoder"), &ecfg)?;
        let init = mvsplat360_encoder::weights::random_tensors(cfg.train.seed, &Device::Cpu, |vb| EncoderCostVolume::new(vb.pp("encoder"), &ecfg))?;
        {
            let data = varmap.data().lock().map_err(|_| TrainError::Data("varmap poisoned".into()))?;
            for (name, var) in data.iter() {
                var.set(&init[name].to_device(dev)?)?;
            }
        }
        let vae_stage = cfg.train.stage == crate::config::Stage::Vae;
        let vae = match &cfg.model.refiner {
            Some(r) if vae_stage => Some(crate::vae_stage::TrainVae::new(&r.vae, cfg.train.refiner_init.as_deref(), cfg.train.seed, dev)?),
            _ => None,
        };
        let refiner = match &cfg.model.refiner {
            Some(_) if vae_stage => None,
            Some(r) => {
                std::fs::create_dir_all(&cfg.train.out).map_err(|e| TrainError::Write { path: cfg.train.out.clone(), msg: e.to_string() })?;
                Some(TrainRefiner::new(r, cfg.train.refiner_init.as_deref(), cfg.train.seed, &cfg.train.out, dev)?)
            }
            None => None,
        };
        let m = Self { varmap, encoder, refiner, vae, cfg: cfg.clone() };
        if let Some(p) = &cfg.train.init {
            crate::init::load_into(&m.varmap, p)?;
        }
        Ok(m)
    }

    /// (name, var) of what this run trains, sorted by name.
    pub fn vars(&self) -> Vec<(String, Var)> {
        if let Some(v) = &self.vae {
            let mut v = v.vars.clone();
            v.sort_by(|a, b| a.0.cmp(&b.0));
            return v;
        }
        let data = self.varmap.data().lock().expect("varmap lock");
        let mut v: Vec<(String, Var)> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        if let Some(r) = &self.refiner {
            v.extend(r.unet_vars.iter().cloned());
        }
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }

    /// The trainable weights, on the host.
    pub fn state_dict(&self) -> Result<Vec<(String, Tensor)>> {
        self.vars().into_iter().map(|(k, v)| Ok((k, v.as_tensor().detach().to_device(&Device::Cpu)?))).collect()
    }

    pub fn load_state_dict(&self, sd: &std::collections::HashMap<String, Tensor>) -> Result<()> {
        for (name, var) in self.vars() {
            let t = sd.get(&name).ok_or_else(|| TrainError::Checkpoint(format!("model weights lack `{name}`")))?;
            if t.dims() != var.dims() {
                return Err(TrainError::Checkpoint(format!("`{name}` has shape {:?}, the model {:?}", t.dims(), var.dims())));
            }
            var.set(&t.to_dtype(DType::F32)?.to_device(var.device())?)?;
        }
        Ok(())
    }

    /// Everything a model folder holds: the trained weights and the refiner's frozen VAE and CLIP. Stage `vae`:
    /// the encoder as initialised, the trained autoencoder, a seeded random UNet and CLIP (a `refiner_init`).
    pub fn model_tensors(&self) -> Result<Vec<(String, Tensor)>> {
        if let (Some(v), Some(r)) = (&self.vae, &self.cfg.model.refiner) {
            let data = self.varmap.data().lock().map_err(|_| TrainError::Data("varmap poisoned".into()))?;
            let mut t: Vec<(String, Tensor)> =
                data.iter().map(|(k, var)| Ok((k.clone(), var.as_tensor().detach().to_device(&Device::Cpu)?))).collect::<Result<_>>()?;
            let trained: std::collections::HashMap<&str, &Var> = v.vars.iter().map(|(k, var)| (k.as_str(), var)).collect();
            let rest = mvsplat360_refiner::state_dict::random_refiner_state_dict(&r.unet, &r.vae, &r.clip, self.cfg.train.seed.wrapping_add(17))
                .map_err(|msg| TrainError::Config { path: PathBuf::from("model.refiner"), msg })?;
            for (k, x) in rest {
                match trained.get(k.as_str()) {
                    Some(var) => t.push((k, var.as_tensor().detach().to_device(&Device::Cpu)?)),
                    None => t.push((k, x)),
                }
            }
            return Ok(t);
        }
        let mut t = self.state_dict()?;
        if let Some(r) = &self.refiner {
            t.extend(r.frozen().iter().cloned());
        }
        Ok(t)
    }

    /// The model-folder config of this model.
    pub fn model_config(&self) -> ModelConfig {
        let m = &self.cfg.model;
        ModelConfig {
            format: MODEL_FORMAT.into(),
            data: DataConfig { experiment: m.experiment.clone(), image_width: m.width, image_height: m.height, near: m.near, far: m.far },
            encoder: self.cfg.encoder(),
            refiner: self.cfg.model.refiner.clone(),
            fit: self.cfg.model.fit,
            // The blender is trained apart from the encoder (the `blend` example) and added to a folder by hand.
            blend: None,
            // Training brings every scene to model units by `auto` (`example_from_views`).
            scene_scale: Some("auto".into()),
        }
    }
}
