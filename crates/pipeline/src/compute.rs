//! Where the pipeline runs (`--device`), the refiner's precision (`--dtype`) and the encoder's
//! (`--encoder-dtype`).

use candle_core::{DType, Device};

use crate::error::{flag, Result};

/// `--device`: `cpu`, `cuda` (GPU 0) or `cuda:N`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceSpec {
    #[default]
    Cpu,
    Cuda(usize),
}

impl std::str::FromStr for DeviceSpec {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "auto" => Ok(Self::detect()),
            "cpu" => Ok(Self::Cpu),
            "cuda" => Ok(Self::Cuda(0)),
            _ => match s.strip_prefix("cuda:").map(str::parse::<usize>) {
                Some(Ok(n)) => Ok(Self::Cuda(n)),
                _ => Err(format!("`{s}` is not a device: use auto, cpu, cuda or cuda:N (N = GPU index)")),
            },
        }
    }
}

impl std::fmt::Display for DeviceSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Cpu => write!(f, "cpu"),
            Self::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

/// GPUs this binary can open (0 without CUDA).
pub fn cuda_device_count() -> usize {
    if !candle_core::utils::cuda_is_available() {
        return 0;
    }
    (0..64).take_while(|&i| Device::new_cuda(i).is_ok()).count()
}

impl DeviceSpec {
    /// GPU 0 when this binary has CUDA and a GPU answers, else the CPU (`--device auto`).
    pub fn detect() -> Self {
        if candle_core::utils::cuda_is_available() && Device::new_cuda(0).is_ok() {
            Self::Cuda(0)
        } else {
            Self::Cpu
        }
    }

    /// Open the device; a CUDA request in a build without CUDA says how to get one.
    pub fn open(&self) -> Result<Device> {
        match self {
            Self::Cpu => Ok(Device::Cpu),
            Self::Cuda(n) => {
                if !candle_core::utils::cuda_is_available() {
                    return Err(flag(
                        "--device",
                        format!(
                            "{self}: this binary was built without CUDA; build it with `cargo build --release --features cuda` \
                             (nvcc at build time, an NVIDIA driver at run time; see docs/gpu.md) or use --device cpu"
                        ),
                    ));
                }
                Device::new_cuda(*n).map_err(|e| flag("--device", format!("{self}: cannot open the GPU: {e}")))
            }
        }
    }
}

/// `--dtype` of the refiner (UNet, VAE, CLIP): f32 (default), f16 or bf16. On the CPU, bf16 keeps f32
/// activations and multiplies bf16 weights packed once at load (`vdpbf16ps` where the CPU has AVX512-BF16,
/// storage only otherwise: see [`cpu_bf16_path`]); f16 stores the weights in f16 and widens them for the f32
/// kernels (the CPU has no f16 dot product). The encoder's precision is `--encoder-dtype`.
pub fn parse_dtype(s: &str) -> std::result::Result<DType, String> {
    match s {
        "f32" | "fp32" => Ok(DType::F32),
        "f16" | "fp16" => Ok(DType::F16),
        "bf16" => Ok(DType::BF16),
        _ => Err(format!("`{s}` is not a refiner dtype: use f32, f16 or bf16")),
    }
}

/// `--encoder-dtype` of the models before the rasterizer (the encoder; VGGT in `pose`): f32 (default, as the
/// official code) or bf16 (CPU: weights packed once in bf16, f32 activations rounded to bf16 inside the
/// products). A separate flag from `--dtype` because the encoder's depth places the Gaussians.
pub fn parse_encoder_dtype(s: &str) -> std::result::Result<DType, String> {
    match s {
        "f32" | "fp32" => Ok(DType::F32),
        "bf16" => Ok(DType::BF16),
        _ => Err(format!("`{s}` is not an --encoder-dtype: use f32 or bf16")),
    }
}

/// Device and precisions of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct Compute {
    pub device: DeviceSpec,
    pub refiner_dtype: DType,
    /// The encoder's precision (`--encoder-dtype`; bf16 on the CPU only).
    pub encoder_dtype: DType,
}

impl Default for Compute {
    fn default() -> Self {
        Self { device: DeviceSpec::Cpu, refiner_dtype: DType::F32, encoder_dtype: DType::F32 }
    }
}

impl Compute {
    /// Open the device, refusing a bf16 encoder on a GPU (its packed bf16 products are CPU kernels; the GPU
    /// encoder runs f32). CPU bf16 on a CPU without AVX512-BF16 is said once (weights stored in bf16, f32
    /// arithmetic: half the weights' memory, no speed-up).
    pub fn open(&self) -> Result<Device> {
        if self.encoder_dtype == DType::BF16 && self.device != DeviceSpec::Cpu {
            return Err(flag("--encoder-dtype", format!("bf16 runs on the CPU only (--device cpu); on {} the encoder runs in f32", self.device)));
        }
        if let Some(path) = self.cpu_bf16_path() {
            if path != mvsplat360_nn::bf16::Bf16Path::Dpbf16 {
                static SAID: std::sync::Once = std::sync::Once::new();
                SAID.call_once(|| {
                    tracing::warn!("bf16 on this CPU: {} — the bf16 models' weights take half the memory, their arithmetic stays f32", path.name())
                });
            }
        }
        self.device.open()
    }

    /// How the bf16 products run on this CPU (None unless `--device cpu` with `--dtype bf16` or
    /// `--encoder-dtype bf16`); recorded in what a run writes.
    pub fn cpu_bf16_path(&self) -> Option<mvsplat360_nn::bf16::Bf16Path> {
        (self.device == DeviceSpec::Cpu && (self.refiner_dtype == DType::BF16 || self.encoder_dtype == DType::BF16)).then(mvsplat360_nn::bf16::path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_and_dtype_spellings() {
        assert_eq!("cpu".parse::<DeviceSpec>(), Ok(DeviceSpec::Cpu));
        assert_eq!("cuda".parse::<DeviceSpec>(), Ok(DeviceSpec::Cuda(0)));
        assert_eq!("cuda:3".parse::<DeviceSpec>(), Ok(DeviceSpec::Cuda(3)));
        for bad in ["gpu", "cuda:", "cuda:x", "CPU", ""] {
            let e = bad.parse::<DeviceSpec>().unwrap_err();
            assert!(e.contains("cpu, cuda or cuda:N"), "{bad}: {e}");
        }
        assert_eq!(parse_dtype("bf16"), Ok(DType::BF16));
        assert_eq!(parse_dtype("f16"), Ok(DType::F16));
        assert_eq!(parse_dtype("f32"), Ok(DType::F32));
        assert!(parse_dtype("f64").unwrap_err().contains("f32, f16 or bf16"));
    }

    /// Without the `cuda` feature, `--device cuda` is refused with the build instruction, not a panic.
    #[cfg(not(feature = "cuda"))]
    #[test]
    fn cuda_without_the_feature_says_how_to_build_it() {
        let e = DeviceSpec::Cuda(0).open().unwrap_err().to_string();
        assert!(e.starts_with("--device: cuda:0:") && e.contains("--features cuda"), "{e}");
        assert!(DeviceSpec::Cpu.open().unwrap().is_cpu());
    }

    #[test]
    fn bf16_on_the_cpu_opens_and_names_its_path() {
        let c = Compute { device: DeviceSpec::Cpu, refiner_dtype: DType::BF16, ..Default::default() };
        assert!(c.open().unwrap().is_cpu());
        assert_eq!(c.cpu_bf16_path(), Some(mvsplat360_nn::bf16::path()));
        let masked = mvsplat360_nn::bf16::with_bf16_masked(|| c.cpu_bf16_path());
        assert_eq!(masked, Some(mvsplat360_nn::bf16::Bf16Path::StorageOnly));
        assert_eq!(Compute { device: DeviceSpec::Cpu, refiner_dtype: DType::F16, ..Default::default() }.cpu_bf16_path(), None);
        assert_eq!(Compute { device: DeviceSpec::Cuda(0), refiner_dtype: DType::BF16, ..Default::default() }.cpu_bf16_path(), None);
        let enc = Compute { encoder_dtype: DType::BF16, ..Default::default() };
        assert_eq!(enc.cpu_bf16_path(), Some(mvsplat360_nn::bf16::path()));
        assert!(enc.open().unwrap().is_cpu());
    }

    #[test]
    fn encoder_dtype_spellings_and_gpu_refusal() {
        assert_eq!(parse_encoder_dtype("f32"), Ok(DType::F32));
        assert_eq!(parse_encoder_dtype("fp32"), Ok(DType::F32));
        assert_eq!(parse_encoder_dtype("bf16"), Ok(DType::BF16));
        for bad in ["f16", "fp16", "BF16", "f64", ""] {
            let e = parse_encoder_dtype(bad).unwrap_err();
            assert!(e.contains("--encoder-dtype") && e.contains("f32 or bf16"), "{bad}: {e}");
        }
        let e = Compute { device: DeviceSpec::Cuda(0), encoder_dtype: DType::BF16, ..Default::default() }.open().unwrap_err().to_string();
        assert!(e.starts_with("--encoder-dtype: bf16 runs on the CPU only"), "{e}");
    }
}
