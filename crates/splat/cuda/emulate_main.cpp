// CPU driver for rasterize.cu compiled through emulate.h: runs the launch sequence a GPU host runs
// (forward, then the backward) on inputs read from a file and writes every output to a file.
//
//   g++ -O2 -std=c++20 -pthread -o emulate_main emulate_main.cpp
//   ./emulate_main inputs.bin outputs.bin
//
// File format (both files, little-endian): a sequence of records until end of file, each
//   u32 name_len, name bytes (ASCII), u32 dtype (0 = f32, 1 = i32, 2 = u32), u64 count, count * 4 bytes.
// Inputs:  dims (i32: n, W, H, sh_coeffs, sh_degree evaluated (<= 3), num_features), params (f32[42], the
//          P_* layout of rasterize.cu), means (n*3), opacities (n), either cov3d (n*6) or scales (n*3) +
//          quats (n*4), sh (n*sh_coeffs*3), features (n*nf), dl_rgb (3*H*W), dl_feat (nf*H*W), planar;
//          optional: exact (i32[1], 1 = GradMode::Exact, default 0 = official), dl_alpha, dl_depth (H*W).
// Outputs: rgb (3,H,W), feat (nf,H,W), alpha, depth, final_t (H,W), n_contrib (u32, H,W), radii (i32),
//          tiles_touched (u32), means2d, depths, cov2d, conic (A,B,C), colors, num_pairs (u32[1]),
//          point_list (u32, sorted pair Gaussian ids), grad_means, grad_cov3d, grad_scales + grad_quats (scale
//          path only), grad_opacities, grad_sh, grad_features, grad_means2d_ndc.
#include "emulate.h"
#include "rasterize.cu"
#include "records.h"

#include <cstdint>
#include <fstream>
#include <map>
#include <stdexcept>
#include <string>

using namespace records;

namespace {

unsigned blocks_for(size_t n) { return (unsigned)((n + BLOCK_SIZE - 1) / BLOCK_SIZE); }

// Exclusive scan of in[0..n) into out, as a GPU host would: block scans, then the block sums recursively.
void exclusive_scan(const unsigned* in, unsigned* out, int n) {
    if (n == 0) return;
    const unsigned nb = blocks_for(n);
    std::vector<unsigned> sums(nb), sums_scanned(nb);
    launch(rast_scan_block, dim3(nb), dim3(BLOCK_SIZE), in, out, sums.data(), n);
    if (nb > 1) {
        exclusive_scan(sums.data(), sums_scanned.data(), (int)nb);
        launch_serial(rast_scan_add, dim3(nb), dim3(BLOCK_SIZE), out, sums_scanned.data(), n);
    }
}

int run(const char* in_path, const char* out_path) {
    const auto m = read_records(in_path);
    const auto dims = take<int>(m, "dims", 6);
    const int n = dims[0], W = dims[1], H = dims[2], K = dims[3], deg = dims[4], nf = dims[5];
    if (nf > MAX_FEAT) throw std::runtime_error("too many feature channels");
    if (deg > 3 || (deg + 1) * (deg + 1) > K) throw std::runtime_error("bad sh degree");
    const size_t hw = (size_t)W * H;
    const auto params = take<float>(m, "params", P_LEN);
    const auto means = take<float>(m, "means", 3 * n);
    const auto opac = take<float>(m, "opacities", n);
    const bool scale_path = !m.count("cov3d");
    std::vector<float> cov3d, scales, quats;
    if (scale_path) {
        scales = take<float>(m, "scales", 3 * n);
        quats = take<float>(m, "quats", 4 * n);
    } else {
        cov3d = take<float>(m, "cov3d", 6 * n);
    }
    const auto sh = take<float>(m, "sh", (size_t)n * K * 3);
    const auto feats = take<float>(m, "features", (size_t)n * nf);
    const auto dl_rgb = take<float>(m, "dl_rgb", 3 * hw);
    const auto dl_feat = take<float>(m, "dl_feat", nf * hw);
    const float* cov_in = scale_path ? nullptr : cov3d.data();
    const int exact = m.count("exact") ? take<int>(m, "exact", 1)[0] : 0;
    std::vector<float> dl_alpha, dl_depth;
    if (m.count("dl_alpha")) dl_alpha = take<float>(m, "dl_alpha", hw);
    if (m.count("dl_depth")) dl_depth = take<float>(m, "dl_depth", hw);
    const float* dl_alpha_p = dl_alpha.empty() ? nullptr : dl_alpha.data();
    const float* dl_depth_p = dl_depth.empty() ? nullptr : dl_depth.data();

    // Forward: preprocess.
    std::vector<int> radii(n), clamped(n);
    std::vector<float> means2d(2 * n), depths(n), cov2d(3 * n), conic_op(4 * n), colors(3 * n);
    std::vector<unsigned> tiles(n), offsets(n);
    const dim3 lin(BLOCK_SIZE);
    launch_serial(rast_preprocess, dim3(blocks_for(n)), lin, n, means.data(), cov_in, scales.data(), quats.data(),
                  opac.data(), sh.data(), K, deg, params.data(), W, H, radii.data(), means2d.data(), depths.data(),
                  cov2d.data(), conic_op.data(), colors.data(), clamped.data(), tiles.data());

    // Binning: scan, duplicate, sort, ranges.
    exclusive_scan(tiles.data(), offsets.data(), n);
    const unsigned pairs = n ? offsets[n - 1] + tiles[n - 1] : 0;
    unsigned npow2 = 1;
    while (npow2 < pairs) npow2 <<= 1;
    std::vector<u64> keys(npow2);
    std::vector<unsigned> vals(npow2);
    launch_serial(rast_duplicate, dim3(blocks_for(n)), lin, n, radii.data(), means2d.data(), depths.data(),
                  offsets.data(), W, H, keys.data(), vals.data());
    if (npow2 > pairs)
        launch_serial(rast_fill_pad, dim3(blocks_for(npow2 - pairs)), lin, keys.data(), vals.data(), pairs, npow2);
    for (unsigned k = 2; k <= npow2; k <<= 1)
        for (unsigned j = k >> 1; j > 0; j >>= 1)
            launch_serial(rast_bitonic_step, dim3(blocks_for(npow2)), lin, keys.data(), vals.data(), npow2, j, k);
    const int gx = (W + TILE - 1) / TILE, gy = (H + TILE - 1) / TILE;
    std::vector<unsigned> ranges(2 * (size_t)gx * gy, 0u);
    if (pairs) launch_serial(rast_tile_ranges, dim3(blocks_for(pairs)), lin, pairs, keys.data(), ranges.data());

    // Forward: render.
    std::vector<float> rgb(3 * hw), feat(nf * hw), alpha(hw), depth(hw), final_t(hw);
    std::vector<unsigned> n_contrib(hw);
    const dim3 tiles_grid(gx, gy), tile_block(TILE, TILE);
    launch(rast_render_fwd, tiles_grid, tile_block, ranges.data(), vals.data(), W, H, means2d.data(), conic_op.data(),
           colors.data(), depths.data(), feats.data(), nf, params.data(), rgb.data(), feat.data(), alpha.data(),
           depth.data(), final_t.data(), n_contrib.data());

    // Backward (gradient buffers start at zero, as cudaMemset would leave them).
    std::vector<float> g_m2(2 * n), g_conic(3 * n), g_op(n), g_col(3 * n), g_feat((size_t)n * nf), g_depth(n);
    launch(rast_render_bwd, tiles_grid, tile_block, ranges.data(), vals.data(), W, H, means2d.data(), conic_op.data(),
           colors.data(), depths.data(), feats.data(), nf, params.data(), final_t.data(), n_contrib.data(),
           dl_rgb.data(), dl_feat.data(), dl_alpha_p, dl_depth_p, exact, g_m2.data(), g_conic.data(), g_op.data(),
           g_col.data(), g_feat.data(), g_depth.data());
    std::vector<float> d_means(3 * n), d_cov(6 * n), d_scales(scale_path ? 3 * n : 0), d_quats(scale_path ? 4 * n : 0),
        d_sh((size_t)n * K * 3);
    launch_serial(rast_preprocess_bwd, dim3(blocks_for(n)), lin, n, means.data(), cov_in, scales.data(),
                  quats.data(), sh.data(), K, deg, params.data(), radii.data(), clamped.data(), g_m2.data(),
                  g_conic.data(), g_col.data(), g_depth.data(), exact, d_means.data(), d_cov.data(), d_scales.data(),
                  d_quats.data(), d_sh.data());

    Writer w(out_path);
    w.put("rgb", rgb);
    w.put("feat", feat);
    w.put("alpha", alpha);
    w.put("depth", depth);
    w.put("final_t", final_t);
    w.put("n_contrib", n_contrib);
    w.put("radii", radii);
    w.put("tiles_touched", tiles);
    w.put("means2d", means2d);
    w.put("depths", depths);
    w.put("cov2d", cov2d);
    std::vector<float> conic(3 * n);
    for (int i = 0; i < n; i++)
        for (int k = 0; k < 3; k++) conic[3 * i + k] = conic_op[4 * i + k];
    w.put("conic", conic);
    w.put("colors", colors);
    w.put("num_pairs", std::vector<unsigned>{pairs});
    vals.resize(pairs);
    w.put("point_list", vals);
    w.put("grad_means", d_means);
    w.put("grad_cov3d", d_cov);
    if (scale_path) {
        w.put("grad_scales", d_scales);
        w.put("grad_quats", d_quats);
    }
    w.put("grad_opacities", g_op);
    w.put("grad_sh", d_sh);
    w.put("grad_features", g_feat);
    w.put("grad_means2d_ndc", g_m2);
    if (!w.f) throw std::runtime_error("write failed");
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 3) {
        std::fprintf(stderr, "usage: %s inputs.bin outputs.bin\n", argv[0]);
        return 2;
    }
    try {
        return run(argv[1], argv[2]);
    } catch (const std::exception& e) {
        std::fprintf(stderr, "emulate_main: %s\n", e.what());
        return 1;
    }
}
