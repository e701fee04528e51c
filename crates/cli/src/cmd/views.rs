//! Flags shared by `render`, `export` and `inspect`: which views are context, where the scene is.

use std::path::PathBuf;

use mvsplat360_pipeline::views::{parse_list, ContextSpec};

/// A comma-separated list of view indices (one clap value, so clap does not treat it as repeated values).
#[derive(Debug, Clone)]
pub struct ViewList(pub Vec<usize>);

pub fn view_list(s: &str) -> Result<ViewList, String> {
    parse_list(s).map(ViewList)
}

#[derive(clap::Args, Debug, Clone)]
pub struct ContextArgs {
    /// Context views by index in the scene, e.g. `--context 3,17,40` (0-based, the scene's view order).
    #[arg(long, value_parser = view_list, conflicts_with_all = ["num_context", "index"])]
    pub context: Option<ViewList>,
    /// Number of context views picked by farthest-point sampling of the camera centres (first view first).
    #[arg(long, default_value_t = 5)]
    pub num_context: usize,
    /// Evaluation index (JSON `{scene: {"context": [...], "target": [...]}}`): take this scene's views from it.
    #[arg(long)]
    pub index: Option<PathBuf>,
    /// Scene key: the scene inside a multi-scene `.torch` chunk, and its entry in `--index`
    /// (default: the first scene of a chunk; the scene's name in the index).
    #[arg(long)]
    pub scene_key: Option<String>,
}

impl ContextArgs {
    pub fn spec(&self) -> ContextSpec {
        if let Some(v) = &self.context {
            ContextSpec::Views(v.0.clone())
        } else if let Some(f) = &self.index {
            ContextSpec::Index { file: f.clone(), scene_key: self.scene_key.clone() }
        } else {
            ContextSpec::Count(self.num_context)
        }
    }
}
