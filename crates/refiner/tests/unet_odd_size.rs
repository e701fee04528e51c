//! VideoUNet at latent sizes that do not divide by 2^(levels−1) (6×10 and 5×7 with 3 levels): upsampling to
//! the skip connection's size as diffusers does, against diffusers' outputs made with the fixture folder's own
//! tiny SVD weights: `svd/svd_unet_odd_size.safetensors`, which scripts/fixtures/official_svd.py writes beside
//! the weights of any seed. The shared folder predates that file: for its weights (checked by their SHA-256) the
//! same outputs are in `tests/fixtures/unet_odd_size/`, made by scripts/fixtures/unet_odd_size.py.

use candle_core::{Device, Tensor};
use mvsplat360_refiner::unet::util::timestep_embedding;
use mvsplat360_refiner::unet::{UNetInputs, VideoUNet, VideoUNetConfig};
use mvsplat360_testkit::fixture;

/// The shared folder's `svd/svd_unet.safetensors`, which the crate's own outputs belong to.
const SHARED_UNET_SHA256: &str = "87edf008a8d94969baa8d3229a784dfff4394e145b1cd1eebae0e2df99eebc65";

fn sha256(p: &std::path::Path) -> String {
    use sha2::Digest;
    let bytes = std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    sha2::Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// The odd-size outputs for the fixture folder's UNet weights.
fn outputs() -> std::collections::HashMap<String, Tensor> {
    let beside = mvsplat360_testkit::fixtures_dir().join("svd/svd_unet_odd_size.safetensors");
    let p = if beside.is_file() {
        beside
    } else {
        let weights = fixture("svd/svd_unet.safetensors");
        assert_eq!(
            sha256(&weights),
            SHARED_UNET_SHA256,
            "{} are not the shared weights and no svd_unet_odd_size.safetensors is beside them: make the folder with scripts/fixtures/official_svd.py, which writes it",
            weights.display()
        );
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/unet_odd_size/odd_size.safetensors")
    };
    candle_core::safetensors::load(&p, &Device::Cpu).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn odd_latent_sizes_match_diffusers() {
    let cfg = VideoUNetConfig::from_diffusers_json(&fixture("svd/svd_unet_config.json")).unwrap();
    let unet = VideoUNet::load(&fixture("svd/svd_unet.safetensors"), None, &cfg, &Device::Cpu).unwrap();
    let fx = outputs();
    for case in ["a", "b"] {
        let s = &fx[&format!("{case}.sample")]; // (1, F, 8, h, w)
        let (b, f, c, h, w) = s.dims5().unwrap();
        let n = b * f;
        let x = s.reshape((n, c, h, w)).unwrap();
        let ctx = fx[&format!("{case}.context")].clone(); // (1, 1, D)
        let d = ctx.dim(2).unwrap();
        let ctx = ctx.broadcast_as((n, 1, d)).unwrap().contiguous().unwrap();
        let t = fx[&format!("{case}.timestep")].to_vec1::<f32>().unwrap()[0];
        let aug = fx[&format!("{case}.cond_aug")].to_vec1::<f32>().unwrap()[0];
        let y = timestep_embedding(&vec![aug; n], cfg.adm_in_channels.unwrap(), 10000.0, &Device::Cpu).unwrap();
        let out = unet
            .forward(&UNetInputs { x: &x, timesteps: &vec![t; n], context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None })
            .unwrap_or_else(|e| panic!("{case} ({h}x{w}): {e}"));
        let want = fx[&format!("{case}.output")].reshape((n, 4, h, w)).unwrap();
        // One UNet call: the model of tests/unet.rs (1e-5 × max|ref|, float32 on both sides).
        mvsplat360_testkit::assert_check(&format!("{case} ({h}x{w})"), &out, &want, mvsplat360_testkit::Tol::of_max(1e-5));
    }
}

/// Any latent size runs (no `cat` shape error) at 2, 3 and 4 levels and keeps its size; random weights.
#[test]
fn any_latent_size_runs_at_2_3_4_levels() {
    for mult in [vec![1, 2], vec![1, 2, 2], vec![1, 2, 2, 2]] {
        let cfg = VideoUNetConfig { channel_mult: mult.clone(), ..VideoUNetConfig::tiny() };
        let unet = VideoUNet::random(&cfg, 7, &Device::Cpu).unwrap();
        for (h, w) in [(1, 1), (2, 3), (5, 7), (6, 10), (9, 13), (8, 8)] {
            let f = 2;
            let x = Tensor::randn(0f32, 1f32, (f, 8, h, w), &Device::Cpu).unwrap();
            let ctx = Tensor::randn(0f32, 1f32, (f, 1, 32), &Device::Cpu).unwrap();
            let y = timestep_embedding(&[0.02; 2], 32, 10000.0, &Device::Cpu).unwrap();
            let out = unet
                .forward(&UNetInputs { x: &x, timesteps: &[1.0; 2], context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None })
                .unwrap_or_else(|e| panic!("{} levels, {h}x{w}: {e}", mult.len()));
            assert_eq!(out.dims(), &[f, 4, h, w], "{} levels, {h}x{w}", mult.len());
            let v = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert!(v.iter().all(|x| x.is_finite()), "{} levels, {h}x{w}: non-finite output", mult.len());
        }
    }
}
