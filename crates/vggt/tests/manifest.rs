//! The VGGT-1B key manifest (every key and shape of the official model, written by
//! `scripts/fixtures/official_vggt.py --manifest` from the official code built without weights) against the
//! model this crate builds with the default config: the same keys, the same shapes, `track_head.*` the only
//! keys not asked for. The weights are served as zero-stride views of one zero, so the check costs no 5 GB.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::{Init, VarBuilder};
use mvsplat360_vggt::{Vggt, VggtConfig};

struct Recorder {
    asked: Arc<Mutex<BTreeMap<String, Vec<usize>>>>,
}

impl candle_nn::var_builder::SimpleBackend for Recorder {
    fn get(&self, s: Shape, name: &str, _h: Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        self.asked.lock().unwrap().insert(name.to_string(), s.dims().to_vec());
        Tensor::zeros((), dtype, dev)?.broadcast_as(s)
    }
    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("unchecked `{name}`")
    }
    fn contains_tensor(&self, _: &str) -> bool {
        true
    }
}

#[test]
fn vggt_1b_manifest_matches_the_built_model() {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/vggt_1b_manifest.json");
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    let manifest: BTreeMap<String, Vec<usize>> = v["keys"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| (e[0].as_str().unwrap().to_string(), e[1].as_array().unwrap().iter().map(|d| d.as_u64().unwrap() as usize).collect()))
        .collect();
    assert_eq!(manifest.len(), 1797, "the manifest of VGGT-1B holds 1797 keys");
    let asked = Arc::new(Mutex::new(BTreeMap::new()));
    let vb = VarBuilder::from_backend(Box::new(Recorder { asked: asked.clone() }), DType::F32, Device::Cpu);
    Vggt::new(vb, &VggtConfig::default()).unwrap();
    let asked = asked.lock().unwrap().clone();
    let mut problems = Vec::new();
    for (k, shape) in &asked {
        match manifest.get(k) {
            None => problems.push(format!("asked for `{k}`, not in VGGT-1B")),
            Some(m) if m != shape => problems.push(format!("`{k}`: built {shape:?}, VGGT-1B has {m:?}")),
            _ => {}
        }
    }
    let not_asked: Vec<&String> = manifest.keys().filter(|k| !asked.contains_key(*k)).collect();
    for k in &not_asked {
        if !k.starts_with(mvsplat360_vggt::weights::SKIPPED_PREFIX) {
            problems.push(format!("VGGT-1B key `{k}` not built"));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    assert_eq!(not_asked.len(), 394, "every track_head key (394) and nothing else is skipped");
    let params: usize = asked.values().map(|s| s.iter().product::<usize>()).sum();
    eprintln!("built {} tensors, {params} parameters (VGGT-1B without the track head)", asked.len());
}
