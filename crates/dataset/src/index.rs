//! Evaluation index: `{scene: {"context": [...], "target": [...], "target_quantify"?: [...]} | [ {…} ] | [] | null}`.
//! A null entry means the scene is skipped by the protocol.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Deserialize;

use mvsplat360_camera::select::{farthest_points, FpsStart};

use crate::error::{field, io};
use crate::torch_chunk::ChunkScene;
use crate::DatasetError;

#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct EvaluationEntry {
    pub context: Vec<usize>,
    pub target: Vec<usize>,
    /// Subset of `target` used for metrics, when the index gives one.
    #[serde(default)]
    pub target_quantify: Option<Vec<usize>>,
}

/// Read an evaluation index; entries that are `null` map to `None`.
pub fn read_evaluation_index(path: &Path) -> Result<BTreeMap<String, Option<EvaluationEntry>>, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| io(path, e))?;
    let raw: BTreeMap<String, serde_json::Value> = serde_json::from_str(&text).map_err(|source| DatasetError::Json { path: path.to_path_buf(), source })?;
    raw.into_iter()
        .map(|(k, v)| {
            // The official sampler also accepts a one-entry list (`[{...}]`) and treats `[]` like null.
            let v = match v {
                serde_json::Value::Array(mut a) if a.len() <= 1 => a.pop().unwrap_or(serde_json::Value::Null),
                serde_json::Value::Array(a) => {
                    return Err(field(path, &k, format!("a list entry must hold one {{\"context\", \"target\"}} object, found {}", a.len())))
                }
                v => v,
            };
            if v.is_null() {
                return Ok((k, None));
            }
            let e: EvaluationEntry =
                serde_json::from_value(v).map_err(|e| field(path, &k, format!("expected {{\"context\": [..], \"target\": [..]}}: {e}")))?;
            if e.context.is_empty() {
                return Err(field(path, format!("{k}.context"), "is empty; at least one context view is needed"));
            }
            Ok((k, Some(e)))
        })
        .collect()
}

/// Check an entry's indices against a scene's view count.
pub fn check_entry(path: &Path, scene: &str, e: &EvaluationEntry, views: usize) -> Result<(), DatasetError> {
    for (name, list) in [("context", &e.context), ("target", &e.target)] {
        if let Some(&bad) = list.iter().find(|&&i| i >= views) {
            return Err(field(path, format!("{scene}.{name}"), format!("view index {bad} is out of range (scene has {views} views)")));
        }
    }
    Ok(())
}

// Evaluation index generation (the official generate_evaluation_index_dl3dv.py): context views by farthest-point
// sampling from the centroid, targets spread over the rest.

/// Settings of the official index generator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndexOptions {
    /// `--num_context_views` (5).
    pub num_context: usize,
    /// `--num_target_views` (56).
    pub num_target: usize,
    /// `--view_selection_ratio`: only the first `int(N · ratio)` views of each scene (0.5 = the `_n150` index).
    pub view_selection_ratio: f64,
}

impl Default for IndexOptions {
    fn default() -> Self {
        Self { num_context: 5, num_target: 56, view_selection_ratio: 1.0 }
    }
}

impl IndexOptions {
    /// The official file name: `dl3dv_ctx_{c}v_tgt_{t}v[_n{int(ratio·300)}].json`.
    pub fn official_file_name(&self) -> String {
        let mut s = format!("dl3dv_ctx_{}v_tgt_{}v", self.num_context, self.num_target);
        if self.view_selection_ratio < 1.0 {
            s.push_str(&format!("_n{}", (self.view_selection_ratio * 300.0) as i64));
        }
        s + ".json"
    }
}

/// The official `partition_list`: `[lst[0], lst[bin], …, lst[(n_bins−1)·bin], lst[-1]]` with
/// `bin = len // n_bins`; None where the official raises (`n_bins` 0 or more than `len`).
pub fn partition_list(lst: &[usize], n_bins: usize) -> Option<Vec<usize>> {
    if n_bins == 0 || lst.len() < n_bins {
        return None;
    }
    let bin = lst.len() / n_bins;
    let mut b = vec![lst[0]];
    for i in 1..n_bins {
        b.push(lst[(i * bin).min(lst.len() - 1)]);
    }
    b.push(lst[lst.len() - 1]);
    Some(b)
}

/// One scene's entry from its camera centres (view order), or why it cannot have one.
pub fn index_entry(centres: &[[f64; 3]], opts: &IndexOptions) -> Result<EvaluationEntry, String> {
    // Python `int(n_views * ratio)`: truncation.
    let n_views = ((centres.len() as f64) * opts.view_selection_ratio) as usize;
    let n_views = n_views.min(centres.len());
    if n_views < opts.num_context {
        return Err(format!("{n_views} views (of {}) are fewer than the {} context views", centres.len(), opts.num_context));
    }
    let mut context = farthest_points(&centres[..n_views], opts.num_context, FpsStart::FarthestFromCentroid);
    context.sort_unstable();
    let rest: Vec<usize> = (0..n_views).filter(|x| !context.contains(x)).collect();
    let sel = partition_list(&rest, opts.num_target)
        .ok_or_else(|| format!("{} non-context views (of {n_views} used) are fewer than the {} target views", rest.len(), opts.num_target))?;
    Ok(EvaluationEntry { context, target: sel[..opts.num_target].to_vec(), target_quantify: None })
}

/// Camera centres of a chunk scene: translation of the inverted 4×4 world-to-camera (f64).
pub fn chunk_centres(s: &ChunkScene) -> Vec<[f64; 3]> {
    s.cameras
        .iter()
        .map(|r| {
            let w2c = nalgebra::Matrix4::from_fn(|i, j| {
                if i < 3 {
                    r[6 + i * 4 + j] as f64
                } else if j == 3 {
                    1.0
                } else {
                    0.0
                }
            });
            let c2w = w2c.try_inverse().unwrap_or_else(|| mvsplat360_camera::convert::invert_rigid(&w2c));
            [c2w[(0, 3)], c2w[(1, 3)], c2w[(2, 3)]]
        })
        .collect()
}

/// A generated index, scenes in the official order (chunks by name, scenes in chunk order).
#[derive(Debug, Clone, PartialEq)]
pub struct GeneratedIndex {
    pub entries: Vec<(String, Option<EvaluationEntry>)>,
    pub chunks: usize,
    /// Scenes written as null, and why.
    pub warnings: Vec<String>,
}

/// The official generator over the `.torch` chunks `chunks` of `data` (file names, in the official order:
/// sorted); `on_chunk` is called after each chunk.
pub fn index_from_chunks(data: &Path, chunks: &[String], opts: &IndexOptions, on_chunk: &mut dyn FnMut()) -> Result<GeneratedIndex, DatasetError> {
    let mut entries: Vec<(String, Option<EvaluationEntry>)> = Vec::new();
    let mut pos: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
    let mut warnings = Vec::new();
    for c in chunks {
        for s in crate::torch_chunk::read_chunk(&data.join(c))? {
            let e = match index_entry(&chunk_centres(&s), opts) {
                Ok(e) => Some(e),
                Err(msg) => {
                    warnings.push(format!("scene {} ({c}): {msg}; written as null", s.key));
                    None
                }
            };
            // OrderedDict.update: a repeated key keeps its first position and takes the new value.
            match pos.get(&s.key) {
                Some(&i) => entries[i].1 = e,
                None => {
                    pos.insert(s.key.clone(), entries.len());
                    entries.push((s.key, e));
                }
            }
        }
        on_chunk();
    }
    Ok(GeneratedIndex { entries, chunks: chunks.len(), warnings })
}

/// The index as Python's `json.dump` writes it (`", "` and `": "` separators, insertion order).
pub fn index_json(entries: &[(String, Option<EvaluationEntry>)]) -> String {
    let list = |v: &[usize]| format!("[{}]", v.iter().map(|x| x.to_string()).collect::<Vec<_>>().join(", "));
    let body: Vec<String> = entries
        .iter()
        .map(|(k, e)| {
            let key = serde_json::to_string(k).unwrap_or_else(|_| format!("\"{k}\""));
            match e {
                None => format!("{key}: null"),
                Some(e) => {
                    let mut s = format!("{key}: {{\"context\": {}, \"target\": {}", list(&e.context), list(&e.target));
                    if let Some(q) = &e.target_quantify {
                        s.push_str(&format!(", \"target_quantify\": {}", list(q)));
                    }
                    s + "}"
                }
            }
        })
        .collect();
    format!("{{{}}}", body.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn partition_list_as_official() {
        let l: Vec<usize> = (10..20).collect();
        assert_eq!(partition_list(&l, 3).unwrap(), vec![10, 13, 16, 19]);
        assert_eq!(partition_list(&l, 10).unwrap(), vec![10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 19]);
        assert!(partition_list(&l, 11).is_none() && partition_list(&l, 0).is_none());
    }

    #[test]
    fn python_json_layout() {
        let e = EvaluationEntry { context: vec![1, 2], target: vec![3], target_quantify: None };
        let s = index_json(&[("b".into(), Some(e)), ("a".into(), None)]);
        assert_eq!(s, r#"{"b": {"context": [1, 2], "target": [3]}, "a": null}"#);
    }

    #[test]
    fn list_and_empty_entries_as_the_official_sampler() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("index.json");
        std::fs::write(
            &p,
            r#"{"a": [{"context": [1, 5], "target": [2, 3], "target_quantify": [3]}], "b": [], "c": null,
            "d": {"context": [0, 9], "target": [4]}}"#,
        )
        .unwrap();
        let idx = read_evaluation_index(&p).unwrap();
        let a = idx["a"].as_ref().unwrap();
        assert_eq!((a.context.clone(), a.target.clone(), a.target_quantify.clone()), (vec![1, 5], vec![2, 3], Some(vec![3])));
        assert!(idx["b"].is_none() && idx["c"].is_none());
        assert_eq!(idx["d"].as_ref().unwrap().target, vec![4]);
        std::fs::write(&p, r#"{"a": [{"context": [1], "target": [2]}, {"context": [1], "target": [2]}]}"#).unwrap();
        assert!(read_evaluation_index(&p).unwrap_err().to_string().contains("one"));
    }
}
