// CUDA kernels of the MVSplat360 Gaussian rasterizer (latentSplat fork of graphdeco's
// diff-gaussian-rasterization: RGB plus latent feature channels), float32, plain CUDA C++.
// Semantics are those of crates/splat/src/cpu (the reference) and the fixture README
// (/work/shared/fixtures/rasterizer/README.md). The backward gives the official gradients
// (GradMode::Official, with its five deviations from the true derivative) or, with `exact`, the true
// derivative including the feature, alpha and depth images (GradMode::Exact).
//
// Launch sequence (host side, see emulate_main.cpp; every kernel is 1-D over 256 threads unless stated):
//   rast_preprocess            per Gaussian: cull, EWA 2D covariance, conic, radius, pixel centre, SH colour
//   rast_scan_block/scan_add   exclusive scan of tiles_touched (recursive over block sums) -> pair offsets
//   rast_duplicate             one (key, Gaussian) pair per touched tile; key = tile << 32 | depth bits
//   rast_fill_pad              pad the pairs to a power of two with maximal keys
//   rast_bitonic_step          one launch per bitonic pass; order (tile, depth, Gaussian id): deterministic
//   rast_tile_ranges           [start, end) of every tile in the sorted pairs (ranges zeroed before)
//   rast_render_fwd            grid = tiles, block = 16x16 (one thread per pixel)
//   rast_render_bwd            grid = tiles, block = 16x16; atomically accumulates per-Gaussian gradients
//                              (output buffers zeroed before)
//   rast_preprocess_bwd        per Gaussian chain rule: 2D -> 3D covariance, scales/quats, means, SH
//   rast_unpack_cols/pack_cols the candle op's packed per-Gaussian matrix <-> per-field buffers (src/cuda.rs)
//
// Camera / settings travel as one float array `params` (layout P_*); images are planar (C,H,W).
//
// Numerics: nvcc contracts a*b+c into FMA by default and atomicAdd order varies from run to run, so GPU
// gradients are nondeterministic in the last bits and differ from the CPU path by rounding; compare with
// tolerances. The same file compiles as C++ with emulate.h (tested on CPU by tests/cuda_emulated.rs).

#define TILE 16
#define BLOCK_SIZE 256
// Feature channels per Gaussian handled by the tile kernels (MVSplat360 uses 4).
#define MAX_FEAT 16

// Layout of `params`.
#define P_VIEW 0     // world-to-camera 4x4, row-major
#define P_PROJ 16    // full projection (P @ view) 4x4, row-major
#define P_CAMPOS 32  // camera centre (3)
#define P_FOCAL 35   // fx, fy as the kernel recomputes them from tan(fov)
#define P_TANFOV 37  // tan(fov/2) x, y
#define P_BG 39      // background RGB
#define P_LEN 42

typedef unsigned long long u64;

static __device__ __forceinline__ int imin(int a, int b) { return a < b ? a : b; }

// trunc(v) clamped to [0, hi]; NaN -> 0 (the CPU path's saturating cast).
static __device__ __forceinline__ int trunc_clamp(float v, int hi) {
    if (!(v > 0.0f)) return 0;
    if (v >= (float)hi) return hi;
    return (int)v;
}

// Tile rectangle [x0, x1) x [y0, y1) touched by a Gaussian at pixel (mx, my) with the given radius.
static __device__ __forceinline__ void tile_rect(float mx, float my, int radius, int gx, int gy, int* r) {
    const float rf = (float)radius;
    r[0] = trunc_clamp((mx - rf) / TILE, gx);
    r[1] = trunc_clamp((my - rf) / TILE, gy);
    r[2] = trunc_clamp((mx + rf + TILE - 1) / TILE, gx);
    r[3] = trunc_clamp((my + rf + TILE - 1) / TILE, gy);
}

static __device__ __forceinline__ void view_point(const float* params, const float* p, float* t) {
    const float* v = params + P_VIEW;
    for (int r = 0; r < 3; r++) t[r] = v[4 * r] * p[0] + v[4 * r + 1] * p[1] + v[4 * r + 2] * p[2] + v[4 * r + 3];
}

// Homogeneous row r of the full projection applied to p.
static __device__ __forceinline__ float proj_row(const float* params, int r, const float* p) {
    const float* m = params + P_PROJ + 4 * r;
    return m[0] * p[0] + m[1] * p[1] + m[2] * p[2] + m[3];
}

// Standard rotation matrix of an unnormalised quaternion (w, x, y, z).
static __device__ __forceinline__ void quat_rot(const float* q, float R[3][3]) {
    const float w = q[0], x = q[1], y = q[2], z = q[3];
    R[0][0] = 1.f - 2.f * (y * y + z * z);
    R[0][1] = 2.f * (x * y - w * z);
    R[0][2] = 2.f * (x * z + w * y);
    R[1][0] = 2.f * (x * y + w * z);
    R[1][1] = 1.f - 2.f * (x * x + z * z);
    R[1][2] = 2.f * (y * z - w * x);
    R[2][0] = 2.f * (x * z - w * y);
    R[2][1] = 2.f * (y * z + w * x);
    R[2][2] = 1.f - 2.f * (x * x + y * y);
}

// Upper triangle (00, 01, 02, 11, 12, 22) of Sigma = R diag(s)^2 R^T, or the precomputed one.
static __device__ __forceinline__ void cov3d_of(int i, const float* cov3d_in, const float* scales, const float* quats,
                                                float* c) {
    if (cov3d_in) {
        for (int k = 0; k < 6; k++) c[k] = cov3d_in[6 * i + k];
        return;
    }
    float R[3][3];
    quat_rot(quats + 4 * i, R);
    const float s2[3] = {scales[3 * i] * scales[3 * i], scales[3 * i + 1] * scales[3 * i + 1],
                         scales[3 * i + 2] * scales[3 * i + 2]};
    const int ia[6] = {0, 0, 0, 1, 1, 2}, ib[6] = {0, 1, 2, 1, 2, 2};
    for (int k = 0; k < 6; k++) {
        const int a = ia[k], b = ib[k];
        c[k] = R[a][0] * R[b][0] * s2[0] + R[a][1] * R[b][1] * s2[1] + R[a][2] * R[b][2] * s2[2];
    }
}

// EWA splatting: M = J W (2x3, W the view rotation) and cov2D = M Sigma M^T + 0.3 I.
struct Ewa {
    float t[3];   // view-space mean with x/z, y/z clamped to 1.3 tan(fov)
    bool clamp_x, clamp_y;
    float m[2][3];
    float cov2d[3];  // a, b, c
};

static __device__ __forceinline__ void ewa(const float* params, const float* tv, const float* cov, Ewa& e) {
    const float limx = 1.3f * params[P_TANFOV], limy = 1.3f * params[P_TANFOV + 1];
    const float tz = tv[2];
    const float txtz = tv[0] / tz, tytz = tv[1] / tz;
    e.clamp_x = txtz < -limx || txtz > limx;
    e.clamp_y = tytz < -limy || tytz > limy;
    const float tx = fminf(limx, fmaxf(-limx, txtz)) * tz;
    const float ty = fminf(limy, fmaxf(-limy, tytz)) * tz;
    e.t[0] = tx;
    e.t[1] = ty;
    e.t[2] = tz;
    const float fx = params[P_FOCAL], fy = params[P_FOCAL + 1];
    const float j00 = fx / tz, j02 = -(fx * tx) / (tz * tz);
    const float j11 = fy / tz, j12 = -(fy * ty) / (tz * tz);
    const float* v = params + P_VIEW;
    for (int k = 0; k < 3; k++) {
        e.m[0][k] = j00 * v[k] + j02 * v[8 + k];
        e.m[1][k] = j11 * v[4 + k] + j12 * v[8 + k];
    }
    const float S[3][3] = {{cov[0], cov[1], cov[2]}, {cov[1], cov[3], cov[4]}, {cov[2], cov[4], cov[5]}};
    float ms[2][3];  // M Sigma
    for (int r = 0; r < 2; r++)
        for (int k = 0; k < 3; k++) ms[r][k] = e.m[r][0] * S[0][k] + e.m[r][1] * S[1][k] + e.m[r][2] * S[2][k];
    e.cov2d[0] = ms[0][0] * e.m[0][0] + ms[0][1] * e.m[0][1] + ms[0][2] * e.m[0][2] + 0.3f;
    e.cov2d[1] = ms[0][0] * e.m[1][0] + ms[0][1] * e.m[1][1] + ms[0][2] * e.m[1][2];
    e.cov2d[2] = ms[1][0] * e.m[1][0] + ms[1][1] * e.m[1][1] + ms[1][2] * e.m[1][2] + 0.3f;
}

// Real SH basis (graphdeco constants, e3nn axis order) of degrees 0..deg (deg <= 3) at the unit direction d.
// With `g`, also its derivative w.r.t. d; with `official` as well, coefficient 14 follows the official
// backward: y(zz - xx) for both its value and its derivative (the forward uses z(zz - xx)).
static __device__ void sh_basis(const float* d, int deg, float* b, float (*g)[3], bool official) {
    const float x = d[0], y = d[1], z = d[2];
    const float C0 = 0.28209479177387814f, C1 = 0.4886025119029199f;
    const float C20 = 1.0925484305920792f, C21 = -1.0925484305920792f, C22 = 0.31539156525252005f,
                C23 = -1.0925484305920792f, C24 = 0.5462742152960396f;
    const float C30 = -0.5900435899266435f, C31 = 2.890611442640554f, C32 = -0.4570457994644658f,
                C33 = 0.3731763325901154f, C34 = -0.4570457994644658f, C35 = 1.445305721320277f,
                C36 = -0.5900435899266435f;
    b[0] = C0;
    if (g) g[0][0] = g[0][1] = g[0][2] = 0.f;
    if (deg < 1) return;
    b[1] = -C1 * x;
    b[2] = C1 * y;
    b[3] = -C1 * z;
    if (g) {
        g[1][0] = -C1, g[1][1] = 0.f, g[1][2] = 0.f;
        g[2][0] = 0.f, g[2][1] = C1, g[2][2] = 0.f;
        g[3][0] = 0.f, g[3][1] = 0.f, g[3][2] = -C1;
    }
    if (deg < 2) return;
    const float xx = x * x, yy = y * y, zz = z * z;
    b[4] = C20 * z * x;
    b[5] = C21 * x * y;
    b[6] = C22 * (2.f * yy - zz - xx);
    b[7] = C23 * z * y;
    b[8] = C24 * (zz - xx);
    if (g) {
        g[4][0] = C20 * z, g[4][1] = 0.f, g[4][2] = C20 * x;
        g[5][0] = C21 * y, g[5][1] = C21 * x, g[5][2] = 0.f;
        g[6][0] = -2.f * C22 * x, g[6][1] = 4.f * C22 * y, g[6][2] = -2.f * C22 * z;
        g[7][0] = 0.f, g[7][1] = C23 * z, g[7][2] = C23 * y;
        g[8][0] = -2.f * C24 * x, g[8][1] = 0.f, g[8][2] = 2.f * C24 * z;
    }
    if (deg < 3) return;
    b[9] = C30 * x * (3.f * zz - xx);
    b[10] = C31 * z * x * y;
    b[11] = C32 * x * (4.f * yy - zz - xx);
    b[12] = C33 * y * (2.f * yy - 3.f * zz - 3.f * xx);
    b[13] = C34 * z * (4.f * yy - zz - xx);
    b[14] = C35 * z * (zz - xx);
    b[15] = C36 * z * (zz - 3.f * xx);
    if (g) {
        g[9][0] = C30 * (3.f * zz - 3.f * xx), g[9][1] = 0.f, g[9][2] = 6.f * C30 * x * z;
        g[10][0] = C31 * z * y, g[10][1] = C31 * z * x, g[10][2] = C31 * x * y;
        g[11][0] = C32 * (4.f * yy - zz - 3.f * xx), g[11][1] = 8.f * C32 * x * y, g[11][2] = -2.f * C32 * x * z;
        g[12][0] = -6.f * C33 * x * y, g[12][1] = C33 * (6.f * yy - 3.f * zz - 3.f * xx),
        g[12][2] = -6.f * C33 * y * z;
        g[13][0] = -2.f * C34 * x * z, g[13][1] = 8.f * C34 * y * z, g[13][2] = C34 * (4.f * yy - 3.f * zz - xx);
        if (official) {  // README item 5
            b[14] = C35 * y * (zz - xx);
            g[14][0] = -2.f * C35 * x * y, g[14][1] = C35 * (zz - xx), g[14][2] = 2.f * C35 * y * z;
        } else {
            g[14][0] = -2.f * C35 * x * z, g[14][1] = 0.f, g[14][2] = C35 * (3.f * zz - xx);
        }
        g[15][0] = -6.f * C36 * x * z, g[15][1] = 0.f, g[15][2] = C36 * (3.f * zz - 3.f * xx);
    }
}

// ---------------------------------------------------------------------------------------------------------
// Forward

// Per Gaussian i < n. Culled Gaussians get radius 0 and zeros everywhere. `cov3d_in` may be null, then
// `scales`/`quats` are used. sh is (n, sh_coeffs, 3); only degrees 0..deg are evaluated. `clamped` holds a
// bit per colour channel whose value was clamped at 0 (no gradient there).
extern "C" __global__ void rast_preprocess(int n, const float* __restrict__ means, const float* __restrict__ cov3d_in,
                                           const float* __restrict__ scales, const float* __restrict__ quats,
                                           const float* __restrict__ opacities, const float* __restrict__ sh,
                                           int sh_coeffs, int deg, const float* __restrict__ params, int W, int H,
                                           int* __restrict__ radii, float* __restrict__ means2d,
                                           float* __restrict__ depths, float* __restrict__ cov2d,
                                           float* __restrict__ conic_opacity, float* __restrict__ colors,
                                           int* __restrict__ clamped, unsigned* __restrict__ tiles_touched) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    radii[i] = 0;
    tiles_touched[i] = 0;
    clamped[i] = 0;
    depths[i] = 0.f;
    means2d[2 * i] = means2d[2 * i + 1] = 0.f;
    for (int k = 0; k < 3; k++) cov2d[3 * i + k] = colors[3 * i + k] = 0.f;
    for (int k = 0; k < 4; k++) conic_opacity[4 * i + k] = 0.f;

    const float p[3] = {means[3 * i], means[3 * i + 1], means[3 * i + 2]};
    float tv[3];
    view_point(params, p, tv);
    if (!(tv[2] > 0.2f)) return;  // near cull (NaN-safe)

    const float pw = 1.0f / (proj_row(params, 3, p) + 0.0000001f);
    const float ndc_x = proj_row(params, 0, p) * pw, ndc_y = proj_row(params, 1, p) * pw;

    float cov[6];
    cov3d_of(i, cov3d_in, scales, quats, cov);
    Ewa e;
    ewa(params, tv, cov, e);
    const float a = e.cov2d[0], b = e.cov2d[1], c = e.cov2d[2];
    const float det = a * c - b * b;
    if (det == 0.0f || !isfinite(det)) return;
    const float det_inv = 1.f / det;
    const float mid = 0.5f * (a + c);
    const float disc = sqrtf(fmaxf(0.1f, mid * mid - det));
    const float rf = ceilf(3.f * sqrtf(fmaxf(mid + disc, mid - disc)));
    if (!isfinite(rf) || !isfinite(ndc_x) || !isfinite(ndc_y)) return;
    const int radius = (int)rf;
    // Pixel centre in double precision, as the official ndc2Pix.
    const float mx = (float)((((double)ndc_x + 1.0) * (double)W - 1.0) * 0.5);
    const float my = (float)((((double)ndc_y + 1.0) * (double)H - 1.0) * 0.5);
    int r[4];
    tile_rect(mx, my, radius, (W + TILE - 1) / TILE, (H + TILE - 1) / TILE, r);
    const int area = (r[2] - r[0]) * (r[3] - r[1]);
    if (area == 0) return;

    // SH colour at the unit direction camera -> Gaussian.
    float dv[3] = {p[0] - params[P_CAMPOS], p[1] - params[P_CAMPOS + 1], p[2] - params[P_CAMPOS + 2]};
    const float nrm = sqrtf(dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]);
    const float inv = nrm > 0.f ? 1.f / nrm : 0.f;
    const float dir[3] = {dv[0] * inv, dv[1] * inv, dv[2] * inv};
    float basis[16];
    sh_basis(dir, deg, basis, nullptr, false);
    const int ncoef = (deg + 1) * (deg + 1);
    const float* shi = sh + (size_t)i * sh_coeffs * 3;
    int mask = 0;
    for (int ch = 0; ch < 3; ch++) {
        float acc = 0.f;
        for (int k = 0; k < ncoef; k++) acc += basis[k] * shi[3 * k + ch];
        acc += 0.5f;
        if (acc < 0.f) mask |= 1 << ch;
        colors[3 * i + ch] = fmaxf(acc, 0.f);
    }
    clamped[i] = mask;
    depths[i] = tv[2];
    means2d[2 * i] = mx;
    means2d[2 * i + 1] = my;
    for (int k = 0; k < 3; k++) cov2d[3 * i + k] = e.cov2d[k];
    conic_opacity[4 * i] = c * det_inv;
    conic_opacity[4 * i + 1] = -b * det_inv;
    conic_opacity[4 * i + 2] = a * det_inv;
    conic_opacity[4 * i + 3] = opacities[i];
    radii[i] = radius;
    tiles_touched[i] = (unsigned)area;
}

// Exclusive scan inside each block of BLOCK_SIZE (= blockDim.x) values; block totals go to block_sums
// (to be scanned themselves, then added back by rast_scan_add).
// The candle op's packed per-Gaussian matrix (row-major n x d): columns [c0, c0 + cw) to a contiguous n x cw
// buffer and back (1-D over n * cw threads).
extern "C" __global__ void rast_unpack_cols(int n, int d, int c0, int cw, const float* __restrict__ packed,
                                            float* __restrict__ out) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * cw) return;
    const int r = i / cw;
    out[i] = packed[r * d + c0 + (i - r * cw)];
}

extern "C" __global__ void rast_pack_cols(int n, int d, int c0, int cw, const float* __restrict__ in,
                                          float* __restrict__ packed) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * cw) return;
    const int r = i / cw;
    packed[r * d + c0 + (i - r * cw)] = in[i];
}

extern "C" __global__ void rast_scan_block(const unsigned* __restrict__ in, unsigned* __restrict__ out,
                                           unsigned* __restrict__ block_sums, int n) {
    __shared__ unsigned buf[2 * BLOCK_SIZE];
    const int t = threadIdx.x;
    const int i = blockIdx.x * BLOCK_SIZE + t;
    const unsigned v = i < n ? in[i] : 0u;
    int cur = 0;
    buf[t] = v;
    __syncthreads();
    // Hillis-Steele, double-buffered so reads and writes of one step never overlap.
    for (int off = 1; off < BLOCK_SIZE; off <<= 1) {
        unsigned x = buf[cur * BLOCK_SIZE + t];
        if (t >= off) x += buf[cur * BLOCK_SIZE + t - off];
        buf[(1 - cur) * BLOCK_SIZE + t] = x;
        cur = 1 - cur;
        __syncthreads();
    }
    const unsigned incl = buf[cur * BLOCK_SIZE + t];
    if (i < n) out[i] = incl - v;
    if (t == BLOCK_SIZE - 1) block_sums[blockIdx.x] = incl;
}

extern "C" __global__ void rast_scan_add(unsigned* __restrict__ data, const unsigned* __restrict__ block_offsets,
                                         int n) {
    const int i = blockIdx.x * BLOCK_SIZE + threadIdx.x;
    if (i < n) data[i] += block_offsets[blockIdx.x];
}

// One pair per tile touched by a visible Gaussian, written at its exclusive-scan offset.
extern "C" __global__ void rast_duplicate(int n, const int* __restrict__ radii, const float* __restrict__ means2d,
                                          const float* __restrict__ depths, const unsigned* __restrict__ offsets,
                                          int W, int H, u64* __restrict__ keys, unsigned* __restrict__ vals) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n || radii[i] <= 0) return;
    const int gx = (W + TILE - 1) / TILE, gy = (H + TILE - 1) / TILE;
    int r[4];
    tile_rect(means2d[2 * i], means2d[2 * i + 1], radii[i], gx, gy, r);
    // Depth > 0.2, so its IEEE bits sort like the value.
    const u64 dbits = (u64)__float_as_uint(depths[i]);
    unsigned off = offsets[i];
    for (int y = r[1]; y < r[3]; y++)
        for (int x = r[0]; x < r[2]; x++) {
            keys[off] = ((u64)(unsigned)(y * gx + x) << 32) | dbits;
            vals[off] = (unsigned)i;
            off++;
        }
}

// Pairs [from, to) become padding that sorts last.
extern "C" __global__ void rast_fill_pad(u64* __restrict__ keys, unsigned* __restrict__ vals, unsigned from,
                                         unsigned to) {
    const unsigned i = from + blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= to) return;
    keys[i] = ~0ull;
    vals[i] = ~0u;
}

// One compare-exchange pass (stage k, distance j) of a bitonic sort over npow2 pairs, ascending by
// (key, value): (tile, depth, Gaussian id), a total order, so the result does not depend on scheduling.
extern "C" __global__ void rast_bitonic_step(u64* __restrict__ keys, unsigned* __restrict__ vals, unsigned npow2,
                                             unsigned j, unsigned k) {
    const unsigned i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= npow2) return;
    const unsigned l = i ^ j;
    if (l <= i) return;
    const u64 ki = keys[i], kl = keys[l];
    const unsigned vi = vals[i], vl = vals[l];
    const bool greater = ki > kl || (ki == kl && vi > vl);
    const bool ascending = (i & k) == 0;
    if (greater == ascending) {
        keys[i] = kl;
        keys[l] = ki;
        vals[i] = vl;
        vals[l] = vi;
    }
}

// ranges[2t], ranges[2t+1] = [start, end) of tile t among the `count` sorted pairs; tiles without pairs keep
// the zeros they were initialised with.
extern "C" __global__ void rast_tile_ranges(unsigned count, const u64* __restrict__ keys,
                                            unsigned* __restrict__ ranges) {
    const unsigned i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= count) return;
    const unsigned tile = (unsigned)(keys[i] >> 32);
    if (i == 0) {
        ranges[2 * tile] = 0;
    } else {
        const unsigned prev = (unsigned)(keys[i - 1] >> 32);
        if (tile != prev) {
            ranges[2 * prev + 1] = i;
            ranges[2 * tile] = i;
        }
    }
    if (i == count - 1) ranges[2 * tile + 1] = count;
}

// Front-to-back compositing, one 16x16 block per tile, one thread per pixel. Outputs: rgb (+ background),
// features (no background), alpha = 1 - T, expected depth, final T, n_contrib = 1-based list position of the
// last blended Gaussian.
extern "C" __global__ void rast_render_fwd(const unsigned* __restrict__ ranges, const unsigned* __restrict__ point_list,
                                           int W, int H, const float* __restrict__ means2d,
                                           const float* __restrict__ conic_opacity, const float* __restrict__ colors,
                                           const float* __restrict__ depths, const float* __restrict__ features,
                                           int nf, const float* __restrict__ params, float* __restrict__ out_rgb,
                                           float* __restrict__ out_feat, float* __restrict__ out_alpha,
                                           float* __restrict__ out_depth, float* __restrict__ out_final_t,
                                           unsigned* __restrict__ out_n_contrib) {
    __shared__ int s_id[BLOCK_SIZE];
    __shared__ float s_xy[2 * BLOCK_SIZE];
    __shared__ float s_co[4 * BLOCK_SIZE];
    __shared__ int s_done;
    const int gx = (W + TILE - 1) / TILE;
    const unsigned tile = blockIdx.y * gx + blockIdx.x;
    const int px = blockIdx.x * TILE + threadIdx.x, py = blockIdx.y * TILE + threadIdx.y;
    const int rank = threadIdx.y * TILE + threadIdx.x;
    const bool inside = px < W && py < H;
    const float pxf = (float)px, pyf = (float)py;
    const unsigned start = ranges[2 * tile], end = ranges[2 * tile + 1];

    bool done = !inside;
    float T = 1.f;
    unsigned contributor = 0, last = 0;
    float acc[4] = {0.f, 0.f, 0.f, 0.f};  // r, g, b, depth
    float facc[MAX_FEAT];
    for (int c = 0; c < nf; c++) facc[c] = 0.f;

    for (unsigned base = start; base < end; base += BLOCK_SIZE) {
        // Stop the whole block once every pixel is done (a block-wide count: no warp votes needed).
        if (rank == 0) s_done = 0;
        __syncthreads();
        if (done) atomicAdd(&s_done, 1);
        __syncthreads();
        if (s_done == BLOCK_SIZE) break;
        const unsigned k = base + rank;
        if (k < end) {
            const int id = (int)point_list[k];
            s_id[rank] = id;
            s_xy[2 * rank] = means2d[2 * id];
            s_xy[2 * rank + 1] = means2d[2 * id + 1];
            for (int q = 0; q < 4; q++) s_co[4 * rank + q] = conic_opacity[4 * id + q];
        }
        __syncthreads();
        const int cnt = imin(BLOCK_SIZE, (int)(end - base));
        for (int j = 0; !done && j < cnt; j++) {
            contributor++;
            const float dx = s_xy[2 * j] - pxf, dy = s_xy[2 * j + 1] - pyf;
            const float A = s_co[4 * j], B = s_co[4 * j + 1], C = s_co[4 * j + 2], o = s_co[4 * j + 3];
            const float power = -0.5f * (A * dx * dx + C * dy * dy) - B * dx * dy;
            if (power > 0.f) continue;
            const float alpha = fminf(0.99f, o * expf(power));
            if (alpha < 1.f / 255.f) continue;
            const float test_T = T * (1.f - alpha);
            if (test_T < 0.0001f) {
                done = true;
                continue;
            }
            const float w = alpha * T;
            const int id = s_id[j];
            for (int ch = 0; ch < 3; ch++) acc[ch] += w * colors[3 * id + ch];
            acc[3] += w * depths[id];
            for (int c = 0; c < nf; c++) facc[c] += w * features[(size_t)nf * id + c];
            T = test_T;
            last = contributor;
        }
        __syncthreads();
    }
    if (!inside) return;
    const int hw = W * H, pix = py * W + px;
    for (int ch = 0; ch < 3; ch++) out_rgb[ch * hw + pix] = acc[ch] + T * params[P_BG + ch];
    for (int c = 0; c < nf; c++) out_feat[(size_t)c * hw + pix] = facc[c];
    out_alpha[pix] = 1.f - T;
    out_depth[pix] = acc[3];
    out_final_t[pix] = T;
    out_n_contrib[pix] = last;
}

// ---------------------------------------------------------------------------------------------------------
// Backward. `exact` = 0: the official gradients (GradMode::Official); 1: the true derivative of the forward
// (GradMode::Exact), including the feature, alpha and depth images.

// Reverse traversal per pixel. Accumulates (atomically) per Gaussian: dL/d ndc of the centre (pixel gradient
// times W/2, H/2), dL/d conic (A, B, C), dL/d opacity, dL/d colour, dL/d feature and (exact only) dL/d view
// depth. Official: only the rgb image sends gradient to alpha (features are stop-grad for geometry and
// opacity), the 0.99 clamp is ignored, and the alpha/depth images send none. Exact: every image sends
// gradient to alpha, and a clamped alpha is a constant. dl_alpha, dl_depth may be null (zero).
extern "C" __global__ void rast_render_bwd(const unsigned* __restrict__ ranges, const unsigned* __restrict__ point_list,
                                           int W, int H, const float* __restrict__ means2d,
                                           const float* __restrict__ conic_opacity, const float* __restrict__ colors,
                                           const float* __restrict__ depths, const float* __restrict__ features,
                                           int nf, const float* __restrict__ params, const float* __restrict__ final_t,
                                           const unsigned* __restrict__ n_contrib, const float* __restrict__ dl_rgb,
                                           const float* __restrict__ dl_feat, const float* __restrict__ dl_alpha,
                                           const float* __restrict__ dl_depth, int exact,
                                           float* __restrict__ g_mean2d, float* __restrict__ g_conic,
                                           float* __restrict__ g_opacity, float* __restrict__ g_color,
                                           float* __restrict__ g_feat, float* __restrict__ g_depth) {
    __shared__ int s_id[BLOCK_SIZE];
    __shared__ float s_xy[2 * BLOCK_SIZE];
    __shared__ float s_co[4 * BLOCK_SIZE];
    __shared__ float s_col[4 * BLOCK_SIZE];  // r, g, b, view depth
    const int gx = (W + TILE - 1) / TILE;
    const unsigned tile = blockIdx.y * gx + blockIdx.x;
    const int px = blockIdx.x * TILE + threadIdx.x, py = blockIdx.y * TILE + threadIdx.y;
    const int rank = threadIdx.y * TILE + threadIdx.x;
    const bool inside = px < W && py < H;
    const float pxf = (float)px, pyf = (float)py;
    const unsigned start = ranges[2 * tile], end = ranges[2 * tile + 1];
    const int hw = W * H, pix = py * W + px;

    const float T_final = inside ? final_t[pix] : 0.f;
    float T = T_final;
    const unsigned last = inside ? n_contrib[pix] : 0u;
    // Pixel gradients of r, g, b, depth, then alpha; features apart.
    float dpix[5] = {0.f, 0.f, 0.f, 0.f, 0.f}, dfeat[MAX_FEAT];
    float bg_dot = 0.f;
    for (int ch = 0; ch < 3; ch++) {
        dpix[ch] = inside ? dl_rgb[ch * hw + pix] : 0.f;
        bg_dot += params[P_BG + ch] * dpix[ch];
    }
    if (exact && inside) {
        dpix[3] = dl_depth ? dl_depth[pix] : 0.f;
        dpix[4] = dl_alpha ? dl_alpha[pix] : 0.f;
    }
    for (int c = 0; c < nf; c++) dfeat[c] = inside ? dl_feat[(size_t)c * hw + pix] : 0.f;
    // Sums over the Gaussians behind the current one of w * value (r, g, b, depth, alpha; features).
    float behind[5] = {0.f, 0.f, 0.f, 0.f, 0.f}, fbehind[MAX_FEAT];
    for (int c = 0; c < nf; c++) fbehind[c] = 0.f;
    const int nch = exact ? 5 : 3;
    const float hx = 0.5f * W, hy = 0.5f * H;

    unsigned contributor = end - start;
    for (unsigned base = 0; base < end - start; base += BLOCK_SIZE) {
        __syncthreads();
        // Batches are loaded from the back of the tile list.
        if (base + rank < end - start) {
            const int id = (int)point_list[end - 1 - base - rank];
            s_id[rank] = id;
            s_xy[2 * rank] = means2d[2 * id];
            s_xy[2 * rank + 1] = means2d[2 * id + 1];
            for (int q = 0; q < 4; q++) s_co[4 * rank + q] = conic_opacity[4 * id + q];
            for (int ch = 0; ch < 3; ch++) s_col[4 * rank + ch] = colors[3 * id + ch];
            s_col[4 * rank + 3] = depths[id];
        }
        __syncthreads();
        const int cnt = imin(BLOCK_SIZE, (int)(end - start - base));
        for (int j = 0; inside && j < cnt; j++) {
            contributor--;
            if (contributor >= last) continue;
            const float dx = s_xy[2 * j] - pxf, dy = s_xy[2 * j + 1] - pyf;
            const float A = s_co[4 * j], B = s_co[4 * j + 1], C = s_co[4 * j + 2], o = s_co[4 * j + 3];
            const float power = -0.5f * (A * dx * dx + C * dy * dy) - B * dx * dy;
            if (power > 0.f) continue;
            const float G = expf(power);
            const float alpha = fminf(0.99f, o * G);
            if (alpha < 1.f / 255.f) continue;
            const float inv = 1.f / (1.f - alpha);
            T *= inv;  // transmittance in front of this Gaussian
            const float w = alpha * T;
            const int id = s_id[j];
            // d image / d alpha = v T - (sum behind of w v) / (1 - alpha); rgb also - T_final / (1 - alpha) bg.
            float dl_dalpha = -T_final * inv * bg_dot;
            for (int ch = 0; ch < nch; ch++) {
                const float v = ch < 4 ? s_col[4 * j + ch] : 1.f;  // the alpha image's value is 1
                dl_dalpha += (v * T - behind[ch] * inv) * dpix[ch];
                behind[ch] += w * v;
            }
            for (int ch = 0; ch < 3; ch++) atomicAdd(&g_color[3 * id + ch], w * dpix[ch]);
            if (exact) atomicAdd(&g_depth[id], w * dpix[3]);
            for (int c = 0; c < nf; c++) {
                atomicAdd(&g_feat[(size_t)nf * id + c], w * dfeat[c]);
                if (exact) {
                    const float f = features[(size_t)nf * id + c];
                    dl_dalpha += (f * T - fbehind[c] * inv) * dfeat[c];
                    fbehind[c] += w * f;
                }
            }
            if (exact && o * G > 0.99f) continue;  // clamped alpha: no gradient to G or opacity
            const float dl_dG = o * dl_dalpha;
            const float gdx = G * dx, gdy = G * dy;
            const float dG_ddx = -gdx * A - gdy * B;
            const float dG_ddy = -gdy * C - gdx * B;
            atomicAdd(&g_mean2d[2 * id], dl_dG * dG_ddx * hx);
            atomicAdd(&g_mean2d[2 * id + 1], dl_dG * dG_ddy * hy);
            atomicAdd(&g_conic[3 * id], -0.5f * gdx * dx * dl_dG);
            atomicAdd(&g_conic[3 * id + 1], -0.5f * gdx * dy * dl_dG);
            atomicAdd(&g_conic[3 * id + 2], -0.5f * gdy * dy * dl_dG);
            atomicAdd(&g_opacity[id], G * dl_dalpha);
        }
    }
}

// d Sigma (upper triangle, off-diagonals counting both positions) -> d scales, d quaternion (raw w, x, y, z).
static __device__ void scale_rot_bwd(const float* s, const float* q, const float* dcov, float* ds, float* dq) {
    float R[3][3];
    quat_rot(q, R);
    const float G[3][3] = {{dcov[0], 0.5f * dcov[1], 0.5f * dcov[2]},
                           {0.5f * dcov[1], dcov[3], 0.5f * dcov[4]},
                           {0.5f * dcov[2], 0.5f * dcov[4], dcov[5]}};
    float GR[3][3];
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) GR[a][b] = G[a][0] * R[0][b] + G[a][1] * R[1][b] + G[a][2] * R[2][b];
    // Sigma = R D R^T, D = diag(s^2): dL/ds_k = 2 s_k (R^T G R)_kk, dL/dR = 2 G R D.
    float dR[3][3];
    for (int k = 0; k < 3; k++) {
        ds[k] = 2.f * s[k] * (R[0][k] * GR[0][k] + R[1][k] * GR[1][k] + R[2][k] * GR[2][k]);
        for (int a = 0; a < 3; a++) dR[a][k] = 2.f * GR[a][k] * s[k] * s[k];
    }
    const float w = q[0], x = q[1], y = q[2], z = q[3];
    // Chain through quat_rot's entries.
    dq[0] = 2.f * (-z * dR[0][1] + y * dR[0][2] + z * dR[1][0] - x * dR[1][2] - y * dR[2][0] + x * dR[2][1]);
    dq[1] = 2.f * (y * dR[0][1] + z * dR[0][2] + y * dR[1][0] - 2.f * x * dR[1][1] - w * dR[1][2] + z * dR[2][0] +
                   w * dR[2][1] - 2.f * x * dR[2][2]);
    dq[2] = 2.f * (-2.f * y * dR[0][0] + x * dR[0][1] + w * dR[0][2] + x * dR[1][0] + z * dR[1][2] - w * dR[2][0] +
                   z * dR[2][1] - 2.f * y * dR[2][2]);
    dq[3] = 2.f * (-2.f * z * dR[0][0] - w * dR[0][1] + x * dR[0][2] + w * dR[1][0] - 2.f * z * dR[1][1] +
                   y * dR[1][2] + x * dR[2][0] + y * dR[2][1]);
}

// Per Gaussian chain rule from the render gradients (g_mean2d in ndc units, g_conic, g_color, g_depth) to
// d means, d cov3d (always), d scales/quats (when cov3d_in is null), d sh. Culled Gaussians get zeros.
// Official quirks (exact = 0): 1/(det^2 + 1e-7) in the conic backward, a clamped Jacobian coordinate is a
// constant, coefficient 14 of the SH backward (see sh_basis), and no depth gradient (g_depth may be null).
extern "C" __global__ void rast_preprocess_bwd(int n, const float* __restrict__ means,
                                               const float* __restrict__ cov3d_in, const float* __restrict__ scales,
                                               const float* __restrict__ quats, const float* __restrict__ sh,
                                               int sh_coeffs, int deg, const float* __restrict__ params,
                                               const int* __restrict__ radii, const int* __restrict__ clamped,
                                               const float* __restrict__ g_mean2d, const float* __restrict__ g_conic,
                                               const float* __restrict__ g_color, const float* __restrict__ g_depth,
                                               int exact, float* __restrict__ d_means,
                                               float* __restrict__ d_cov3d, float* __restrict__ d_scales,
                                               float* __restrict__ d_quats, float* __restrict__ d_sh) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    float* dsh = d_sh + (size_t)i * sh_coeffs * 3;
    for (int k = 0; k < sh_coeffs * 3; k++) dsh[k] = 0.f;
    for (int k = 0; k < 3; k++) d_means[3 * i + k] = 0.f;
    for (int k = 0; k < 6; k++) d_cov3d[6 * i + k] = 0.f;
    if (!cov3d_in) {
        for (int k = 0; k < 3; k++) d_scales[3 * i + k] = 0.f;
        for (int k = 0; k < 4; k++) d_quats[4 * i + k] = 0.f;
    }
    if (radii[i] <= 0) return;

    const float p[3] = {means[3 * i], means[3 * i + 1], means[3 * i + 2]};
    float dmean[3] = {0.f, 0.f, 0.f};

    // Projected centre: ndc = hom.xy / (hom.w + 1e-7).
    const float gnx = g_mean2d[2 * i], gny = g_mean2d[2 * i + 1];
    const float mw = 1.0f / (proj_row(params, 3, p) + 0.0000001f);
    const float hxw = proj_row(params, 0, p) * mw * mw, hyw = proj_row(params, 1, p) * mw * mw;
    const float* fp = params + P_PROJ;
    for (int j = 0; j < 3; j++)
        dmean[j] += (fp[j] * mw - fp[12 + j] * hxw) * gnx + (fp[4 + j] * mw - fp[12 + j] * hyw) * gny;

    // Conic -> 2D covariance.
    float tv[3];
    view_point(params, p, tv);
    float cov[6];
    cov3d_of(i, cov3d_in, scales, quats, cov);
    Ewa e;
    ewa(params, tv, cov, e);
    const float a = e.cov2d[0], b = e.cov2d[1], c = e.cov2d[2];
    const float det = a * c - b * b;
    const float ga = g_conic[3 * i], gb = g_conic[3 * i + 1], gc = g_conic[3 * i + 2];
    const float d2inv = exact ? 1.f / (det * det) : 1.f / (det * det + 0.0000001f);
    float da = 0.f, db = 0.f, dc = 0.f;
    if (d2inv != 0.f && isfinite(d2inv)) {
        da = d2inv * (-c * c * ga + 2.f * b * c * gb + (det - a * c) * gc);
        db = d2inv * 2.f * (b * c * ga - (det + 2.f * b * b) * gb + a * b * gc);
        dc = d2inv * (-a * a * gc + 2.f * a * b * gb + (det - a * c) * ga);
    }

    // cov2D = M Sigma M^T: dL/dSigma = M^T Gc M, dL/dM = 2 Gc M Sigma, Gc = [[da, db/2], [db/2, dc]].
    float gm[2][3];
    for (int k = 0; k < 3; k++) {
        gm[0][k] = da * e.m[0][k] + 0.5f * db * e.m[1][k];
        gm[1][k] = 0.5f * db * e.m[0][k] + dc * e.m[1][k];
    }
    float dcov[6];
    const int ia[6] = {0, 0, 0, 1, 1, 2}, ib[6] = {0, 1, 2, 1, 2, 2};
    for (int k = 0; k < 6; k++) {
        const float v = e.m[0][ia[k]] * gm[0][ib[k]] + e.m[1][ia[k]] * gm[1][ib[k]];
        dcov[k] = ia[k] == ib[k] ? v : 2.f * v;
    }
    const float S[3][3] = {{cov[0], cov[1], cov[2]}, {cov[1], cov[3], cov[4]}, {cov[2], cov[4], cov[5]}};
    float dM[2][3];
    for (int r = 0; r < 2; r++)
        for (int k = 0; k < 3; k++) dM[r][k] = 2.f * (gm[r][0] * S[0][k] + gm[r][1] * S[1][k] + gm[r][2] * S[2][k]);
    const float* v = params + P_VIEW;
    const float dj00 = dM[0][0] * v[0] + dM[0][1] * v[1] + dM[0][2] * v[2];
    const float dj02 = dM[0][0] * v[8] + dM[0][1] * v[9] + dM[0][2] * v[10];
    const float dj11 = dM[1][0] * v[4] + dM[1][1] * v[5] + dM[1][2] * v[6];
    const float dj12 = dM[1][0] * v[8] + dM[1][1] * v[9] + dM[1][2] * v[10];
    const float fx = params[P_FOCAL], fy = params[P_FOCAL + 1];
    const float tx = e.t[0], ty = e.t[1], tz = e.t[2];
    const float tz2 = 1.f / (tz * tz), tz3 = tz2 / tz;
    float dt[3];
    const float dtxc = -fx * tz2 * dj02, dtyc = -fy * tz2 * dj12;
    dt[2] = -fx * tz2 * dj00 - fy * tz2 * dj11 + 2.f * fx * tx * tz3 * dj02 + 2.f * fy * ty * tz3 * dj12;
    // A clamped coordinate: official, a constant (no gradient to it nor through it to t.z); exact,
    // t.x = +-lim t.z.
    dt[0] = e.clamp_x ? 0.f : dtxc;
    dt[1] = e.clamp_y ? 0.f : dtyc;
    if (exact) {
        if (e.clamp_x) dt[2] += dtxc * (tx / tz);
        if (e.clamp_y) dt[2] += dtyc * (ty / tz);
        dt[2] += g_depth[i];
    }
    for (int j = 0; j < 3; j++) dmean[j] += v[j] * dt[0] + v[4 + j] * dt[1] + v[8 + j] * dt[2];

    // SH colour -> coefficients and view direction.
    const float dv[3] = {p[0] - params[P_CAMPOS], p[1] - params[P_CAMPOS + 1], p[2] - params[P_CAMPOS + 2]};
    const float sum2 = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2];
    const float nrm = sqrtf(sum2);
    const float inv = nrm > 0.f ? 1.f / nrm : 0.f;
    const float dir[3] = {dv[0] * inv, dv[1] * inv, dv[2] * inv};
    float basis[16], bgrad[16][3];
    sh_basis(dir, deg, basis, bgrad, !exact);
    const int mask = clamped[i];
    float dcol[3];
    for (int ch = 0; ch < 3; ch++) dcol[ch] = (mask >> ch) & 1 ? 0.f : g_color[3 * i + ch];
    const float* shi = sh + (size_t)i * sh_coeffs * 3;
    const int ncoef = (deg + 1) * (deg + 1);
    float ddir[3] = {0.f, 0.f, 0.f};
    for (int k = 0; k < ncoef; k++) {
        float proj = 0.f;
        for (int ch = 0; ch < 3; ch++) {
            dsh[3 * k + ch] = basis[k] * dcol[ch];
            proj += shi[3 * k + ch] * dcol[ch];
        }
        for (int q = 0; q < 3; q++) ddir[q] += bgrad[k][q] * proj;
    }
    if (sum2 > 0.f) {
        // d normalize(v) / dv = (|v|^2 I - v v^T) / |v|^3
        const float inv32 = 1.f / sqrtf(sum2 * sum2 * sum2);
        const float vd = dv[0] * ddir[0] + dv[1] * ddir[1] + dv[2] * ddir[2];
        for (int q = 0; q < 3; q++) dmean[q] += (sum2 * ddir[q] - dv[q] * vd) * inv32;
    }

    for (int k = 0; k < 3; k++) d_means[3 * i + k] = dmean[k];
    for (int k = 0; k < 6; k++) d_cov3d[6 * i + k] = dcov[k];
    if (!cov3d_in) {
        const float s[3] = {scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]};
        scale_rot_bwd(s, quats + 4 * i, dcov, d_scales + 3 * i, d_quats + 4 * i);
    }
}
