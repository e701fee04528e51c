//! A job's settings, as the page sends them and `render` takes them; each value is checked before it becomes an
//! argument (no value may pass for a flag).

use serde::{Deserialize, Serialize};

/// The page's choices; the defaults are the CLI's.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Settings {
    /// `default` (the shipped model), a path, or a name from `mvsplat360 weights list` (`dl3dv`, `hf:…`).
    pub weights: String,
    /// `auto`, `colmap` or `vggt` (a video or bare photos only).
    pub engine: String,
    /// VGGT weights (a path or name) for `vggt`, or for `auto` on a few photos; empty: none.
    pub vggt_weights: String,
    /// Context views (farthest-point sampled).
    pub context_views: usize,
    /// Frames of the 360° orbit.
    pub orbit_frames: usize,
    /// Refiner sampling steps; 0: no refiner (the 3DGS frames).
    pub refiner_steps: usize,
    /// `auto`, `cpu`, `cuda`, `cuda:N`.
    pub device: String,
    /// `f32`, `f16`, `bf16`.
    pub dtype: String,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            weights: "default".into(),
            engine: "auto".into(),
            vggt_weights: String::new(),
            context_views: 5,
            orbit_frames: 56,
            refiner_steps: 25,
            device: "auto".into(),
            dtype: "f32".into(),
        }
    }
}

/// A path or name given as one argument: not empty, not a flag, one line.
fn plain(what: &str, v: &str) -> Result<(), String> {
    if v.is_empty() || v.starts_with('-') || v.contains(['\n', '\r', '\0']) || v.len() > 4096 {
        return Err(format!("{what}: {v:?} is not a path or a name"));
    }
    Ok(())
}

impl Settings {
    /// Ok when every value is one `render` takes.
    pub fn check(&self) -> Result<(), String> {
        plain("weights", &self.weights)?;
        if !self.vggt_weights.is_empty() {
            plain("VGGT weights", &self.vggt_weights)?;
        }
        if !matches!(self.engine.as_str(), "auto" | "colmap" | "vggt") {
            return Err(format!("pose engine: {:?} is not auto, colmap or vggt", self.engine));
        }
        if !(1..=64).contains(&self.context_views) {
            return Err("context views: 1 to 64".into());
        }
        if !(1..=2000).contains(&self.orbit_frames) {
            return Err("orbit frames: 1 to 2000".into());
        }
        if self.refiner_steps > 1000 {
            return Err("refiner steps: 0 to 1000".into());
        }
        let dev = &self.device;
        let cuda_n = dev.strip_prefix("cuda:").is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if !(matches!(dev.as_str(), "auto" | "cpu" | "cuda") || cuda_n) {
            return Err(format!("device: {dev:?} is not auto, cpu, cuda or cuda:N"));
        }
        if !matches!(self.dtype.as_str(), "f32" | "f16" | "bf16") {
            return Err(format!("dtype: {:?} is not f32, f16 or bf16", self.dtype));
        }
        Ok(())
    }

    /// The `render` arguments (after the scene and `--out`).
    pub fn render_args(&self) -> Vec<String> {
        let mut a = Vec::new();
        if self.weights != "default" {
            a.extend(["--ckpt".into(), self.weights.clone()]);
        }
        if self.refiner_steps == 0 {
            a.extend(["--refiner".into(), "none".into()]);
        } else {
            a.extend(["--steps".into(), self.refiner_steps.to_string()]);
        }
        a.extend(["--num-context".into(), self.context_views.to_string(), "--orbit".into(), self.orbit_frames.to_string()]);
        a.extend(["--engine".into(), self.engine.clone(), "--device".into(), self.device.clone(), "--dtype".into(), self.dtype.clone()]);
        if !self.vggt_weights.is_empty() {
            a.extend(["--vggt-weights".into(), self.vggt_weights.clone()]);
        }
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_pass_and_flags_are_refused() {
        assert!(Settings::default().check().is_ok());
        let s = Settings { weights: "--out=/etc".into(), ..Settings::default() };
        assert!(s.check().is_err());
        let s = Settings { device: "cuda:1".into(), ..Settings::default() };
        assert!(s.check().is_ok());
        let s = Settings { device: "cuda:x".into(), ..Settings::default() };
        assert!(s.check().is_err());
        let a = Settings { refiner_steps: 0, ..Settings::default() }.render_args();
        assert_eq!(&a[..2], ["--refiner", "none"]);
    }
}
