//! Winograd F(2×2, 3×3) convolution (Lavin & Gray, "Fast Algorithms for Convolutional Neural Networks", 2016)
//! for CPU f32 inference: NCHW, 3×3 kernel, stride 1, padding 1, dilation 1, groups 1, any channel counts and
//! any H, W ≥ 1. Anything else (another device or dtype, differentiable mode, an input that records a graph,
//! another kernel shape) takes [`crate::conv2d`], so [`Winograd3x3::forward`] is a drop-in for a padded 3×3 conv.
//!
//! # Algorithm
//! Each output tile of 2×2 pixels is `Y = Aᵀ [Σ_c (G g_c Gᵀ) ⊙ (Bᵀ d_c B)] A` with `d_c` the 4×4 input patch
//! of channel `c` (zero outside the image: the padding) and `g_c` the 3×3 kernel, using the points {0, 1, −1, ∞}:
//! ```text
//!      ⎡1  0 −1  0⎤        ⎡ 1   0   0⎤
//! Bᵀ = ⎢0  1  1  0⎥    G = ⎢ ½   ½   ½⎥    Aᵀ = ⎡1 1  1  0⎤
//!      ⎢0 −1  1  0⎥        ⎢ ½  −½   ½⎥         ⎣0 1 −1 −1⎦
//!      ⎣0  1  0 −1⎦        ⎣ 0   0   1⎦
//! ```
//! [`Winograd3x3::new`] transforms the weights once (in f64, rounded to f32 once): 16 matrices
//! `U_k (C_in × C_out)`, k = 4ξ + ν. A forward pass cuts the tiles (N × ⌈H/2⌉ × ⌈W/2⌉) into blocks of whole
//! tile rows; each rayon task takes a block: the input transform writes 16 matrices `V_k (tiles × C_in)`
//! (tile index contiguous), then 16 single-threaded `gemm` products `M_k = V_k U_k (tiles × C_out)`, then the
//! output transform adds the bias (and the optional epilogue: residual, ReLU) and writes the 2×2 pixels. The
//! products hold 4 multiplies per output pixel and input channel instead of 9 (2.25× fewer FLOPs); the
//! scratch per task is `16·(C_in + C_out)·tiles` floats, ≈ 16·(C_in + C_out)·[`TARGET_TILES`] floats
//! (16 MiB at 256 → 256 channels; blocks shrink to keep it ≤ 16 MiB for wider layers), whatever the image
//! size: memory stays bounded (2 threads: ≤ 32 MiB besides the output). The transformed weights take 16/9 of
//! the weight's memory.
//! Measured on 2 Zen 4 cores (5 frames, VGGT DPT shapes, shared machine): 2.0–2.5× faster than the shifted-gemm
//! [`crate::conv2d`] (≈ 290–370 GFLOP/s counted as a direct convolution's FLOPs), 1.8× for 256 → 128 at
//! 168×296 (its 1.5 GB of transformed tiles stream through memory).
//!
//! # Error bound (f32, unit roundoff u = 2⁻²⁴, γ_n = nu/(1 − nu))
//! Per output pixel (p, q) of a tile, the kernel computes
//! `Ŷ = fl(Σ_{ξν} Aᵀ_pξ Aᵀ_qν M̂_ξν + b)` with `M̂_ξν = fl(Σ_c Û_ξν,c V̂_ξν,c)`, where
//! * `Û = fl(G g Gᵀ)` is computed in f64 and rounded once: `Û = U(1 + δ)`, |δ| ≤ u;
//! * `V̂ = fl(Bᵀ d B)`: every entry is ±d_a ± d_b ± d_c ± d_d of 4 inputs in two rounds of one addition
//!   (coefficients 0, ±1, exact): `V̂ = Σ_4 ±d (1 + θ₂)`, |θ₂| ≤ γ₂;
//! * the C_in-term dot products in any order (the gemm's blocking, FMAs or not): `(1 + θ_{C_in})`;
//! * the output transform sums 9 of the 16 `M̂` (each row of Aᵀ has 3 nonzeros ±1) in two rounds of two
//!   additions: `(1 + θ₄)`; the bias one more rounding; a residual one more.
//!
//! Multiplying the factors (|θ_a θ_b| folded into γ_{a+b}):
//! `|Ŷ − Y| ≤ γ_{C_in+8} · (Ŝ + |b|)` (+ γ₁|r| with a residual), with the *transform-domain absolute sum*
//! `Ŝ = Σ_c Σ_{ξν} |Aᵀ_pξ| |Aᵀ_qν| |U_ξν,c| (|Bᵀ| |d_c| |B|)_ξν`
//! (a ReLU after the sum cannot increase the error). The tests compute Ŝ in f64 per output and check the bound.
//! In units of the direct convolution's `S = Σ_{c,a,b} |g_c,ab| |x_c,ab|` (9·C_in terms): expanding Ŝ gives
//! 8 × 8 = 64 products |g||d| per channel, each with weight ≤ 1 (in 1-D, output 0 takes g₀·{d₀, d₂} from
//! ξ = 0 and ½·{g₀,g₁,g₂}×{d₁,d₂} from each of ξ = 1, 2: 2 + 3 + 3 = 8; output 1 likewise), so
//! `Ŝ ≤ 64 Σ_c max|g_c| max|d_c|` — the transform's amplification: with kernel and input magnitudes uniform
//! (|g| ≡ ḡ, |d| ≡ d̄, so S = 9 C_in ḡ d̄), Ŝ ≤ (64/9) S ≈ 7.1 S. The bound is then ≈ 7.1 (C_in + 8) u S,
//! against (9 C_in) u S for a direct convolution's `γ_{9C_in} S`: the same order (Winograd's dot products are
//! 9× shorter, its terms up to 7× larger). The cancellations are where Ŝ exceeds S: a kernel such as
//! (1, −1, 1) makes ½|g₀ + g₁ + g₂| small while its |·| sum is 3, and an input with large values beside a zero
//! patch has large |d| terms in Ŝ that S weights by |g| = 0 — which is why the bound is stated with Ŝ, not S.
//! F(4×4, 3×3) was not chosen: its points ±2, ±½ give transform entries up to 8 and amplification in the
//! hundreds (Ŝ/S), i.e. an error two orders of magnitude above a direct convolution's.
//!
//! # bf16 products (issue 73)
//! [`Winograd3x3::new_bf16`] keeps the transformed weights in bf16 only (`U_kᵀ`, C_out rows of ⌈C_in/2⌉
//! channel pairs, rounded to nearest even from f32 `Û` and packed once); the forward rounds each block's
//! `V̂_k` to bf16 pair rows and runs the 16 products in `vdpbf16ps` (`crate::bf16::conv_kernel`, f32
//! accumulation); transforms, bias and epilogue stay f32. Without AVX512-BF16 (or inside
//! [`crate::bf16::with_bf16_masked`] on the calling thread) the stored bf16 `U` is widened to f32 and the f32
//! kernel runs (storage only). Error: the two bf16 roundings (|ε| ≤ u₈ = 2⁻⁸ each) multiply every term of the
//! bound above, and the reduction runs over K = 2⌈C_in/2⌉ channels in ⌈K/512⌉ blocks (one more f32 rounding
//! each): `|Ŷ − Y| ≤ ((1 + u₈)²(1 + γ_n) − 1)·(Ŝ + |b|) + γ_n|r| + 18K·2⁻¹²⁶`, n = K + ⌈K/512⌉ + 8
//! (the last term: `vdpbf16ps` flushes denormal operands and partial sums, ≤ 2⁻¹²⁶ per term and addition, 9
//! `M` entries per output). First order ≈ (2u₈ + (C_in + 9)u)·Ŝ: the bf16 roundings dominate from the first
//! channel, independent of C_in, against f32's (C_in + 8)u.

use std::sync::Arc;

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use super::{conv2d, Conv2dConfig};
use crate::bf16::conv_kernel::{matmul_rows, pair_row, Bf16Rows};
use crate::bf16::{bf16_to_f32, Bf16Path};
use crate::mode::{cpu_f32, is_differentiable, with_f32};

/// Tiles per block (rounded to whole tile rows): large enough that each of the 16 products amortises the
/// gemm's packing of `U_k` (its cost ∝ C_in·C_out, the product's ∝ tiles·C_in·C_out).
pub const TARGET_TILES: usize = 512;

/// Scratch floats per task at most (16 MiB; the block shrinks for wide layers): `16·(C_in + C_out)·tiles`.
const MAX_SCRATCH: usize = 4 << 20;

const CFG: Conv2dConfig = Conv2dConfig { padding: 1, stride: 1, dilation: 1 };

const G: [[f64; 3]; 4] = [[1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.0, 0.0, 1.0]];

/// What [`Winograd3x3::forward_epilogue`] does around the convolution:
/// `out = act(conv(relu?(x)) + bias + relu?(residual))`, `act` = ReLU when `relu_output`, then GELU when
/// `gelu_output`.
#[derive(Debug, Clone, Copy, Default)]
pub struct WinogradEpilogue<'a> {
    /// Rectify the input as it is read (the convolution sees `relu(x)`).
    pub relu_input: bool,
    /// Added to the output (same shape), before the output ReLU.
    pub residual: Option<&'a Tensor>,
    /// Rectify the residual as it is added.
    pub relu_residual: bool,
    /// ReLU on the result.
    pub relu_output: bool,
    /// GELU (exact erf form) on the result, the values of [`crate::activation::gelu`] bit for bit: spares the
    /// caller a full-size intermediate.
    pub gelu_output: bool,
}

/// A 3×3, stride 1, padding 1 convolution with its Winograd-transformed weights (built once).
#[derive(Debug, Clone)]
pub struct Winograd3x3 {
    /// `(C_out, C_in, 3, 3)` as given: the fallback's weight.
    pub weight: Tensor,
    pub bias: Option<Tensor>,
    ci: usize,
    co: usize,
    /// `16 × C_out × C_in`: `U_k[c, o]` at `(k·C_out + o)·C_in + c`. None when the weight is not CPU f32.
    u: Option<Arc<[f32]>>,
    /// [`Winograd3x3::new_bf16`]: the 16 `U_kᵀ` in bf16 (then `u` is None).
    ub: Option<Arc<PackedU>>,
    b: Option<Arc<[f32]>>,
}

/// The 16 transformed weights `U_kᵀ` in bf16: C_out rows of ⌈C_in/2⌉ channel pairs each.
struct PackedU(Vec<Bf16Rows>);

impl std::fmt::Debug for PackedU {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PackedU(16 bf16 matrices)")
    }
}

/// `Û = fl32(G g Gᵀ)` of every (o, c) kernel: `16 × C_out × C_in`, `U_k[c, o]` at `(k·C_out + o)·C_in + c`.
fn transform_weights(w: &[f32], co: usize, ci: usize) -> Vec<f32> {
    let mut u = vec![0f32; 16 * co * ci];
    for o in 0..co {
        for c in 0..ci {
            let t = transform_kernel(&w[(o * ci + c) * 9..][..9]);
            for (k, v) in t.iter().enumerate() {
                u[(k * co + o) * ci + c] = *v as f32;
            }
        }
    }
    u
}

/// `G g Gᵀ` for one 3×3 kernel (f64).
fn transform_kernel(g: &[f32]) -> [f64; 16] {
    let mut out = [0f64; 16];
    for xi in 0..4 {
        for nu in 0..4 {
            let mut s = 0f64;
            for a in 0..3 {
                for b in 0..3 {
                    s += G[xi][a] * G[nu][b] * g[a * 3 + b] as f64;
                }
            }
            out[xi * 4 + nu] = s;
        }
    }
    out
}

impl Winograd3x3 {
    /// `weight (C_out, C_in, 3, 3)`, `bias (C_out)`. The transform is built when the weight is CPU f32;
    /// otherwise every forward takes [`crate::conv2d`].
    pub fn new(weight: &Tensor, bias: Option<&Tensor>) -> Result<Self> {
        let (co, ci, kh, kw) = weight.dims4()?;
        if let Some(b) = bias {
            if b.dims() != [co] {
                candle_core::bail!("winograd: bias {:?} for {co} output channels", b.dims());
            }
        }
        let build = kh == 3 && kw == 3 && cpu_f32(weight) && bias.is_none_or(cpu_f32);
        let (u, b) = if build {
            let u = with_f32(weight, |w| transform_weights(w, co, ci))?;
            let b = match bias {
                Some(b) => Some(Arc::from(with_f32(b, |v| v.to_vec())?)),
                None => None,
            };
            (Some(Arc::from(u)), b)
        } else {
            (None, None)
        };
        Ok(Self { weight: weight.clone(), bias: bias.cloned(), ci, co, u, ub: None, b })
    }

    /// [`Self::new`] with the transformed weights kept in bf16 only (rounded to nearest even from the f32
    /// `Û`, packed once; 8/9 of the f32 weight's memory): the 16 products run in `vdpbf16ps` where the calling
    /// thread's [`crate::bf16::path`] has it, else on `Û` widened back to f32 (storage only). See the module doc.
    pub fn new_bf16(weight: &Tensor, bias: Option<&Tensor>) -> Result<Self> {
        let mut me = Self::new(weight, bias)?;
        if let Some(u) = me.u.take() {
            let (co, ci) = (me.co, me.ci);
            let cpp = ci.div_ceil(2);
            let packed = (0..16)
                .map(|k| {
                    let uk = &u[k * co * ci..][..co * ci];
                    Bf16Rows::pack(co, cpp, |o, p| {
                        let at = |c: usize| if c < ci { uk[o * ci + c] } else { 0.0 };
                        (at(2 * p), at(2 * p + 1))
                    })
                })
                .collect();
            me.ub = Some(Arc::new(PackedU(packed)));
        }
        Ok(me)
    }

    /// Whether forwards of CPU f32 inputs run the Winograd kernel (false: always the fallback).
    pub fn is_transformed(&self) -> bool {
        self.u.is_some() || self.ub.is_some()
    }

    /// Whether the transformed weights are held in bf16 ([`Self::new_bf16`]).
    pub fn is_bf16(&self) -> bool {
        self.ub.is_some()
    }

    /// The bf16 `Û` widened to f32 (exact), in the f32 kernel's layout (the storage-only path's weights).
    fn widened_u(&self, pu: &PackedU) -> Vec<f32> {
        let (co, ci) = (self.co, self.ci);
        let mut u = vec![0f32; 16 * co * ci];
        for (k, a) in pu.0.iter().enumerate() {
            for o in 0..co {
                for c in 0..ci {
                    u[(k * co + o) * ci + c] = bf16_to_f32((a.word(o, c / 2) >> (16 * (c & 1))) as u16);
                }
            }
        }
        u
    }

    /// `conv2d(x, weight, bias, padding 1)`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_epilogue(x, WinogradEpilogue::default())
    }

    /// `act(conv(relu?(x)) + bias + relu?(residual))` (see [`WinogradEpilogue`]).
    pub fn forward_epilogue(&self, x: &Tensor, epi: WinogradEpilogue) -> Result<Tensor> {
        self.forward_blocked(x, epi, TARGET_TILES)
    }

    /// [`Self::forward_epilogue`] with `target_tiles` tiles per block (for benchmarks and tests).
    #[doc(hidden)]
    pub fn forward_blocked(&self, x: &Tensor, epi: WinogradEpilogue, target_tiles: usize) -> Result<Tensor> {
        let (n, c, h, w) = x.dims4()?;
        if c != self.ci {
            candle_core::bail!("conv2d: input has {c} channels, weight expects {}", self.ci);
        }
        let residual_ok = epi.residual.is_none_or(|r| cpu_f32(r) && !r.track_op() && r.dims() == [n, self.co, h, w]);
        if !(self.is_transformed() && cpu_f32(x) && !is_differentiable() && !x.track_op() && residual_ok) {
            return self.fallback(x, epi);
        }
        let geo = Geo { n, ci: c, co: self.co, h, w, th: h.div_ceil(2), tw: w.div_ceil(2) };
        let x = x.contiguous()?;
        let widened;
        let kernel = match (&self.u, &self.ub) {
            (Some(u), _) => Kernel::F32(u),
            (None, Some(pu)) if crate::bf16::path() == Bf16Path::Dpbf16 => Kernel::Bf16(&pu.0),
            (None, Some(pu)) => {
                widened = self.widened_u(pu);
                Kernel::F32(&widened)
            }
            (None, None) => unreachable!("checked by is_transformed"),
        };
        let out = with_f32(&x, |xd| match epi.residual {
            Some(r) => with_f32(r, |rd| winograd_any(xd, kernel, self.b.as_deref(), Some(rd), &geo, epi, target_tiles)),
            None => Ok(winograd_any(xd, kernel, self.b.as_deref(), None, &geo, epi, target_tiles)),
        })??;
        Tensor::from_vec(out, (n, self.co, h, w), x.device())
    }

    /// The same result from [`crate::conv2d`] and tensor ops.
    fn fallback(&self, x: &Tensor, epi: WinogradEpilogue) -> Result<Tensor> {
        let x = if epi.relu_input { x.relu()? } else { x.clone() };
        let mut y = conv2d(&x, &self.weight, self.bias.as_ref(), CFG)?;
        if let Some(r) = epi.residual {
            y = if epi.relu_residual { (y + r.relu()?)? } else { (y + r)? };
        }
        if epi.relu_output {
            y = y.relu()?;
        }
        if epi.gelu_output {
            y = crate::activation::gelu(&y)?;
        }
        Ok(y)
    }
}

/// `conv2d(x, weight, bias)` with padding 1 by Winograd F(2×2, 3×3) (transforms the weight on every call:
/// keep a [`Winograd3x3`] to reuse it). Other devices, dtypes and kernel shapes: [`crate::conv2d`].
pub fn conv2d_winograd3x3(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    Winograd3x3::new(weight, bias)?.forward(x)
}

#[derive(Debug, Clone, Copy)]
struct Geo {
    n: usize,
    ci: usize,
    co: usize,
    h: usize,
    w: usize,
    /// tile rows and columns
    th: usize,
    tw: usize,
}

/// The products' weights: f32 `Û` (the f32 layout) or the 16 bf16 `U_kᵀ`.
#[derive(Clone, Copy)]
enum Kernel<'a> {
    F32(&'a [f32]),
    Bf16(&'a [Bf16Rows]),
}

fn winograd_any(x: &[f32], k: Kernel, bias: Option<&[f32]>, res: Option<&[f32]>, g: &Geo, epi: WinogradEpilogue, target_tiles: usize) -> Vec<f32> {
    match k {
        Kernel::F32(u) => winograd_raw(x, u, bias, res, g, epi, target_tiles),
        Kernel::Bf16(ub) => winograd_raw_bf16(x, ub, bias, res, g, epi, target_tiles),
    }
}

#[derive(Clone, Copy)]
struct OutPtr(*mut f32);
// SAFETY: each task writes the output rows of its own tile rows only.
unsafe impl Send for OutPtr {}
unsafe impl Sync for OutPtr {}

/// Whole tile rows per block, about `target` tiles each, the block count a multiple of the thread count where
/// there are enough rows (no thread idles at the end): (rows per block, blocks).
fn row_blocks(rows: usize, tw: usize, target: usize) -> (usize, usize) {
    let threads = rayon::current_num_threads().max(1);
    let mut blocks = rows.div_ceil(target.div_ceil(tw));
    if rows >= threads {
        blocks = blocks.div_ceil(threads) * threads;
    }
    let rpb = rows.div_ceil(blocks);
    (rpb, rows.div_ceil(rpb))
}

/// The kernel on contiguous NCHW data; returns `(N, C_out, H, W)`.
fn winograd_raw(x: &[f32], u: &[f32], bias: Option<&[f32]>, res: Option<&[f32]>, g: &Geo, epi: WinogradEpilogue, target_tiles: usize) -> Vec<f32> {
    let Geo { n, ci, co, h, w, th, tw } = *g;
    let rows = n * th;
    let (rpb, blocks) = row_blocks(rows, tw, target_tiles.min(MAX_SCRATCH / (16 * (ci + co))).max(1));
    let mut out = vec![0f32; n * co * h * w];
    let optr = OutPtr(out.as_mut_ptr());
    (0..blocks).into_par_iter().for_each_init(
        || (Vec::<f32>::new(), Vec::<f32>::new(), Vec::<f32>::new()),
        |(v, m, tmp), bi| {
            let g0 = bi * rpb;
            let g1 = (g0 + rpb).min(rows);
            let t = (g1 - g0) * tw;
            v.resize(16 * ci * t, 0.0);
            m.resize(16 * co * t, 0.0);
            tmp.resize(16 * (tw + 1), 0.0);
            input_transform(x, v, tmp, g, g0, g1, epi.relu_input);
            for k in 0..16 {
                // M_k (t × co, column-major) = V_k (t × ci, column-major) · U_k (ci × co, column-major).
                // SAFETY: dst covers co columns of t floats in m; lhs ci columns of t floats in v; rhs co
                // columns of ci floats in u; all within their buffers (k < 16).
                unsafe {
                    gemm::gemm(
                        t,
                        co,
                        ci,
                        m.as_mut_ptr().add(k * co * t),
                        t as isize,
                        1,
                        false,
                        v.as_ptr().add(k * ci * t),
                        t as isize,
                        1,
                        u.as_ptr().add(k * co * ci),
                        ci as isize,
                        1,
                        0.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    );
                }
            }
            output_transform(m, tmp, bias, res, g, g0, g1, epi, optr);
        },
    );
    out
}

/// [`winograd_raw`] with the 16 products in bf16: per block the same f32 input transform, `V̂_k` rounded to
/// pair rows (`vp[(k·⌈C_in/2⌉ + p)·t + tile]`), `M_k (C_out × t) = U_kᵀ · V̂_k` by the rows gemm (its own
/// tasks nested in the block's), the same output transform.
fn winograd_raw_bf16(x: &[f32], ub: &[Bf16Rows], bias: Option<&[f32]>, res: Option<&[f32]>, g: &Geo, epi: WinogradEpilogue, target_tiles: usize) -> Vec<f32> {
    let Geo { n, ci, co, h, w, th, tw } = *g;
    let cpp = ci.div_ceil(2);
    let rows = n * th;
    let (rpb, blocks) = row_blocks(rows, tw, target_tiles.min(MAX_SCRATCH / (16 * (co + cpp))).max(1));
    let mut out = vec![0f32; n * co * h * w];
    let optr = OutPtr(out.as_mut_ptr());
    (0..blocks).into_par_iter().for_each_init(
        || (Vec::<f32>::new(), Vec::<f32>::new(), Vec::<u32>::new()),
        |(m, tmp, vp), bi| {
            let g0 = bi * rpb;
            let g1 = (g0 + rpb).min(rows);
            let t = (g1 - g0) * tw;
            m.resize(16 * co * t, 0.0);
            vp.resize(16 * cpp * t, 0);
            tmp.resize(16 * (tw + 1) + 32 * tw, 0.0);
            input_transform_pairs(x, vp, tmp, g, g0, g1, epi.relu_input);
            let brows: Vec<usize> = (0..cpp).map(|p| p * t).collect();
            for (k, a) in ub.iter().enumerate() {
                matmul_rows(a, 0, &vp[k * cpp * t..][..cpp * t], &brows, t, &mut m[k * co * t..][..co * t], t, 1.0, false);
            }
            output_transform(m, tmp, bias, res, g, g0, g1, epi, optr);
        },
    );
    out
}

#[inline(never)]
/// `V_k[c, tile]` at `v[(k·ci + c)·t + tile]` for the tiles of tile rows g0..g1 (global: image·th + row).
fn input_transform(x: &[f32], v: &mut [f32], tmp: &mut [f32], g: &Geo, g0: usize, g1: usize, relu: bool) {
    let t = (g1 - g0) * g.tw;
    for c in 0..g.ci {
        for gr in g0..g1 {
            let t0 = (gr - g0) * g.tw;
            transform_tile_row(x, tmp, g, c, gr, relu, v, |k| (k * g.ci + c) * t + t0);
        }
    }
}

#[inline(never)]
/// [`input_transform`] written as bf16 pair rows: `vp[(k·⌈ci/2⌉ + p)·t + tile]` = channels 2p, 2p + 1 of
/// `V̂_k` (f32, the same operations) rounded to nearest even; `tmp` ≥ 16·(tw + 1) + 32·tw floats.
fn input_transform_pairs(x: &[f32], vp: &mut [u32], tmp: &mut [f32], g: &Geo, g0: usize, g1: usize, relu: bool) {
    let (ci, tw) = (g.ci, g.tw);
    let (cpp, t) = (ci.div_ceil(2), (g1 - g0) * tw);
    let (tmp, two) = tmp.split_at_mut(16 * (tw + 1));
    let two = &mut two[..32 * tw];
    for p in 0..cpp {
        for gr in g0..g1 {
            let t0 = (gr - g0) * tw;
            for h in 0..2.min(ci - 2 * p) {
                transform_tile_row(x, tmp, g, 2 * p + h, gr, relu, two, |k| (2 * k + h) * tw);
            }
            for k in 0..16 {
                let hi = (2 * p + 1 < ci).then(|| &two[(2 * k + 1) * tw..][..tw]);
                pair_row(&two[2 * k * tw..][..tw], hi, &mut vp[(k * cpp + p) * t + t0..][..tw]);
            }
        }
    }
}

/// `V̂_k` of channel c for the tw tiles of tile row gr, written to `dst[off(k)..][..tw]`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn transform_tile_row(x: &[f32], tmp: &mut [f32], g: &Geo, c: usize, gr: usize, relu: bool, dst: &mut [f32], off: impl Fn(usize) -> usize) {
    let Geo { ci, h, w, th, tw, .. } = *g;
    let e = tw + 1;
    // tmp: 4 rows × (even, odd) de-interleaved padded columns: E_i[j] = d(row i, x = 2j − 1), O_i[j] = d(row i, x = 2j).
    let (ev, od) = tmp[..8 * e].split_at_mut(4 * e);
    let (b, tr) = (gr / th, gr % th);
    let plane = &x[(b * ci + c) * h * w..][..h * w];
    for i in 0..4 {
        let (er, or) = (&mut ev[i * e..][..e], &mut od[i * e..][..e]);
        let y = (2 * tr + i) as isize - 1;
        if y < 0 || y as usize >= h {
            er.fill(0.0);
            or.fill(0.0);
            continue;
        }
        let src = &plane[y as usize * w..][..w];
        // x = 2j − 1 for E (j ≥ 1), x = 2j for O; zeros past the image (O[tw], E[w/2 + 1..]).
        er[0] = 0.0;
        for ((o, ev), pair) in or.iter_mut().zip(&mut er[1..]).zip(src.chunks_exact(2)) {
            *o = pair[0];
            *ev = pair[1];
        }
        if w % 2 == 1 {
            or[w / 2] = src[w - 1];
        }
        or[tw] = 0.0;
        er[w / 2 + 1..].fill(0.0);
        if relu {
            er.iter_mut().chain(or.iter_mut()).for_each(|v| *v = v.max(0.0));
        }
    }
    // Rows: Bᵀ d (in place on both halves): r0 = d0 − d2, r1 = d1 + d2, r2 = d2 − d1, r3 = d1 − d3.
    for half in [&mut *ev, &mut *od] {
        let (r01, r23) = half.split_at_mut(2 * e);
        let (r0, r1) = r01.split_at_mut(e);
        let (r2, r3) = r23.split_at_mut(e);
        for (((d0, d1), d2), d3) in r0.iter_mut().zip(r1.iter_mut()).zip(r2.iter_mut()).zip(r3.iter_mut()) {
            (*d0, *d1, *d2, *d3) = (*d0 - *d2, *d1 + *d2, *d2 - *d1, *d1 - *d3);
        }
    }
    // Columns: (· B) with e0 = E[j], e1 = O[j], e2 = E[j+1], e3 = O[j+1].
    for xi in 0..4 {
        let er = &ev[xi * e..][..e];
        let or = &od[xi * e..][..e];
        let (e0, e2) = (&er[..tw], &er[1..]);
        let (e1, e3) = (&or[..tw], &or[1..]);
        let off = |nu: usize| off(xi * 4 + nu);
        dst[off(0)..][..tw].iter_mut().zip(e0.iter().zip(e2)).for_each(|(d, (a, b))| *d = a - b);
        dst[off(1)..][..tw].iter_mut().zip(e1.iter().zip(e2)).for_each(|(d, (a, b))| *d = a + b);
        dst[off(2)..][..tw].iter_mut().zip(e2.iter().zip(e1)).for_each(|(d, (a, b))| *d = a - b);
        dst[off(3)..][..tw].iter_mut().zip(e1.iter().zip(e3)).for_each(|(d, (a, b))| *d = a - b);
    }
}

#[inline(never)]
/// `Y = Aᵀ M A` per tile plus the epilogue, written to the output rows of tile rows g0..g1.
#[allow(clippy::too_many_arguments)]
fn output_transform(m: &[f32], tmp: &mut [f32], bias: Option<&[f32]>, res: Option<&[f32]>, g: &Geo, g0: usize, g1: usize, epi: WinogradEpilogue, optr: OutPtr) {
    let Geo { co, h, w, th, tw, .. } = *g;
    let t = (g1 - g0) * tw;
    let (ys, sv) = tmp[..12 * tw].split_at_mut(4 * tw);
    let (y0, y1) = ys.split_at_mut(2 * tw);
    for o in 0..co {
        let add = bias.map_or(0.0, |b| b[o]);
        for gr in g0..g1 {
            let (b, tr) = (gr / th, gr % th);
            let t0 = (gr - g0) * tw;
            let ms: [&[f32]; 16] = std::array::from_fn(|k| &m[(k * co + o) * t + t0..][..tw]);
            // y0/y1: output rows 2tr and 2tr + 1, interleaved (2j, 2j + 1).
            // Rows of Aᵀ: s_pν = Σ_ξ Aᵀ_pξ M_ξν (s0ν at sv[ν·tw..], s1ν at sv[(4 + ν)·tw..]).
            for nu in 0..4 {
                let (m0, m1, m2, m3) = (ms[nu], ms[4 + nu], ms[8 + nu], ms[12 + nu]);
                let (lo, hi) = sv.split_at_mut(4 * tw);
                let (s0, s1) = (&mut lo[nu * tw..][..tw], &mut hi[nu * tw..][..tw]);
                for (((((d0, d1), &a), &b), &c), &d) in s0.iter_mut().zip(s1.iter_mut()).zip(m0).zip(m1).zip(m2).zip(m3) {
                    *d0 = a + b + c;
                    *d1 = b - c - d;
                }
            }
            // Columns: y_p,2j = s_p0 + s_p1 + s_p2, y_p,2j+1 = s_p1 − s_p2 − s_p3.
            for (p, yr) in [&mut *y0, &mut *y1].into_iter().enumerate() {
                let sp = &sv[4 * p * tw..][..4 * tw];
                let (a, b, c, d) = (&sp[..tw], &sp[tw..2 * tw], &sp[2 * tw..3 * tw], &sp[3 * tw..]);
                for ((((pair, &a), &b), &c), &d) in yr.chunks_exact_mut(2).zip(a).zip(b).zip(c).zip(d) {
                    pair[0] = a + b + c;
                    pair[1] = b - c - d;
                }
            }
            for (p, yr) in [&*y0, &*y1].into_iter().enumerate() {
                let y = 2 * tr + p;
                if y >= h {
                    break;
                }
                let off = ((b * co + o) * h + y) * w;
                // SAFETY: output row (b, o, y) belongs to tile row gr, which only this task handles.
                let dst = unsafe { std::slice::from_raw_parts_mut(optr.0.add(off), w) };
                let src = &yr[..w];
                match res {
                    None => dst.iter_mut().zip(src).for_each(|(d, &s)| *d = s + add),
                    Some(r) => {
                        let r = &r[off..][..w];
                        if epi.relu_residual {
                            dst.iter_mut().zip(src).zip(r).for_each(|((d, &s), &r)| *d = (s + add) + r.max(0.0));
                        } else {
                            dst.iter_mut().zip(src).zip(r).for_each(|((d, &s), &r)| *d = (s + add) + r);
                        }
                    }
                }
                if epi.relu_output {
                    dst.iter_mut().for_each(|d| *d = d.max(0.0));
                }
                if epi.gelu_output {
                    crate::activation::gelu_erf_in_place(dst);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    const U: f64 = 1.0 / (1u64 << 24) as f64;

    fn gamma(k: usize) -> f64 {
        k as f64 * U / (1.0 - k as f64 * U)
    }

    /// splitmix64 → uniform in [−scale, scale).
    fn data(seed: u64, len: usize, scale: f32) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(1);
        (0..len)
            .map(|_| {
                s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let mut z = s;
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                z ^= z >> 31;
                ((z >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale
            })
            .collect()
    }

    /// f64 direct convolution (padding 1) of `relu?(x)`, and per output the bound's Ŝ (module docs).
    fn reference(x: &[f32], wt: &[f32], (n, ci, co, h, w): (usize, usize, usize, usize, usize), relu: bool) -> (Vec<f64>, Vec<f64>) {
        let xin = |b: usize, c: usize, y: isize, xx: isize| -> f64 {
            if y < 0 || xx < 0 || y as usize >= h || xx as usize >= w {
                return 0.0;
            }
            let v = x[((b * ci + c) * h + y as usize) * w + xx as usize] as f64;
            if relu {
                v.max(0.0)
            } else {
                v
            }
        };
        let bt: [[f64; 4]; 4] = [[1.0, 0.0, -1.0, 0.0], [0.0, 1.0, 1.0, 0.0], [0.0, -1.0, 1.0, 0.0], [0.0, 1.0, 0.0, -1.0]];
        let at: [[f64; 4]; 2] = [[1.0, 1.0, 1.0, 0.0], [0.0, 1.0, -1.0, -1.0]];
        let uabs: Vec<[f64; 16]> = (0..co * ci).map(|oc| transform_kernel(&wt[oc * 9..][..9]).map(f64::abs)).collect();
        let mut exact = vec![0f64; n * co * h * w];
        let mut shat = vec![0f64; n * co * h * w];
        for b in 0..n {
            for o in 0..co {
                for y in 0..h {
                    for xx in 0..w {
                        let mut s = 0f64;
                        for c in 0..ci {
                            for ky in 0..3 {
                                for kx in 0..3 {
                                    s += wt[((o * ci + c) * 3 + ky) * 3 + kx] as f64 * xin(b, c, (y + ky) as isize - 1, (xx + kx) as isize - 1);
                                }
                            }
                        }
                        exact[((b * co + o) * h + y) * w + xx] = s;
                        // Ŝ: the tile containing (y, xx), its patch origin and the pixel's (p, q) in it.
                        let (y0, x0, p, q) = ((y / 2 * 2) as isize - 1, (xx / 2 * 2) as isize - 1, y % 2, xx % 2);
                        let mut sh = 0f64;
                        for c in 0..ci {
                            let ua = &uabs[o * ci + c];
                            for xi in 0..4 {
                                for nu in 0..4 {
                                    let a = at[p][xi].abs() * at[q][nu].abs();
                                    if a == 0.0 {
                                        continue;
                                    }
                                    let mut vd = 0f64;
                                    for i in 0..4 {
                                        for j in 0..4 {
                                            vd += bt[xi][i].abs() * bt[nu][j].abs() * xin(b, c, y0 + i as isize, x0 + j as isize).abs();
                                        }
                                    }
                                    sh += a * ua[xi * 4 + nu] * vd;
                                }
                            }
                        }
                        shat[((b * co + o) * h + y) * w + xx] = sh;
                    }
                }
            }
        }
        (exact, shat)
    }

    /// Max over outputs of |got − want| / bound (≤ 1 passes).
    fn worst(got: &[f32], want: &[f64], bound: &[f64]) -> f64 {
        got.iter().zip(want).zip(bound).map(|((&g, &r), &b)| (g as f64 - r).abs() / b).fold(0.0, f64::max)
    }

    fn tensor(v: &[f32], shape: &[usize]) -> Tensor {
        Tensor::from_vec(v.to_vec(), shape, &Device::Cpu).unwrap()
    }

    fn vec4(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    }

    const SHAPES: [(usize, usize, usize, usize, usize); 10] = [
        (1, 1, 1, 1, 1),
        (1, 3, 2, 1, 7),
        (2, 5, 3, 9, 1),
        (1, 17, 4, 2, 2),
        (2, 7, 6, 2, 5),
        (3, 20, 9, 7, 9),
        (2, 33, 16, 6, 13),
        (1, 40, 24, 16, 15),
        (1, 6, 5, 5, 2),
        (4, 9, 3, 3, 4),
    ];

    #[test]
    fn winograd_within_derived_bound_and_one_percent_fails() {
        for seed in 0..3u64 {
            for (si, &(n, ci, co, h, w)) in SHAPES.iter().enumerate() {
                let sd = seed * 100 + si as u64;
                let x = data(sd, n * ci * h * w, 1.0);
                // Mixed magnitudes: some inputs 100× larger, to exercise the cancellation Ŝ accounts for.
                let x: Vec<f32> = x.iter().enumerate().map(|(i, &v)| if i % 7 == 3 { v * 100.0 } else { v }).collect();
                let wt = data(sd + 50, co * ci * 9, 0.5);
                let bias = data(sd + 70, co, 2.0);
                let (exact, shat) = reference(&x, &wt, (n, ci, co, h, w), false);
                for with_bias in [false, true] {
                    let wb = with_bias.then(|| tensor(&bias, &[co]));
                    let wg = Winograd3x3::new(&tensor(&wt, &[co, ci, 3, 3]), wb.as_ref()).unwrap();
                    assert!(wg.is_transformed());
                    let xt = tensor(&x, &[n, ci, h, w]);
                    let want: Vec<f64> = exact.iter().enumerate().map(|(i, &e)| e + if with_bias { bias[i / (h * w) % co] as f64 } else { 0.0 }).collect();
                    let bound: Vec<f64> = shat
                        .iter()
                        .enumerate()
                        .map(|(i, &s)| gamma(ci + 8) * (s + if with_bias { bias[i / (h * w) % co].abs() as f64 } else { 0.0 }))
                        .collect();
                    // Default blocks, and one tile row per block (many blocks, partial ones).
                    for tiles in [TARGET_TILES, 1, 5] {
                        let got = vec4(&wg.forward_blocked(&xt, WinogradEpilogue::default(), tiles).unwrap());
                        let r = worst(&got, &want, &bound);
                        assert!(r <= 1.0, "seed {seed} shape {:?} bias {with_bias} tiles {tiles}: error {r} × bound", (n, ci, co, h, w));
                        let moved: Vec<f32> = got.iter().map(|v| v * 1.01).collect();
                        let rm = worst(&moved, &want, &bound);
                        assert!(rm > 1.0, "seed {seed} shape {:?}: a 1 % change passes the bound ({rm})", (n, ci, co, h, w));
                    }
                    let free = vec4(&conv2d_winograd3x3(&xt, &tensor(&wt, &[co, ci, 3, 3]), wb.as_ref()).unwrap());
                    assert!(worst(&free, &want, &bound) <= 1.0);
                }
            }
        }
    }

    #[test]
    fn winograd_epilogue_within_bound() {
        for (si, &(n, ci, co, h, w)) in SHAPES.iter().enumerate() {
            let sd = 1000 + si as u64;
            let x = data(sd, n * ci * h * w, 1.0);
            let wt = data(sd + 1, co * ci * 9, 0.5);
            let bias = data(sd + 2, co, 1.0);
            let res = data(sd + 3, n * co * h * w, 3.0);
            let (exact, shat) = reference(&x, &wt, (n, ci, co, h, w), true);
            let wg = Winograd3x3::new(&tensor(&wt, &[co, ci, 3, 3]), Some(&tensor(&bias, &[co]))).unwrap();
            let xt = tensor(&x, &[n, ci, h, w]);
            let rt = tensor(&res, &[n, co, h, w]);
            for (relu_residual, relu_output) in [(true, false), (false, true), (true, true)] {
                let epi = WinogradEpilogue { relu_input: true, residual: Some(&rt), relu_residual, relu_output, gelu_output: false };
                let pre = |i: usize| exact[i] + bias[i / (h * w) % co] as f64 + if relu_residual { res[i].max(0.0) as f64 } else { res[i] as f64 };
                let want: Vec<f64> = (0..exact.len()).map(|i| if relu_output { pre(i).max(0.0) } else { pre(i) }).collect();
                let bound: Vec<f64> = (0..exact.len()).map(|i| gamma(ci + 9) * (shat[i] + bias[i / (h * w) % co].abs() as f64 + res[i].abs() as f64)).collect();
                for tiles in [TARGET_TILES, 1] {
                    let got = vec4(&wg.forward_blocked(&xt, epi, tiles).unwrap());
                    let r = worst(&got, &want, &bound);
                    assert!(r <= 1.0, "shape {:?} {relu_residual} {relu_output}: error {r} × bound", (n, ci, co, h, w));
                }
                // The fallback (differentiable mode) computes the same.
                let _g = crate::mode::differentiable();
                let fb = vec4(&wg.forward_epilogue(&xt, epi).unwrap());
                assert!(worst(&fb, &want, &bound) <= 1.0, "fallback epilogue {:?}", (n, ci, co, h, w));
            }
        }
    }

    /// The GELU epilogue gives the separate [`crate::activation::gelu`]'s values bit for bit (f32 and bf16 `Û`,
    /// several block sizes), and the fallback the same as its tensor ops.
    #[test]
    fn winograd_gelu_epilogue_is_the_separate_gelu() {
        for (si, &(n, ci, co, h, w)) in SHAPES.iter().enumerate() {
            let sd = 2000 + si as u64;
            let x = tensor(&data(sd, n * ci * h * w, 2.0), &[n, ci, h, w]);
            let wt = tensor(&data(sd + 1, co * ci * 9, 0.5), &[co, ci, 3, 3]);
            let bias = tensor(&data(sd + 2, co, 1.0), &[co]);
            let epi = WinogradEpilogue { gelu_output: true, ..Default::default() };
            for wg in [Winograd3x3::new(&wt, Some(&bias)).unwrap(), Winograd3x3::new_bf16(&wt, Some(&bias)).unwrap()] {
                for tiles in [TARGET_TILES, 1, 5] {
                    let plain = wg.forward_blocked(&x, WinogradEpilogue::default(), tiles).unwrap();
                    let want = vec4(&crate::activation::gelu(&plain).unwrap());
                    let got = vec4(&wg.forward_blocked(&x, epi, tiles).unwrap());
                    assert!(want.iter().zip(vec4(&plain)).any(|(g, p)| *g != p), "GELU changed nothing");
                    let same = got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits());
                    assert!(same, "shape {:?} bf16 {} tiles {tiles}: the GELU epilogue differs from gelu()", (n, ci, co, h, w), wg.is_bf16());
                }
            }
            let wg = Winograd3x3::new(&wt, Some(&bias)).unwrap();
            let _g = crate::mode::differentiable();
            let fb = vec4(&wg.forward_epilogue(&x, epi).unwrap());
            let want = vec4(&crate::activation::gelu(&crate::conv2d(&x, &wt, Some(&bias), CFG).unwrap()).unwrap());
            assert!(fb.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "fallback GELU epilogue {:?}", (n, ci, co, h, w));
        }
    }

    const U8: f64 = 1.0 / 256.0;

    /// A bf16 operand as `vdpbf16ps` reads it (nearest even, denormals to zero).
    fn r8(x: f32) -> f64 {
        crate::bf16::bf16_to_f32_daz(crate::bf16::f32_to_bf16(x)) as f64
    }

    /// The kernel's f32 `V̂ = Bᵀ d B` (same operations, same order) of the tile (ty, tx) of image b, channel c.
    fn v_hat(x: &[f32], (ci, h, w): (usize, usize, usize), relu: bool, b: usize, c: usize, ty: usize, tx: usize) -> [f32; 16] {
        let d = |i: usize, j: usize| -> f32 {
            let (y, xx) = ((2 * ty + i) as isize - 1, (2 * tx + j) as isize - 1);
            if y < 0 || xx < 0 || y as usize >= h || xx as usize >= w {
                return 0.0;
            }
            let v = x[((b * ci + c) * h + y as usize) * w + xx as usize];
            if relu {
                v.max(0.0)
            } else {
                v
            }
        };
        let bt = |a: [f32; 4]| [a[0] - a[2], a[1] + a[2], a[2] - a[1], a[1] - a[3]];
        let cols: [[f32; 4]; 4] = std::array::from_fn(|j| bt([d(0, j), d(1, j), d(2, j), d(3, j)]));
        let mut out = [0f32; 16];
        for xi in 0..4 {
            let r = bt([cols[0][xi], cols[1][xi], cols[2][xi], cols[3][xi]]);
            out[xi * 4..][..4].copy_from_slice(&r);
        }
        out
    }

    /// Per output: the f64 result of the bf16-rounded operands (`r8(Û)·r8(V̂)` summed exactly, the output
    /// transform and bias exact) and the transform-domain absolute sum of those terms.
    fn rounded_reference(x: &[f32], wt: &[f32], (n, ci, co, h, w): (usize, usize, usize, usize, usize), relu: bool) -> (Vec<f64>, Vec<f64>) {
        let u = transform_weights(wt, co, ci);
        let at: [[f64; 4]; 2] = [[1.0, 1.0, 1.0, 0.0], [0.0, 1.0, -1.0, -1.0]];
        let (th, tw) = (h.div_ceil(2), w.div_ceil(2));
        let mut want = vec![0f64; n * co * h * w];
        let mut sabs = vec![0f64; n * co * h * w];
        for b in 0..n {
            for ty in 0..th {
                for tx in 0..tw {
                    let vs: Vec<[f64; 16]> = (0..ci).map(|c| v_hat(x, (ci, h, w), relu, b, c, ty, tx).map(r8)).collect();
                    for o in 0..co {
                        let (mut m, mut ma) = ([0f64; 16], [0f64; 16]);
                        for (c, v) in vs.iter().enumerate() {
                            for k in 0..16 {
                                let t = r8(u[(k * co + o) * ci + c]) * v[k];
                                m[k] += t;
                                ma[k] += t.abs();
                            }
                        }
                        for p in 0..2 {
                            for q in 0..2 {
                                let (y, xx) = (2 * ty + p, 2 * tx + q);
                                if y >= h || xx >= w {
                                    continue;
                                }
                                let i = ((b * co + o) * h + y) * w + xx;
                                for k in 0..16 {
                                    want[i] += at[p][k / 4] * at[q][k % 4] * m[k];
                                    sabs[i] += (at[p][k / 4] * at[q][k % 4]).abs() * ma[k];
                                }
                            }
                        }
                    }
                }
            }
        }
        (want, sabs)
    }

    /// The bf16 products within the module's bound against the f64 direct convolution of the unrounded
    /// operands, and within the f32 summation's γ against the f64 sum of the bf16-rounded operands (the tight
    /// check: a truncating conversion fails it); a result 1 % off fails the tight check, one 1 % past its
    /// bound the loose one; masked it is the f32 kernel on the
    /// widened `Û`, bit for bit. Shapes off the 12 × 32 tile, odd C_in, C_in = 515 (two 256-pair blocks), tile
    /// rows of 35 tiles (two column panels), blocks of 1 and 5 tiles, with and without bias and epilogue.
    #[test]
    fn winograd_bf16_within_derived_bound_on_seeds_and_shapes() {
        let dpbf16 = crate::bf16::path() == crate::bf16::Bf16Path::Dpbf16;
        if !dpbf16 {
            eprintln!("no AVX512-BF16 on this CPU: only the storage-only path is checked");
        }
        let shapes: Vec<(usize, usize, usize, usize, usize)> = SHAPES.iter().copied().chain([(1, 515, 5, 4, 6), (1, 8, 13, 3, 70)]).collect();
        let (mut worst_loose, mut worst_tight) = (0f64, 0f64);
        for seed in 0..2u64 {
            for (si, &(n, ci, co, h, w)) in shapes.iter().enumerate() {
                let sd = 500 + seed * 100 + si as u64;
                let x = data(sd, n * ci * h * w, 1.0);
                let x: Vec<f32> = x.iter().enumerate().map(|(i, &v)| if i % 7 == 3 { v * 100.0 } else { v }).collect();
                let wt = data(sd + 50, co * ci * 9, 0.5);
                let bias = data(sd + 70, co, 2.0);
                let res = data(sd + 90, n * co * h * w, 3.0);
                let kk = 2 * ci.div_ceil(2);
                let nn = kk + kk.div_ceil(512) + 8;
                let flush = 18.0 * kk as f64 * 2f64.powi(-126);
                let loose = (1.0 + U8) * (1.0 + U8) * (1.0 + gamma(nn)) - 1.0;
                let tight = gamma(kk + kk.div_ceil(512) + 5);
                let xt = tensor(&x, &[n, ci, h, w]);
                let rt = tensor(&res, &[n, co, h, w]);
                let wg = Winograd3x3::new_bf16(&tensor(&wt, &[co, ci, 3, 3]), Some(&tensor(&bias, &[co]))).unwrap();
                assert!(wg.is_transformed() && wg.is_bf16());
                let f32_u = transform_weights(&wt, co, ci);
                let geo = Geo { n, ci, co, h, w, th: h.div_ceil(2), tw: w.div_ceil(2) };
                for relu_in in [false, true] {
                    let (exact, shat) = reference(&x, &wt, (n, ci, co, h, w), relu_in);
                    let (rwant, rabs) = rounded_reference(&x, &wt, (n, ci, co, h, w), relu_in);
                    let epi = if relu_in {
                        WinogradEpilogue { relu_input: true, residual: Some(&rt), relu_residual: true, relu_output: false, gelu_output: false }
                    } else {
                        WinogradEpilogue::default()
                    };
                    let r_add = |i: usize| if relu_in { res[i].max(0.0) as f64 } else { 0.0 };
                    let bi = |i: usize| bias[i / (h * w) % co] as f64;
                    let want: Vec<f64> = (0..exact.len()).map(|i| exact[i] + bi(i) + r_add(i)).collect();
                    let bound: Vec<f64> = (0..exact.len()).map(|i| loose * (shat[i] + bi(i).abs()) + gamma(nn) * r_add(i).abs() + flush).collect();
                    let twant: Vec<f64> = (0..exact.len()).map(|i| rwant[i] + bi(i) + r_add(i)).collect();
                    let tbound: Vec<f64> = (0..exact.len()).map(|i| tight * (rabs[i] + bi(i).abs() + r_add(i).abs()) + flush).collect();
                    for tiles in [TARGET_TILES, 1, 5] {
                        let got = vec4(&wg.forward_blocked(&xt, epi, tiles).unwrap());
                        let tag = format!("seed {seed} shape {:?} relu/residual {relu_in} tiles {tiles}", (n, ci, co, h, w));
                        // Masked: the f32 kernel on the widened Û, bit for bit.
                        let masked = crate::bf16::with_bf16_masked(|| vec4(&wg.forward_blocked(&xt, epi, tiles).unwrap()));
                        let wide = wg.widened_u(wg.ub.as_deref().unwrap());
                        let rd = relu_in.then_some(&res[..]);
                        let f32_wide = winograd_raw(&x, &wide, Some(&bias), rd, &geo, epi, tiles);
                        assert!(
                            masked.iter().zip(&f32_wide).all(|(a, b)| a.to_bits() == b.to_bits()),
                            "{tag}: masked is not the f32 kernel on the widened weights"
                        );
                        assert!(worst(&masked, &want, &bound) <= 1.0, "{tag}: masked off the bound");
                        if !dpbf16 {
                            continue;
                        }
                        let r = worst(&got, &want, &bound);
                        assert!(r <= 1.0, "{tag}: error {r} × bound");
                        let rt_ = worst(&got, &twant, &tbound);
                        assert!(rt_ <= 1.0, "{tag}: {rt_} × the rounded operands' f32-summation bound");
                        (worst_loose, worst_tight) = (worst_loose.max(r), worst_tight.max(rt_));
                        let moved: Vec<f32> = got.iter().map(|v| v * 1.01).collect();
                        assert!(worst(&moved, &twant, &tbound) > 1.0, "{tag}: a 1 % change passes the tight check");
                        // One result moved 1 % past its derived bound fails it.
                        let mut past = got.clone();
                        past[0] = (want[0] + 1.01 * bound[0]) as f32;
                        assert!(worst(&past, &want, &bound) > 1.0, "{tag}: a result past the bound passes");
                        // The packed products ran: some result differs from the f32 kernel's.
                        let f32_out = winograd_raw(&x, &f32_u, Some(&bias), rd, &geo, epi, tiles);
                        if n * ci * h * w > 8 {
                            assert!(got.iter().zip(&f32_out).any(|(a, b)| a != b), "{tag}: equal to f32 (bf16 products did not run?)");
                        }
                    }
                }
            }
        }
        eprintln!("largest |error| / bound: {worst_loose:.3} (unrounded operands), {worst_tight:.3} (rounded operands)");
    }

    #[test]
    fn winograd_falls_back_to_conv2d() {
        let (n, ci, co, h, w) = (2, 6, 4, 5, 7);
        let x = tensor(&data(1, n * ci * h * w, 1.0), &[n, ci, h, w]);
        let wt = tensor(&data(2, co * ci * 9, 0.5), &[co, ci, 3, 3]);
        let b = tensor(&data(3, co, 1.0), &[co]);
        let direct = vec4(&conv2d(&x, &wt, Some(&b), CFG).unwrap());
        let close = |a: &[f32], tag: &str| {
            let d = a.iter().zip(&direct).map(|(p, q)| (p - q).abs()).fold(0f32, f32::max);
            assert!(d < 1e-4, "{tag}: {d}");
        };
        let wg = Winograd3x3::new(&wt, Some(&b)).unwrap();
        // Differentiable mode: conv2d's path, and the gradient flows.
        {
            let _g = crate::mode::differentiable();
            let xv = candle_core::Var::from_tensor(&x).unwrap();
            let y = wg.forward(xv.as_tensor()).unwrap();
            close(&vec4(&y), "differentiable");
            let grads = y.sum_all().unwrap().backward().unwrap();
            assert!(grads.get(xv.as_tensor()).is_some());
        }
        // An input that records a graph (a Var) outside differentiable mode: conv2d too (keeps the graph).
        let xv = candle_core::Var::from_tensor(&x).unwrap();
        let y = wg.forward(xv.as_tensor()).unwrap();
        close(&vec4(&y), "tracked input");
        assert!(y.track_op());
        // A non-f32 weight: no transform, every forward falls back (conv2d in f64).
        let w64 = Winograd3x3::new(&wt.to_dtype(DType::F64).unwrap(), Some(&b.to_dtype(DType::F64).unwrap())).unwrap();
        assert!(!w64.is_transformed());
        let y64 = w64.forward(&x.to_dtype(DType::F64).unwrap()).unwrap();
        assert_eq!(y64.dtype(), DType::F64);
        close(&vec4(&y64.to_dtype(DType::F32).unwrap()), "f64");
        // Another kernel size: conv2d with padding 1.
        let w5 = tensor(&data(4, co * ci * 25, 0.2), &[co, ci, 5, 5]);
        let wg5 = Winograd3x3::new(&w5, None).unwrap();
        assert!(!wg5.is_transformed());
        let y5 = wg5.forward(&x).unwrap();
        assert_eq!(y5.dims(), [n, co, h - 2, w - 2]);
        let d5 = vec4(&conv2d(&x, &w5, None, CFG).unwrap());
        assert_eq!(vec4(&y5), d5);
        // Wrong channel count: an error, not a panic.
        assert!(wg.forward(&Tensor::zeros((1, ci + 1, h, w), DType::F32, &Device::Cpu).unwrap()).is_err());
    }
}
