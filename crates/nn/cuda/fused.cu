// Fused element-wise kernels for the refiner on CUDA (see src/fused_cuda.rs for the launch sequence):
//
// GroupNorm (+ per-channel affine, + optional SiLU) of x (N, C, S), N = B·frames, statistics of group g of
// batch b pooled over the `frames` consecutive items b·frames .. b·frames + frames − 1 (channels g·cg ..
// (g+1)·cg of each, cg = C / groups), biased variance, eps inside the square root — norm.rs::group_norm.
//   1. gn_partial_*: one block per chunk of one (item, group) run (a run is cg·S contiguous values), chunks
//      of at most GN_THREADS·GN_ITEMS values held in registers: the chunk's mean c, then Σ(x−c) and Σ(x−c)²
//      about it (two passes over registers, one read of memory).
//   2. gn_finalize: one block per (b, g) merges its chunks in f64: mean m = Σ(n·c + Σ(x−c)) / n_total,
//      M2 = Σ[Σ(x−c)² + 2(c−m)·Σ(x−c) + n(c−m)²] (exact for any shift c; Σ(x−c) ≈ 0 keeps it well
//      conditioned). Frames are pooled by indexing, never by a transpose.
//   3. gn_apply_*: y = (x − m)·(rstd·w) + b, then SiLU; element-wise.
//
// GEGLU (diffusers/sgm `GEGLU`: hidden, gate = proj(x).chunk(2, -1); hidden · gelu(gate), exact erf GELU):
//   geglu_*: h (M, 2H) (+ bias (2H), f32, optional) → (M, H), one block per row.
//
// Types: x / h / outputs in f32, f16 or bf16 (suffix _f32, _f16, _bf16), arithmetic in f32 (statistics
// merged in f64), weights, biases and statistics in f32. Compiles as C++ with emulate.h + emulate_half.h
// (emulate_main.cpp) so its logic is tested without a GPU; block reductions use shared memory and
// __syncthreads only (no warp shuffles, which the emulation does not model).
#ifdef __CUDACC__
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#endif

// Full unrolling keeps gn_partial's per-thread values in registers.
#ifdef __CUDACC__
#define UNROLL _Pragma("unroll")
#else
#define UNROLL
#endif

#define GN_THREADS 256
#define GN_ITEMS 16
// Largest chunk of gn_partial (values per block).
#define GN_CHUNK (GN_THREADS * GN_ITEMS)
#define EW_THREADS 256

typedef long long i64;

__device__ __forceinline__ float to_f(float v) { return v; }
__device__ __forceinline__ float to_f(__half v) { return __half2float(v); }
__device__ __forceinline__ float to_f(__nv_bfloat16 v) { return __bfloat162float(v); }

__device__ __forceinline__ void store_f(float* p, float v) { *p = v; }
__device__ __forceinline__ void store_f(__half* p, float v) { *p = __float2half(v); }
__device__ __forceinline__ void store_f(__nv_bfloat16* p, float v) { *p = __float2bfloat16(v); }

// Sum of v over the block (blockDim.x == GN_THREADS, a power of two); every thread gets the result. `sh` is
// a shared array of GN_THREADS; a barrier at the end lets the caller reuse it.
template <class A>
__device__ __forceinline__ A block_sum(A v, A* sh) {
    const unsigned t = threadIdx.x;
    sh[t] = v;
    __syncthreads();
    for (unsigned s = GN_THREADS / 2; s > 0; s >>= 1) {
        if (t < s) sh[t] += sh[t + s];
        __syncthreads();
    }
    const A r = sh[0];
    __syncthreads();
    return r;
}

// grid (frames · chunks_per_run, B · groups), block GN_THREADS. Run length len = cg · S; chunk ≤ GN_CHUNK.
// part[((b·groups + g)·frames + f)·chunks_per_run + k] = (n, c, Σ(x−c), Σ(x−c)²) as 4 floats.
template <class T>
__device__ void gn_partial(const T* __restrict__ x, float* __restrict__ part, int groups, int frames, int channels,
                           int cg, i64 s, int chunk, int chunks_per_run) {
    __shared__ float sh[GN_THREADS];
    const unsigned t = threadIdx.x;
    const int f = blockIdx.x / chunks_per_run, k = blockIdx.x % chunks_per_run;
    const int bg = blockIdx.y, b = bg / groups, g = bg % groups;
    const i64 len = (i64)cg * s;
    const i64 start = (i64)k * chunk;
    const i64 rem = len - start;
    const int n = (int)(rem < chunk ? rem : chunk);
    const T* src = x + ((i64)(b * frames + f) * channels + (i64)g * cg) * s + start;
    float v[GN_ITEMS];
    float sum = 0.f;
    UNROLL
    for (int j = 0; j < GN_ITEMS; ++j) {
        const int i = (int)t + j * GN_THREADS;
        v[j] = i < n ? to_f(src[i]) : 0.f;
        sum += v[j];
    }
    const float c = block_sum(sum, sh) / (float)n;
    float d1 = 0.f, d2 = 0.f;
    UNROLL
    for (int j = 0; j < GN_ITEMS; ++j) {
        const int i = (int)t + j * GN_THREADS;
        const float d = i < n ? v[j] - c : 0.f;
        d1 += d;
        d2 += d * d;
    }
    d1 = block_sum(d1, sh);
    d2 = block_sum(d2, sh);
    if (t == 0) {
        float* p = part + 4 * (((i64)bg * frames + f) * chunks_per_run + k);
        p[0] = (float)n;
        p[1] = c;
        p[2] = d1;
        p[3] = d2;
    }
}

// grid (B · groups), block GN_THREADS: merges the chunks of each (b, g) into stats[2·bg] = mean,
// stats[2·bg + 1] = 1 / sqrt(var + eps).
extern "C" __global__ void gn_finalize(const float* __restrict__ part, float* __restrict__ stats, int chunks, float eps) {
    __shared__ double sh[GN_THREADS];
    const unsigned t = threadIdx.x;
    const float* p = part + 4 * (i64)blockIdx.x * chunks;
    double cnt = 0.0, tot = 0.0;
    for (int k = t; k < chunks; k += GN_THREADS) {
        cnt += (double)p[4 * k];
        tot += (double)p[4 * k] * (double)p[4 * k + 1] + (double)p[4 * k + 2];
    }
    cnt = block_sum(cnt, sh);
    tot = block_sum(tot, sh);
    const double m = tot / cnt;
    double m2 = 0.0;
    for (int k = t; k < chunks; k += GN_THREADS) {
        const double dc = (double)p[4 * k + 1] - m;
        m2 += (double)p[4 * k + 3] + 2.0 * dc * (double)p[4 * k + 2] + (double)p[4 * k] * dc * dc;
    }
    m2 = block_sum(m2, sh);
    if (t == 0) {
        const double var = m2 > 0.0 ? m2 / cnt : 0.0;
        stats[2 * blockIdx.x] = (float)m;
        stats[2 * blockIdx.x + 1] = (float)(1.0 / sqrt(var + (double)eps));
    }
}

// grid (N · C, ⌈S / (EW_THREADS · per-thread)⌉ capped at 65535), block EW_THREADS; a block-stride loop
// covers the rest of the row.
template <class T>
__device__ void gn_apply(const T* __restrict__ x, T* __restrict__ y, const float* __restrict__ stats,
                         const float* __restrict__ w, const float* __restrict__ bias, int groups, int frames,
                         int channels, int cg, i64 s, int silu) {
    const i64 row = blockIdx.x;
    const int ch = (int)(row % channels);
    const int item = (int)(row / channels);
    const int bg = (item / frames) * groups + ch / cg;
    const float m = stats[2 * bg];
    const float a = stats[2 * bg + 1] * w[ch];
    const float o = bias[ch];
    const T* src = x + row * s;
    T* dst = y + row * s;
    for (i64 i = (i64)blockIdx.y * EW_THREADS + threadIdx.x; i < s; i += (i64)gridDim.y * EW_THREADS) {
        float v = (to_f(src[i]) - m) * a + o;
        if (silu) v = v / (1.f + expf(-v));
        store_f(dst + i, v);
    }
}

// grid (M), block EW_THREADS: out[r, j] = (h[r, j] + b[j]) · gelu(h[r, H + j] + b[H + j]), b optional.
template <class T>
__device__ void geglu(const T* __restrict__ h, const float* __restrict__ bias, T* __restrict__ out, int hdim) {
    const i64 r = blockIdx.x;
    const T* src = h + r * 2 * hdim;
    T* dst = out + r * hdim;
    for (int j = threadIdx.x; j < hdim; j += EW_THREADS) {
        float a = to_f(src[j]);
        float g = to_f(src[hdim + j]);
        if (bias) {
            a += bias[j];
            g += bias[hdim + j];
        }
        // 0.70710678118654752 = 1/√2: exact-erf GELU, as torch's nn.GELU() default.
        store_f(dst + j, a * (0.5f * g * (1.f + erff(g * 0.70710678118654752f))));
    }
}

#define FUSED_KERNELS(SUF, T)                                                                                    \
    extern "C" __global__ void gn_partial_##SUF(const T* x, float* part, int groups, int frames, int channels,    \
                                                int cg, i64 s, int chunk, int chunks_per_run) {                  \
        gn_partial<T>(x, part, groups, frames, channels, cg, s, chunk, chunks_per_run);                          \
    }                                                                                                            \
    extern "C" __global__ void gn_apply_##SUF(const T* x, T* y, const float* stats, const float* w,              \
                                              const float* bias, int groups, int frames, int channels, int cg,   \
                                              i64 s, int silu) {                                                 \
        gn_apply<T>(x, y, stats, w, bias, groups, frames, channels, cg, s, silu);                                \
    }                                                                                                            \
    extern "C" __global__ void geglu_##SUF(const T* h, const float* bias, T* out, int hdim) {                    \
        geglu<T>(h, bias, out, hdim);                                                                            \
    }

FUSED_KERNELS(f32, float)
FUSED_KERNELS(f16, __half)
FUSED_KERNELS(bf16, __nv_bfloat16)
