//! `mvsplat360 convert` on tiny safetensors inputs: the prefix filter, verbatim key names, bit-exact values and
//! dtypes, and clear errors. (The torch-zip / Lightning `.ckpt` reading behind it is tested in
//! crates/encoder/tests/weights.rs; this tests the command.)

use std::collections::HashMap;
use std::path::Path;
use std::process::{Command, Output};

use candle_core::{DType, Device, Tensor};

fn convert(input: &Path, out: &Path, prefix: Option<&str>) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_mvsplat360"));
    c.arg("convert").arg(input).arg("--out").arg(out);
    if let Some(p) = prefix {
        c.args(["--prefix", p]);
    }
    c.output().unwrap()
}

fn tiny_checkpoint(path: &Path) -> HashMap<String, Tensor> {
    let dev = Device::Cpu;
    let mut t = HashMap::new();
    t.insert("encoder.backbone.conv1.weight".to_string(), Tensor::arange(0f32, 24.0, &dev).unwrap().affine(0.37, -1.5).unwrap().reshape((2, 3, 2, 2)).unwrap());
    t.insert("encoder.depth_predictor.to_disparity.2.bias".to_string(), Tensor::new(&[1.25f32, -3.5], &dev).unwrap());
    t.insert("encoder.half".to_string(), Tensor::new(&[0.1f32, 2.0, -7.0], &dev).unwrap().to_dtype(DType::F16).unwrap());
    t.insert("encoder.steps".to_string(), Tensor::new(&[3i64, -9], &dev).unwrap());
    t.insert("refiner.model.diffusion_model.out.2.weight".to_string(), Tensor::ones((4, 4), DType::F32, &dev).unwrap());
    t.insert("global_step".to_string(), Tensor::new(&[1234i64], &dev).unwrap());
    candle_core::safetensors::save(&t, path).unwrap();
    t
}

fn assert_same(got: &HashMap<String, Tensor>, want: &HashMap<String, Tensor>, keys: &[&String]) {
    let mut got_keys: Vec<&String> = got.keys().collect();
    got_keys.sort();
    let mut keys = keys.to_vec();
    keys.sort();
    assert_eq!(got_keys, keys, "key set");
    for k in keys {
        let (g, w) = (&got[k], &want[k]);
        assert_eq!(g.dtype(), w.dtype(), "{k}: dtype");
        assert_eq!(g.dims(), w.dims(), "{k}: shape");
        // Bit-exact (f16 → f32 is exact, so comparing the f32 bits compares the f16 bits).
        let bytes = |t: &Tensor| -> Vec<u8> {
            match t.dtype() {
                DType::F32 | DType::F16 => {
                    t.to_dtype(DType::F32).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap().iter().flat_map(|x| x.to_le_bytes()).collect()
                }
                DType::I64 => t.flatten_all().unwrap().to_vec1::<i64>().unwrap().iter().flat_map(|x| x.to_le_bytes()).collect(),
                d => panic!("{k}: unexpected dtype {d:?}"),
            }
        };
        assert_eq!(bytes(g), bytes(w), "{k}: values");
    }
}

#[test]
fn convert_keeps_the_prefixed_tensors_verbatim() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.safetensors");
    let want = tiny_checkpoint(&input);

    // Default prefix `encoder.`: only those keys, names unchanged.
    let out = dir.path().join("enc.safetensors");
    let o = convert(&input, &out, None);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("wrote 4 tensors"), "{}", String::from_utf8_lossy(&o.stderr));
    let got = candle_core::safetensors::load(&out, &Device::Cpu).unwrap();
    let enc: Vec<&String> = want.keys().filter(|k| k.starts_with("encoder.")).collect();
    assert_eq!(enc.len(), 4);
    assert_same(&got, &want, &enc);

    // Empty prefix: everything.
    let all = dir.path().join("all.safetensors");
    let o = convert(&input, &all, Some(""));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let got = candle_core::safetensors::load(&all, &Device::Cpu).unwrap();
    assert_same(&got, &want, &want.keys().collect::<Vec<_>>());

    // Another prefix.
    let r = dir.path().join("ref.safetensors");
    let o = convert(&input, &r, Some("refiner."));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let got = candle_core::safetensors::load(&r, &Device::Cpu).unwrap();
    assert_same(&got, &want, &want.keys().filter(|k| k.starts_with("refiner.")).collect::<Vec<_>>());
}

#[test]
fn convert_errors_are_clear() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.safetensors");
    tiny_checkpoint(&input);
    let err = |o: Output| {
        assert!(!o.status.success());
        String::from_utf8_lossy(&o.stderr).to_string()
    };
    // No key with the prefix: says so, names the file and the prefix; writes nothing.
    let out = dir.path().join("none.safetensors");
    let e = err(convert(&input, &out, Some("decoder.")));
    assert!(e.contains("in.safetensors") && e.contains("decoder."), "{e}");
    assert!(!out.exists());
    // --out equal to the input.
    let e = err(convert(&input, &input, None));
    assert!(e.contains("--out must differ"), "{e}");
    // Not a checkpoint.
    let junk = dir.path().join("junk.ckpt");
    std::fs::write(&junk, b"definitely not a checkpoint").unwrap();
    let e = err(convert(&junk, &dir.path().join("j.safetensors"), None));
    assert!(e.contains("junk.ckpt"), "{e}");
    // Missing input.
    let e = err(convert(&dir.path().join("missing.ckpt"), &dir.path().join("m.safetensors"), None));
    assert!(e.contains("missing.ckpt"), "{e}");
}
