// CPU emulation of the small CUDA subset rasterize.cu uses, so the very same kernel source compiles as
// ordinary C++20 (g++ -O2 -std=c++20 -pthread) and its logic can be tested without a GPU.
//
// Execution model:
// - Blocks run one after another. `__shared__` is `static`, so each kernel's shared arrays are one set of
//   statics that the block currently running owns.
// - `launch` runs the threads of a block as real std::threads (one per CUDA thread, reused for every block
//   of the launch); `__syncthreads` is a std::barrier over them, so a missing barrier or a race can show
//   up as it would on a GPU. A thread that returns drops out of its block's barrier (the kernels keep every thread in the
//   loops that synchronise anyway).
// - `launch_serial` runs a block's threads one after another on the calling thread: for kernels without
//   `__syncthreads` (element-wise work, sort passes), which would otherwise cost one OS thread per element.
//   Calling `__syncthreads` in that mode aborts.
// - atomicAdd is std::atomic_ref::fetch_add (float, int, unsigned).
// - No FMA contraction with the default flags (baseline x86-64 has no FMA); nvcc contracts a*b+c by
//   default, so compare the GPU and emulated results with tolerances, not bitwise.
#pragma once

#include <atomic>
#include <barrier>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <optional>
#include <thread>
#include <tuple>
#include <vector>

#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
#define __shared__ static

struct dim3 {
    unsigned x, y, z;
    constexpr dim3(unsigned x_ = 1, unsigned y_ = 1, unsigned z_ = 1) : x(x_), y(y_), z(z_) {}
};

inline thread_local dim3 threadIdx;
inline thread_local dim3 blockIdx;
// Same for every thread of a launch; written only between blocks.
inline dim3 blockDim;
inline dim3 gridDim;

namespace emu {
inline std::barrier<>* block_barrier = nullptr;
}

inline void __syncthreads() {
    if (!emu::block_barrier) {
        std::fprintf(stderr, "emulate.h: __syncthreads in a kernel launched with launch_serial\n");
        std::abort();
    }
    emu::block_barrier->arrive_and_wait();
}

inline float atomicAdd(float* p, float v) { return std::atomic_ref<float>(*p).fetch_add(v); }
inline int atomicAdd(int* p, int v) { return std::atomic_ref<int>(*p).fetch_add(v); }
inline unsigned atomicAdd(unsigned* p, unsigned v) { return std::atomic_ref<unsigned>(*p).fetch_add(v); }

inline unsigned __float_as_uint(float f) {
    unsigned u;
    std::memcpy(&u, &f, sizeof u);
    return u;
}

using std::isfinite;

namespace emu {

inline dim3 block_coord(unsigned b, dim3 g) { return dim3(b % g.x, (b / g.x) % g.y, b / (g.x * g.y)); }

inline dim3 thread_coord(unsigned t, dim3 d) { return dim3(t % d.x, (t / d.x) % d.y, t / (d.x * d.y)); }

}  // namespace emu

// kernel<<<grid, block>>>(args...) with one std::thread per CUDA thread and a block-wide barrier. The
// threads are created once per launch and run the blocks in turn; a gate barrier between blocks makes the
// next block start only when every thread has finished the previous one (its shared statics are free).
template <class... P, class... A>
void launch(void (*kernel)(P...), dim3 grid, dim3 block, A... args) {
    const std::tuple<P...> params(static_cast<P>(args)...);
    gridDim = grid;
    blockDim = block;
    const unsigned nb = grid.x * grid.y * grid.z;
    const unsigned nt = block.x * block.y * block.z;
    // A fresh barrier per block: threads that return early drop out of their block's barrier only.
    std::optional<std::barrier<>> bar;
    bar.emplace(nt);
    emu::block_barrier = &*bar;
    auto next_block = [&]() noexcept {
        bar.emplace(nt);
        emu::block_barrier = &*bar;
    };
    std::barrier gate(nt, next_block);
    std::vector<std::thread> threads;
    threads.reserve(nt);
    for (unsigned t = 0; t < nt; ++t) {
        threads.emplace_back([&, t] {
            threadIdx = emu::thread_coord(t, block);
            for (unsigned b = 0; b < nb; ++b) {
                blockIdx = emu::block_coord(b, grid);
                std::apply(kernel, params);
                emu::block_barrier->arrive_and_drop();
                gate.arrive_and_wait();
            }
        });
    }
    for (auto& th : threads) th.join();
    emu::block_barrier = nullptr;
}

// kernel<<<grid, block>>>(args...) for kernels that never call __syncthreads: threads run in sequence.
template <class... P, class... A>
void launch_serial(void (*kernel)(P...), dim3 grid, dim3 block, A... args) {
    const std::tuple<P...> params(static_cast<P>(args)...);
    gridDim = grid;
    blockDim = block;
    const unsigned nb = grid.x * grid.y * grid.z;
    const unsigned nt = block.x * block.y * block.z;
    for (unsigned b = 0; b < nb; ++b) {
        blockIdx = emu::block_coord(b, grid);
        for (unsigned t = 0; t < nt; ++t) {
            threadIdx = emu::thread_coord(t, block);
            std::apply(kernel, params);
        }
    }
}
