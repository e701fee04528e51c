//! Links scripts/build-flash-attn's `libflashattention.a` when the `link` feature is on; otherwise does nothing,
//! so that workspace builds without the library (and without CUDA) compile this crate as an empty one.
//!
//! Environment: `FLASH_ATTN_LIB_DIR` (default `<workspace>/target/flash-attn/lib`), and for the static CUDA
//! runtime `CUDA_LIB_DIR`, else `$CUDA_HOME` / `$CUDA_PATH` / `/usr/local/cuda` (`lib64` or `lib`).

use std::path::{Path, PathBuf};

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    if std::env::var_os("CARGO_FEATURE_LINK").is_none() {
        return;
    }
    for v in ["FLASH_ATTN_LIB_DIR", "CUDA_LIB_DIR", "CUDA_HOME", "CUDA_PATH"] {
        println!("cargo:rerun-if-env-changed={v}");
    }
    let manifest = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let dir = std::env::var_os("FLASH_ATTN_LIB_DIR").map(PathBuf::from).unwrap_or_else(|| manifest.join("../../target/flash-attn/lib"));
    let lib = dir.join("libflashattention.a");
    if !lib.is_file() {
        panic!(
            "mvsplat360-flash-attn-sys: {} not found. Build it with `nice -n 19 scripts/build-flash-attn` \
             (docs/research/flash-attention-build.md), or point FLASH_ATTN_LIB_DIR at the folder holding it.",
            lib.display()
        );
    }
    println!("cargo:rerun-if-changed={}", lib.display());
    println!("cargo:rustc-link-search=native={}", dir.display());
    println!("cargo:rustc-link-lib=static=flashattention");

    // libflashattention.a calls the CUDA runtime API (kernel launches, cudaFuncSetAttribute). The PyPI runtime
    // wheel ships libcudart_static.a but no libcudart.so link, so link the static runtime.
    let cudart = cudart_dir().unwrap_or_else(|| {
        panic!(
            "mvsplat360-flash-attn-sys: libcudart_static.a not found; set CUDA_LIB_DIR (or CUDA_HOME, as \
             scripts/check-cuda does)"
        )
    });
    println!("cargo:rerun-if-changed={}", cudart.join("libcudart_static.a").display());
    println!("cargo:rustc-link-search=native={}", cudart.display());
    println!("cargo:rustc-link-lib=static=cudart_static");
    for l in ["stdc++", "dl", "rt", "pthread"] {
        println!("cargo:rustc-link-lib=dylib={l}");
    }
}

fn cudart_dir() -> Option<PathBuf> {
    let has = |d: &Path| d.join("libcudart_static.a").is_file();
    if let Some(d) = std::env::var_os("CUDA_LIB_DIR").map(PathBuf::from) {
        return has(&d).then_some(d);
    }
    let roots = ["CUDA_HOME", "CUDA_PATH"].iter().filter_map(|v| std::env::var_os(v).map(PathBuf::from));
    roots.chain([PathBuf::from("/usr/local/cuda")]).flat_map(|r| [r.join("lib64"), r.join("lib")]).find(|d| has(d))
}
