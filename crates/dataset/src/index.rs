//! Evaluation index: `{scene: {"context": [...], "target": [...], "target_quantify"?: [...]} | [ {…} ] | [] | null}`.
//! A null entry means the scene is skipped by the protocol.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Deserialize;

use crate::error::{field, io};
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

#[cfg(test)]
mod tests {
    use super::*;

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
