//! With the `cuda` feature: compile cuda/fused.cu to PTX for src/fused_cuda.rs (nvcc from $NVCC or PATH,
//! architecture from $MVSPLAT360_CUDA_ARCH, default sm_80), as crates/splat/build.rs does for the rasterizer.
//! Without it: nothing.

use std::path::PathBuf;
use std::process::Command;

fn main() {
    let src = "cuda/fused.cu";
    println!("cargo:rerun-if-changed={src}");
    println!("cargo:rerun-if-env-changed=NVCC");
    println!("cargo:rerun-if-env-changed=MVSPLAT360_CUDA_ARCH");
    if std::env::var_os("CARGO_FEATURE_CUDA").is_none() {
        return;
    }
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("cargo sets OUT_DIR")).join("fused.ptx");
    let nvcc = std::env::var("NVCC").unwrap_or_else(|_| "nvcc".into());
    let arch = std::env::var("MVSPLAT360_CUDA_ARCH").unwrap_or_else(|_| "sm_80".into());
    let status = Command::new(&nvcc).args(["--ptx", &format!("-arch={arch}"), "-O3", "-o"]).arg(&out).arg(src).status().unwrap_or_else(|e| {
        panic!(
            "cannot run `{nvcc}` ({e}): the `cuda` feature of mvsplat360-nn compiles {src} with nvcc; install the CUDA \
             toolkit or set NVCC (scripts/check-cuda shows a pip-installed nvcc)"
        )
    });
    assert!(status.success(), "nvcc failed on {src} (arch {arch}); set MVSPLAT360_CUDA_ARCH for older GPUs");
}
