//! Scene scale. The official code never rescales a scene: the model assumes the content lies between its near
//! and far planes (1 and 100) in the data's own units — COLMAP's scale for DL3DV and RE10K, which is also what
//! COLMAP and nerfstudio give users. Other sources (unit-cube NeRF scenes, millimetre CAD units) may lie far
//! outside that range; `--scene-scale auto` then scales the scene so the context cameras' median distance to
//! the point they look at becomes 10, the geometric middle of [1, 100] (the cost volume samples inverse depth
//! uniformly between 1/far and 1/near). Scenes whose pose engine states its units take that engine's rule
//! ([`pose_engine_scale`]: VGGT's normalised world → `auto`).

use std::path::Path;

use mvsplat360_camera::{trajectory, Camera};

/// How a scene is brought to the model's units (`--scene-scale`).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub enum SceneScale {
    /// The scene's own units (the official behaviour).
    #[default]
    None,
    /// Median context-camera distance to the look-at point → [`AUTO_DISTANCE`].
    Auto,
    /// Multiply scene units by this factor.
    Factor(f64),
}

/// The scaling that applies to a run and why: `--scene-scale` when given, else what the scene's pose engine
/// states ([`pose_engine_scale`]), else the model folder's `scene_scale`, else scene units (the official protocol).
pub fn resolve(flag: Option<SceneScale>, scene: Option<(SceneScale, &'static str)>, model: Option<SceneScale>) -> (SceneScale, &'static str) {
    match (flag, scene, model) {
        (Some(s), _, _) => (s, "--scene-scale"),
        (None, Some(s), _) => s,
        (None, None, Some(s)) => (s, "the model's config.json"),
        (None, None, None) => (SceneScale::None, "default: scene units, the official protocol (the model sets no scene_scale)"),
    }
}

/// Where [`pose_engine_scale`]'s rule for VGGT-posed scenes is recorded from (`run.json`'s `scene_scale_source`).
pub const VGGT_SOURCE: &str = "the scene's pose engine (vggt: normalised units)";

/// The scaling a scene's units call for, read from the `pose.json` that `mvsplat360 pose` writes in the scene
/// folder (`scene` itself, or the folder of a scene file). VGGT's world is normalised (mean point distance 1), so
/// its content sits near depth 1, the cost volume's near plane, for every model: such scenes take `auto`.
/// COLMAP's units are the ones the official model learned (docs/cameras.md §4) and state nothing; so do scenes
/// without a `pose.json`, or with one that cannot be read.
pub fn pose_engine_scale(scene: &Path) -> Option<(SceneScale, &'static str)> {
    let dir = if scene.is_dir() { scene } else { scene.parent()? };
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("pose.json")).ok()?).ok()?;
    match report.get("engine")?.as_str()? {
        "vggt" => Some((SceneScale::Auto, VGGT_SOURCE)),
        _ => None,
    }
}

/// Target distance of `auto`: √(near·far) for the official near 1 / far 100.
pub const AUTO_DISTANCE: f64 = 10.0;

impl std::str::FromStr for SceneScale {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "none" => Ok(Self::None),
            "auto" => Ok(Self::Auto),
            f => match f.parse::<f64>() {
                Ok(v) if v.is_finite() && v > 0.0 => Ok(Self::Factor(v)),
                _ => Err(format!("expected `none`, `auto` or a positive factor, got `{s}`")),
            },
        }
    }
}

/// Model space = scene space scaled by `scale` about the origin (rotations unchanged).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneTransform {
    pub scale: f64,
}

impl SceneTransform {
    pub fn identity() -> Self {
        Self { scale: 1.0 }
    }

    /// The camera in model space.
    pub fn apply(&self, c: &Camera) -> Camera {
        let mut out = c.clone();
        for r in 0..3 {
            out.c2w[r][3] *= self.scale;
        }
        out
    }

    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({ "scale": self.scale })
    }
}

/// Median distance from the cameras to the point they look at (None when it is not finite or zero).
pub fn look_at_distance(cams: &[Camera]) -> Option<f64> {
    let p = trajectory::look_at_point(cams);
    let mut d: Vec<f64> = cams.iter().map(|c| (c.center() - p).norm()).filter(|d| d.is_finite()).collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(|a, b| a.total_cmp(b));
    Some(d[d.len() / 2]).filter(|&m| m > 0.0)
}

/// The transform for a scene given its context cameras, and a warning when the scene looks out of range.
pub fn scene_transform(mode: SceneScale, context: &[Camera], near: f32, far: f32) -> (SceneTransform, Option<String>) {
    let d = look_at_distance(context);
    match mode {
        SceneScale::Factor(s) => (SceneTransform { scale: s }, None),
        SceneScale::Auto => match d {
            Some(d) => (SceneTransform { scale: AUTO_DISTANCE / d }, None),
            None => (SceneTransform::identity(), Some("--scene-scale auto: the context cameras do not look at a common point; scene units kept".into())),
        },
        SceneScale::None => {
            let warn = d.filter(|&d| d < near as f64 || d > far as f64).map(|d| {
                format!(
                    "the context cameras are {d:.3} scene units from what they look at, outside the model's depth range [{near}, {far}]; \
                     consider --scene-scale auto (see docs/cameras.md)"
                )
            });
            (SceneTransform::identity(), warn)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ring(r: f64) -> Vec<Camera> {
        // Four cameras on a circle of radius r around the origin, each looking at it.
        let up = nalgebra::Vector3::new(0.0, -1.0, 0.0);
        let t = Camera {
            fx: 100.0,
            fy: 100.0,
            cx: 50.0,
            cy: 50.0,
            width: 100,
            height: 100,
            c2w: [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        };
        (0..4)
            .map(|i| {
                let a = std::f64::consts::FRAC_PI_2 * i as f64;
                let eye = nalgebra::Vector3::new(r * a.cos(), 0.0, r * a.sin());
                trajectory::look_at(&t, &eye, &nalgebra::Vector3::zeros(), &up)
            })
            .collect()
    }

    #[test]
    fn auto_scales_to_distance_ten_and_none_warns_out_of_range() {
        let cams = ring(0.5);
        assert!((look_at_distance(&cams).unwrap() - 0.5).abs() < 1e-9);
        let (t, w) = scene_transform(SceneScale::Auto, &cams, 1.0, 100.0);
        assert!((t.scale - 20.0).abs() < 1e-9 && w.is_none());
        let moved = t.apply(&cams[1]);
        assert!((moved.center().norm() - 10.0).abs() < 1e-9);
        let (t, w) = scene_transform(SceneScale::None, &cams, 1.0, 100.0);
        assert_eq!(t.scale, 1.0);
        assert!(w.unwrap().contains("0.500"));
        assert!(scene_transform(SceneScale::None, &ring(13.0), 1.0, 100.0).1.is_none());
        assert_eq!(scene_transform(SceneScale::Factor(3.0), &cams, 1.0, 100.0).0.scale, 3.0);
        assert_eq!("auto".parse::<SceneScale>().unwrap(), SceneScale::Auto);
        assert!("-1".parse::<SceneScale>().is_err());
    }

    #[test]
    fn the_flag_wins_over_the_pose_engine_over_the_model_over_scene_units() {
        let vggt = Some((SceneScale::Auto, VGGT_SOURCE));
        assert_eq!(resolve(Some(SceneScale::Factor(2.0)), vggt, Some(SceneScale::Auto)), (SceneScale::Factor(2.0), "--scene-scale"));
        assert_eq!(resolve(Some(SceneScale::None), vggt, Some(SceneScale::Auto)).0, SceneScale::None);
        assert_eq!(resolve(None, vggt, Some(SceneScale::None)), (SceneScale::Auto, VGGT_SOURCE));
        assert_eq!(resolve(None, vggt, None), (SceneScale::Auto, VGGT_SOURCE));
        assert_eq!(resolve(None, None, Some(SceneScale::Auto)), (SceneScale::Auto, "the model's config.json"));
        assert_eq!(resolve(None, None, None).0, SceneScale::None);
    }

    #[test]
    fn only_a_vggt_pose_report_states_a_scale() {
        let dir = tempfile::tempdir().unwrap();
        let tmp = dir.path();
        let report = |text: &str| {
            std::fs::write(tmp.join("pose.json"), text).unwrap();
            (pose_engine_scale(tmp), pose_engine_scale(&tmp.join("transforms.json")))
        };
        assert_eq!(pose_engine_scale(tmp), None, "no pose.json");
        let vggt = Some((SceneScale::Auto, VGGT_SOURCE));
        assert_eq!(report(r#"{"engine": "vggt", "views": 5}"#), (vggt, vggt));
        assert_eq!(report(r#"{"engine": "colmap"}"#), (None, None));
        assert_eq!(report(r#"{"input": "video.mp4"}"#), (None, None));
        assert_eq!(report("not json"), (None, None));
    }
}
