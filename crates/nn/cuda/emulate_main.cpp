// CPU driver for fused.cu compiled through crates/splat/cuda/emulate.h and emulate_half.h: runs the launch
// sequence of src/fused_cuda.rs on inputs read from a file and writes the outputs to a file.
//
//   g++ -O2 -std=c++20 -pthread -o emulate_main emulate_main.cpp
//   ./emulate_main inputs.bin outputs.bin
//
// Record files as crates/splat/cuda/emulate_main.cpp's (little-endian; until end of file):
//   u32 name_len, name bytes, u32 dtype (0 = f32, 1 = i32), u64 count, count * 4 bytes.
// Inputs:  op (i32[1]: 0 = GroupNorm, 1 = GEGLU), dtype (i32[1]: 0 = f32, 1 = f16, 2 = bf16; the f32 values
//          given must be exact in it), then
//   GroupNorm: dims (i32: n, c, s, groups, frames, silu, chunk), eps (f32[1]), x (n*c*s), weight, bias (c);
//   GEGLU:     dims (i32: m, hdim, has_bias), h (m*2*hdim), bias (2*hdim, when has_bias).
// Outputs: y (f32: (n, c, s) or (m, hdim)); GroupNorm also stats (f32: mean, rstd per (batch, group)).
#include "../../splat/cuda/emulate.h"
#include "emulate_half.h"
#include "fused.cu"
#include "../../splat/cuda/records.h"

#include <cstdint>
#include <algorithm>
#include <fstream>
#include <map>
#include <stdexcept>
#include <string>

using namespace records;

namespace {

template <class T>
T from_f32(float v) {
    T out;
    store_f(&out, v);
    return out;
}

// The device copy of an input: must round-trip exactly (the test rounds its inputs to the dtype first).
template <class T>
std::vector<T> to_device(const std::vector<float>& v, const char* what) {
    std::vector<T> out(v.size());
    for (size_t i = 0; i < v.size(); ++i) {
        out[i] = from_f32<T>(v[i]);
        if (to_f(out[i]) != v[i] && v[i] == v[i])
            throw std::runtime_error(std::string(what) + ": value not exact in the dtype at " + std::to_string(i));
    }
    return out;
}

template <class T>
std::vector<float> to_host(const std::vector<T>& v) {
    std::vector<float> out(v.size());
    for (size_t i = 0; i < v.size(); ++i) out[i] = to_f(v[i]);
    return out;
}

using PartialFn = void (*)(const void*, float*, int, int, int, int, i64, int, int);

template <class T>
void group_norm(const std::map<std::string, Rec>& m, void (*partial)(const T*, float*, int, int, int, int, i64, int, int),
                void (*apply)(const T*, T*, const float*, const float*, const float*, int, int, int, int, i64, int),
                Writer& w) {
    const auto d = take<int>(m, "dims", 7);
    const int n = d[0], c = d[1], groups = d[3], frames = d[4], silu = d[5], chunk = d[6];
    const i64 s = d[2];
    if (c % groups || n % frames || chunk < 1 || chunk > GN_CHUNK) throw std::runtime_error("bad dims");
    const int cg = c / groups, bn = n / frames;
    const float eps = take<float>(m, "eps", 1)[0];
    const auto x = to_device<T>(take<float>(m, "x", (size_t)n * c * s), "x");
    const auto wt = take<float>(m, "weight", c), bs = take<float>(m, "bias", c);
    // Launch sequence of fused_cuda.rs::GroupNormFused.
    const i64 len = (i64)cg * s;
    const int cpr = (int)((len + chunk - 1) / chunk);
    std::vector<float> part(4 * (size_t)bn * groups * frames * cpr, NAN), stats(2 * (size_t)bn * groups, NAN);
    launch(partial, dim3(frames * cpr, bn * groups), dim3(GN_THREADS), x.data(), part.data(), groups, frames, c, cg, s,
           chunk, cpr);
    launch(gn_finalize, dim3(bn * groups), dim3(GN_THREADS), (const float*)part.data(), stats.data(), frames * cpr, eps);
    std::vector<T> y(x.size());
    const i64 by = std::min<i64>((s + 4 * EW_THREADS - 1) / (4 * EW_THREADS), 65535);
    launch_serial(apply, dim3(n * c, (unsigned)by), dim3(EW_THREADS), x.data(), y.data(), (const float*)stats.data(),
                  wt.data(), bs.data(), groups, frames, c, cg, s, silu);
    w.put("y", to_host(y));
    w.put("stats", stats);
}

template <class T>
void geglu_run(const std::map<std::string, Rec>& m, void (*kernel)(const T*, const float*, T*, int), Writer& w) {
    const auto d = take<int>(m, "dims", 3);
    const int rows = d[0], hdim = d[1];
    const auto h = to_device<T>(take<float>(m, "h", (size_t)rows * 2 * hdim), "h");
    std::vector<float> bias;
    if (d[2]) bias = take<float>(m, "bias", 2 * (size_t)hdim);
    std::vector<T> out((size_t)rows * hdim);
    launch_serial(kernel, dim3(rows), dim3(EW_THREADS), h.data(), (const float*)(bias.empty() ? nullptr : bias.data()),
                  out.data(), hdim);
    w.put("y", to_host(out));
}

int run(const char* in_path, const char* out_path) {
    const auto m = read_records(in_path);
    const int op = take<int>(m, "op", 1)[0], dtype = take<int>(m, "dtype", 1)[0];
    Writer w(out_path);
    if (op == 0) {
        if (dtype == 0) group_norm<float>(m, gn_partial_f32, gn_apply_f32, w);
        else if (dtype == 1) group_norm<__half>(m, gn_partial_f16, gn_apply_f16, w);
        else if (dtype == 2) group_norm<__nv_bfloat16>(m, gn_partial_bf16, gn_apply_bf16, w);
        else throw std::runtime_error("bad dtype");
    } else if (op == 1) {
        if (dtype == 0) geglu_run<float>(m, geglu_f32, w);
        else if (dtype == 1) geglu_run<__half>(m, geglu_f16, w);
        else if (dtype == 2) geglu_run<__nv_bfloat16>(m, geglu_bf16, w);
        else throw std::runtime_error("bad dtype");
    } else {
        throw std::runtime_error("bad op");
    }
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
