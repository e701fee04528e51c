//! Which of the GPU-specific kernels a CUDA run uses, chosen at run time so that one binary measures each
//! one's A/B on a lent GPU in the same sitting. `MVSPLAT360_GPU_OPS` is a comma-separated list of
//! [`GpuOp`] names, `all` or `none` (the default: candle's compositions, the path every CUDA build has).
//! CPU runs ignore it.

use std::sync::OnceLock;

/// The environment variable that selects the GPU kernels.
pub const ENV: &str = "MVSPLAT360_GPU_OPS";

/// A GPU kernel family that replaces a composition of candle ops.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GpuOp {
    /// Convolutions on cuDNN with cached plans (tensor-op math in f16/bf16), bias in the same call.
    Cudnn,
    /// GroupNorm + affine + SiLU and GEGLU as single kernels.
    Fused,
    /// Attention without a materialised score tensor.
    Flash,
}

impl GpuOp {
    pub const ALL: [GpuOp; 3] = [GpuOp::Cudnn, GpuOp::Fused, GpuOp::Flash];

    pub fn name(self) -> &'static str {
        match self {
            GpuOp::Cudnn => "cudnn",
            GpuOp::Fused => "fused",
            GpuOp::Flash => "flash",
        }
    }

    fn bit(self) -> u8 {
        1 << (self as u8)
    }
}

/// A set of [`GpuOp`]s.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct GpuOps(u8);

impl GpuOps {
    pub fn contains(self, op: GpuOp) -> bool {
        self.0 & op.bit() != 0
    }

    pub fn names(self) -> Vec<&'static str> {
        GpuOp::ALL.into_iter().filter(|&o| self.contains(o)).map(GpuOp::name).collect()
    }
}

impl std::str::FromStr for GpuOps {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let mut set = 0u8;
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            match part {
                "all" => set = GpuOp::ALL.iter().fold(0, |a, o| a | o.bit()),
                "none" => set = 0,
                _ => match GpuOp::ALL.into_iter().find(|o| o.name() == part) {
                    Some(o) => set |= o.bit(),
                    None => {
                        return Err(format!(
                            "{ENV}: unknown GPU op `{part}`; use a comma-separated list of {}, or `all` / `none`",
                            GpuOp::ALL.map(GpuOp::name).join(", ")
                        ))
                    }
                },
            }
        }
        Ok(GpuOps(set))
    }
}

static SELECTED: OnceLock<Result<GpuOps, String>> = OnceLock::new();

/// The set `MVSPLAT360_GPU_OPS` selects (read once per process), or its parse error. Commands call this at
/// start so that a typo stops the run with the message instead of silently falling back.
pub fn from_env() -> Result<GpuOps, String> {
    SELECTED.get_or_init(|| std::env::var(ENV).map_or(Ok(GpuOps::default()), |v| v.parse())).clone()
}

/// Whether `op` is selected (an invalid variable selects nothing; [`from_env`] reports it).
pub fn enabled(op: GpuOp) -> bool {
    from_env().is_ok_and(|s| s.contains(op))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_lists_all_and_none() {
        let s: GpuOps = "cudnn, fused".parse().unwrap();
        assert!(s.contains(GpuOp::Cudnn) && s.contains(GpuOp::Fused) && !s.contains(GpuOp::Flash));
        assert_eq!("all".parse::<GpuOps>().unwrap().names(), ["cudnn", "fused", "flash"]);
        assert_eq!("".parse::<GpuOps>().unwrap(), GpuOps::default());
        assert_eq!("all,none".parse::<GpuOps>().unwrap(), GpuOps::default());
        let e = "cudnn,flashh".parse::<GpuOps>().unwrap_err();
        assert!(e.contains("flashh") && e.contains(ENV), "{e}");
    }
}
