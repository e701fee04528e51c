//! Weight loading: strict key/shape checks on safetensors, and the torch zip/pickle (Lightning `.ckpt`) path.

use std::collections::HashMap;
use std::io::Write;

use candle_core::{DType, Device, Tensor};
use mvsplat360_encoder::backbone::{BackboneMultiview, MultiViewFeatureTransformer};
use mvsplat360_encoder::weights::{convert_to_safetensors, load_strict, Checkpoint, WeightsError};
use mvsplat360_testkit as tk;

/// The fixture's backbone keys load with zero missing and zero unexpected keys under `encoder.backbone.`.
#[test]
fn fixture_backbone_loads_strictly() {
    let path = tk::fixture("encoder/state_dict.safetensors");
    let ckpt = Checkpoint::open(&path).unwrap();
    let n_backbone = ckpt.keys().iter().filter(|k| k.starts_with("encoder.backbone.")).count();
    assert!(n_backbone > 0);
    let model = load_strict(&path, "encoder.backbone.", &Device::Cpu, |vb| BackboneMultiview::new(vb, 128, 6, 4));
    assert!(model.is_ok(), "{}", model.err().map(|e| e.to_string()).unwrap_or_default());
    // The same file seen through a wrong architecture (4 blocks) must report the 2 extra blocks as unexpected.
    let err = load_strict(&path, "encoder.backbone.", &Device::Cpu, |vb| BackboneMultiview::new(vb, 128, 4, 4))
        .err()
        .expect("4-block model must not load a 6-block checkpoint");
    match err {
        WeightsError::Strict { missing, unexpected, mismatched, .. } => {
            assert!(missing.is_empty() && mismatched.is_empty());
            assert!(unexpected.iter().all(|k| k.contains("layers.4.") || k.contains("layers.5.")));
            // 2 blocks × (6 self-attn + 10 cross-attn/FFN tensors)
            assert_eq!(unexpected.len(), 32, "{unexpected:?}");
        }
        other => panic!("unexpected error kind: {other}"),
    }
}

fn tiny_transformer_tensors() -> HashMap<String, Tensor> {
    // Build a 1-block d=8 transformer from random weights to get its exact key set and shapes.
    let varmap = candle_nn::VarMap::new();
    let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    MultiViewFeatureTransformer::new(vb.pp("encoder").pp("t"), 1, 8, 2).unwrap();
    let data = varmap.data().lock().unwrap();
    data.iter().map(|(k, v)| (k.clone(), v.as_tensor().clone())).collect()
}

/// Missing keys, unexpected keys and shape mismatches are all reported, each naming its key.
#[test]
fn strict_errors_name_the_keys() {
    let dir = tempfile::tempdir().unwrap();
    let mut t = tiny_transformer_tensors();
    assert_eq!(t.len(), 16);
    t.remove("encoder.t.layers.0.self_attn.q_proj.weight");
    t.insert("encoder.t.layers.0.self_attn.merge.weight".into(), Tensor::zeros((8, 9), DType::F32, &Device::Cpu).unwrap());
    t.insert("encoder.extra.weight".into(), Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap());
    t.insert("refiner.other".into(), Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap());
    let p = dir.path().join("bad.safetensors");
    candle_core::safetensors::save(&t, &p).unwrap();
    let err = load_strict(&p, "encoder.", &Device::Cpu, |vb| MultiViewFeatureTransformer::new(vb.pp("t"), 1, 8, 2)).err().expect("must fail");
    let msg = err.to_string();
    match err {
        WeightsError::Strict { missing, unexpected, mismatched, .. } => {
            assert_eq!(missing, vec!["encoder.t.layers.0.self_attn.q_proj.weight".to_string()]);
            // Keys outside the prefix (`refiner.*`) are not the encoder's business.
            assert_eq!(unexpected, vec!["encoder.extra.weight".to_string()]);
            assert_eq!(mismatched.len(), 1);
            assert_eq!(mismatched[0].0, "encoder.t.layers.0.self_attn.merge.weight");
            assert_eq!(mismatched[0].1, vec![8, 8]);
            assert_eq!(mismatched[0].2, vec![8, 9]);
        }
        other => panic!("unexpected error kind: {other}"),
    }
    assert!(msg.contains("merge.weight") && msg.contains("[8, 9]"), "{msg}");
}

// ---------------------------------------------------------------------------------------------------------------
// A minimal torch checkpoint written by hand, in the layout `torch.save` produces (zip archive, pickle protocol 2):
//   archive/data.pkl   pickle of {"state_dict": {name: _rebuild_tensor_v2(persistent_load(("storage",
//                      <Float|Half>Storage, "<i>", "cpu", numel)), 0, size, stride, False, OrderedDict())},
//                      "epoch": 7}
//   archive/data/<i>   raw little-endian storage bytes of tensor i
//   archive/version    "3\n"
// ---------------------------------------------------------------------------------------------------------------

struct Pickle(Vec<u8>);

impl Pickle {
    fn op(&mut self, b: u8) {
        self.0.push(b);
    }
    fn unicode(&mut self, s: &str) {
        self.op(b'X');
        self.0.extend_from_slice(&(s.len() as u32).to_le_bytes());
        self.0.extend_from_slice(s.as_bytes());
    }
    fn int(&mut self, v: i32) {
        self.op(b'J');
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn global(&mut self, module: &str, name: &str) {
        self.op(b'c');
        self.0.extend_from_slice(format!("{module}\n{name}\n").as_bytes());
    }
    fn int_tuple(&mut self, v: &[usize]) {
        self.op(b'(');
        for &x in v {
            self.int(x as i32);
        }
        self.op(b't');
    }
}

enum Stored {
    F32(Vec<f32>),
    F16(Vec<u16>),
}

fn write_torch_zip(path: &std::path::Path, tensors: &[(&str, Vec<usize>, Stored)]) {
    let mut p = Pickle(vec![0x80, 2]);
    p.op(b'}');
    p.op(b'(');
    p.unicode("state_dict");
    p.op(b'}');
    p.op(b'(');
    for (i, (name, shape, data)) in tensors.iter().enumerate() {
        p.unicode(name);
        p.global("torch._utils", "_rebuild_tensor_v2");
        p.op(b'(');
        // persistent id tuple
        p.op(b'(');
        p.unicode("storage");
        p.global("torch", if matches!(data, Stored::F32(_)) { "FloatStorage" } else { "HalfStorage" });
        p.unicode(&i.to_string());
        p.unicode("cpu");
        p.int(shape.iter().product::<usize>() as i32);
        p.op(b't');
        p.op(b'Q');
        p.int(0);
        p.int_tuple(shape);
        let mut stride = vec![1usize; shape.len()];
        for d in (0..shape.len().saturating_sub(1)).rev() {
            stride[d] = stride[d + 1] * shape[d + 1];
        }
        p.int_tuple(&stride);
        p.op(0x89); // False
        p.global("collections", "OrderedDict");
        p.op(b')');
        p.op(b'R');
        p.op(b't');
        p.op(b'R');
    }
    p.op(b'u');
    p.unicode("epoch");
    p.int(7);
    p.op(b'u');
    p.op(b'.');

    let f = std::fs::File::create(path).unwrap();
    let mut z = zip::ZipWriter::new(f);
    let opts: zip::write::SimpleFileOptions = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    z.start_file("archive/data.pkl", opts).unwrap();
    z.write_all(&p.0).unwrap();
    for (i, (_, _, data)) in tensors.iter().enumerate() {
        z.start_file(format!("archive/data/{i}"), opts).unwrap();
        match data {
            Stored::F32(v) => v.iter().for_each(|x| z.write_all(&x.to_le_bytes()).unwrap()),
            Stored::F16(v) => v.iter().for_each(|x| z.write_all(&x.to_le_bytes()).unwrap()),
        }
    }
    z.start_file("archive/version", opts).unwrap();
    z.write_all(b"3\n").unwrap();
    z.finish().unwrap();
}

/// A Lightning-style torch zip: `encoder.*` keys are read from `state_dict`, f16 is upcast to f32, other keys are
/// ignored by the strict check, and `convert_to_safetensors` writes the same tensors.
#[test]
fn torch_zip_checkpoint_loads_and_converts() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt_path = dir.path().join("tiny.ckpt");
    let t = tiny_transformer_tensors();
    let mut entries: Vec<(String, Vec<usize>, Vec<f32>)> =
        t.iter().map(|(k, v)| (k.clone(), v.dims().to_vec(), v.flatten_all().unwrap().to_vec1::<f32>().unwrap())).collect();
    entries.sort_by(|a, b| a.0.cmp(&b.0));
    // Store one tensor as f16 with values exactly representable in f16 (k/8, |k| ≤ 64).
    let f16_key = "encoder.t.layers.0.cross_attn_ffn.norm2.weight";
    let mut stored: Vec<(&str, Vec<usize>, Stored)> = Vec::new();
    let mut expected: HashMap<String, Vec<f32>> = HashMap::new();
    for (k, shape, vals) in &entries {
        if k == f16_key {
            let exact: Vec<f32> = (0..vals.len()).map(|i| (i as f32 - 4.0) / 8.0).collect();
            // f16 bit patterns computed by hand: value = (i-4)/8 for i in 0..8
            let bits: Vec<u16> = exact.iter().map(|&x| f32_to_f16_bits(x)).collect();
            expected.insert(k.clone(), exact);
            stored.push((k.as_str(), shape.clone(), Stored::F16(bits)));
        } else {
            expected.insert(k.clone(), vals.clone());
            stored.push((k.as_str(), shape.clone(), Stored::F32(vals.clone())));
        }
    }
    stored.push(("refiner.unrelated", vec![2], Stored::F32(vec![1.0, 2.0])));
    write_torch_zip(&ckpt_path, &stored);

    let ckpt = Checkpoint::open(&ckpt_path).unwrap();
    assert_eq!(ckpt.keys().len(), 17);
    assert_eq!(ckpt.dtype(f16_key), Some(DType::F16));
    let model = load_strict(&ckpt_path, "encoder.", &Device::Cpu, |vb| MultiViewFeatureTransformer::new(vb.pp("t"), 1, 8, 2));
    assert!(model.is_ok(), "{}", model.err().map(|e| e.to_string()).unwrap_or_default());
    for (k, vals) in &expected {
        let got = ckpt.load(k, DType::F32, &Device::Cpu).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(&got, vals, "{k}");
    }

    let out = dir.path().join("tiny.safetensors");
    let n = convert_to_safetensors(&ckpt_path, &out, "encoder.").unwrap();
    assert_eq!(n, 16);
    let back = candle_core::safetensors::load(&out, &Device::Cpu).unwrap();
    assert_eq!(back.len(), 16);
    assert_eq!(back[f16_key].dtype(), DType::F16);
    for (k, vals) in &expected {
        let got = back[k].to_dtype(DType::F32).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(&got, vals, "{k}");
    }
}

/// IEEE half bits for values that are exactly representable (the test only uses k/8, small k).
fn f32_to_f16_bits(x: f32) -> u16 {
    if x == 0.0 {
        return 0;
    }
    let sign = if x < 0.0 { 0x8000u16 } else { 0 };
    let a = x.abs();
    let e = a.log2().floor() as i32;
    let mant = a / 2f32.powi(e) - 1.0;
    let m = (mant * 1024.0).round() as u16;
    sign | (((e + 15) as u16) << 10) | m
}

/// A file that is neither safetensors nor a zip gives a format error naming the path.
#[test]
fn garbage_file_is_a_format_error() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("junk.ckpt");
    std::fs::write(&p, b"hello world, not weights").unwrap();
    let err = Checkpoint::open(&p).err().expect("must fail");
    assert!(err.to_string().contains("junk.ckpt"), "{err}");
}
