// Fake libcuda.so for developers without a GPU: the subset of the CUDA driver API that cudarc uses, running
// rasterize.cu's kernels on the CPU through emulate.h (synchronously; new device memory is filled with garbage so
// missing zeroing shows; launches with a wrong block/grid shape or out-of-bounds copies abort). Lets
// src/cuda.rs run end to end: see device-test-on-cpu.
#include "emulate.h"
#include "rasterize.cu"

#include <cstdint>
#include <map>
#include <mutex>
#include <string>
#include <utility>

typedef int CUresult;
typedef int CUdevice;
typedef unsigned long long CUdeviceptr;

namespace {
struct Func { std::string name; };
std::map<std::string, Func*> funcs;
int dummy_ctx, dummy_module, dummy_stream_storage[64];
int stream_counter = 0;
std::map<uintptr_t, size_t> allocs;  // live device allocations
std::mutex mu;
unsigned long launches = 0;

void note(const char* what) {
    if (getenv("FAKECUDA_TRACE")) fprintf(stderr, "fakecuda: %s\n", what);
}

void check_ptr(CUdeviceptr p, size_t bytes, const char* what) {
    // p must lie in a live allocation with `bytes` available.
    auto it = allocs.upper_bound((uintptr_t)p);
    if (it == allocs.begin()) { fprintf(stderr, "fakecuda: %s: bad pointer\n", what); abort(); }
    --it;
    if ((uintptr_t)p + bytes > it->first + it->second) {
        fprintf(stderr, "fakecuda: %s: %zu bytes at offset %zu overflow allocation of %zu\n", what, bytes,
                (size_t)((uintptr_t)p - it->first), it->second);
        abort();
    }
}

template <class... P, size_t... I>
void call(void (*k)(P...), void** a, dim3 g, dim3 b, bool serial, std::index_sequence<I...>) {
    if (serial)
        launch_serial(k, g, b, *static_cast<P*>(a[I])...);
    else
        launch(k, g, b, *static_cast<P*>(a[I])...);
}
template <class... P>
void run(void (*k)(P...), void** a, dim3 g, dim3 b, bool serial) {
    call(k, a, g, b, serial, std::index_sequence_for<P...>{});
}
}  // namespace

extern "C" {
CUresult cuInit(unsigned) { note("cuInit"); return 0; }
CUresult cuDriverGetVersion(int* v) { *v = 13040; return 0; }
CUresult cuDeviceGet(CUdevice* d, int o) { *d = o; return o == 0 ? 0 : 101; }
CUresult cuDeviceGetCount(int* c) { *c = 1; return 0; }
CUresult cuDeviceGetAttribute(int* v, int attr, CUdevice) {
    // 115 = CU_DEVICE_ATTRIBUTE_MEMORY_POOLS_SUPPORTED: say no (plain alloc/free).
    *v = attr == 115 ? 0 : 1;
    return 0;
}
CUresult cuDevicePrimaryCtxRetain(void** c, CUdevice) { *c = &dummy_ctx; return 0; }
CUresult cuDevicePrimaryCtxRelease_v2(CUdevice) { return 0; }
CUresult cuDevicePrimaryCtxRelease(CUdevice) { return 0; }
CUresult cuCtxSetCurrent(void*) { return 0; }
CUresult cuCtxGetCurrent(void** c) { *c = &dummy_ctx; return 0; }
CUresult cuCtxPushCurrent_v2(void*) { return 0; }
CUresult cuCtxPopCurrent_v2(void** c) { *c = &dummy_ctx; return 0; }
CUresult cuCtxSynchronize() { return 0; }
CUresult cuStreamCreate(void** s, unsigned) { *s = &dummy_stream_storage[(stream_counter++) % 64]; return 0; }
CUresult cuStreamCreateWithPriority(void** s, unsigned, int) { return cuStreamCreate(s, 0); }
CUresult cuStreamDestroy_v2(void*) { return 0; }
CUresult cuStreamDestroy(void*) { return 0; }
CUresult cuStreamSynchronize(void*) { note("sync"); return 0; }
CUresult cuStreamWaitEvent(void*, void*, unsigned) { return 0; }
CUresult cuEventCreate(void** e, unsigned) { *e = new int(0); return 0; }
CUresult cuEventRecord(void*, void*) { return 0; }
CUresult cuEventSynchronize(void*) { return 0; }
CUresult cuEventQuery(void*) { return 0; }
CUresult cuEventDestroy_v2(void* e) { delete static_cast<int*>(e); return 0; }
CUresult cuEventDestroy(void* e) { return cuEventDestroy_v2(e); }
CUresult cuModuleLoadData(void** m, const void* image) {
    const char* s = static_cast<const char*>(image);
    if (!strstr(s, ".entry rast_render_bwd")) return 200;
    *m = &dummy_module;
    return 0;
}
CUresult cuModuleUnload(void*) { return 0; }
CUresult cuModuleGetFunction(void** f, void*, const char* name) {
    std::lock_guard<std::mutex> g(mu);
    static const char* known[] = {"rast_preprocess", "rast_scan_block", "rast_scan_add", "rast_duplicate",
                                  "rast_fill_pad", "rast_bitonic_step", "rast_tile_ranges", "rast_render_fwd",
                                  "rast_render_bwd", "rast_preprocess_bwd", "rast_unpack_cols", "rast_pack_cols"};
    bool ok = false;
    for (auto k : known) ok |= !strcmp(k, name);
    if (!ok) return 500;  // CUDA_ERROR_NOT_FOUND
    auto& p = funcs[name];
    if (!p) p = new Func{name};
    *f = p;
    return 0;
}
CUresult cuMemAlloc_v2(CUdeviceptr* p, size_t bytes) {
    std::lock_guard<std::mutex> g(mu);
    void* m = malloc(bytes ? bytes : 1);
    // Poison: device memory is not zeroed by cuMemAlloc.
    memset(m, 0xA5, bytes);
    allocs[(uintptr_t)m] = bytes;
    *p = (CUdeviceptr)m;
    return 0;
}
CUresult cuMemAllocAsync(CUdeviceptr* p, size_t bytes, void*) { return cuMemAlloc_v2(p, bytes); }
CUresult cuMemFree_v2(CUdeviceptr p) {
    std::lock_guard<std::mutex> g(mu);
    auto it = allocs.find((uintptr_t)p);
    if (it == allocs.end()) { fprintf(stderr, "fakecuda: free of unknown pointer\n"); abort(); }
    memset((void*)p, 0x5A, it->second);
    allocs.erase(it);
    free((void*)p);
    return 0;
}
CUresult cuMemFreeAsync(CUdeviceptr p, void*) { return cuMemFree_v2(p); }
CUresult cuMemsetD8Async(CUdeviceptr p, unsigned char v, size_t n, void*) {
    check_ptr(p, n, "memset");
    memset((void*)p, v, n);
    return 0;
}
CUresult cuMemsetD8_v2(CUdeviceptr p, unsigned char v, size_t n) { return cuMemsetD8Async(p, v, n, nullptr); }
CUresult cuMemcpyHtoDAsync_v2(CUdeviceptr d, const void* s, size_t n, void*) {
    check_ptr(d, n, "htod");
    memcpy((void*)d, s, n);
    return 0;
}
CUresult cuMemcpyHtoD_v2(CUdeviceptr d, const void* s, size_t n) { return cuMemcpyHtoDAsync_v2(d, s, n, nullptr); }
CUresult cuMemcpyDtoHAsync_v2(void* d, CUdeviceptr s, size_t n, void*) {
    check_ptr(s, n, "dtoh");
    memcpy(d, (void*)s, n);
    return 0;
}
CUresult cuMemcpyDtoH_v2(void* d, CUdeviceptr s, size_t n) { return cuMemcpyDtoHAsync_v2(d, s, n, nullptr); }
CUresult cuMemcpyDtoDAsync_v2(CUdeviceptr d, CUdeviceptr s, size_t n, void*) {
    check_ptr(s, n, "dtod src");
    check_ptr(d, n, "dtod dst");
    memmove((void*)d, (const void*)s, n);
    return 0;
}
CUresult cuMemcpyDtoD_v2(CUdeviceptr d, CUdeviceptr s, size_t n) { return cuMemcpyDtoDAsync_v2(d, s, n, nullptr); }
CUresult cuGetErrorString(CUresult, const char** s) { *s = "fakecuda error"; return 0; }
CUresult cuGetErrorName(CUresult, const char** s) { *s = "FAKECUDA_ERROR"; return 0; }

CUresult cuLaunchKernel(void* f, unsigned gx, unsigned gy, unsigned gz, unsigned bx, unsigned by, unsigned bz,
                        unsigned shmem, void*, void** a, void** extra) {
    const std::string& name = static_cast<Func*>(f)->name;
    if (extra || shmem) { fprintf(stderr, "fakecuda: %s: extra/shared mem\n", name.c_str()); abort(); }
    if (gz != 1 || bz != 1 || gx == 0 || gy == 0) { fprintf(stderr, "fakecuda: %s: bad grid\n", name.c_str()); abort(); }
    const dim3 g(gx, gy), b(bx, by);
    const bool tile = name == "rast_render_fwd" || name == "rast_render_bwd";
    if (tile ? (bx != TILE || by != TILE) : (bx != BLOCK_SIZE || by != 1 || gy != 1)) {
        fprintf(stderr, "fakecuda: %s: block %ux%u grid %ux%u\n", name.c_str(), bx, by, gx, gy);
        abort();
    }
    static std::mutex launch_mu;  // the emulator's globals (blockDim, shared statics) serve one launch at a time
    std::lock_guard<std::mutex> lk(launch_mu);
    launches++;
    if (getenv("FAKECUDA_TRACE")) fprintf(stderr, "fakecuda: launch %s grid %u x %u\n", name.c_str(), gx, gy);
    if (name == "rast_preprocess") run(rast_preprocess, a, g, b, true);
    else if (name == "rast_scan_block") run(rast_scan_block, a, g, b, false);
    else if (name == "rast_scan_add") run(rast_scan_add, a, g, b, true);
    else if (name == "rast_duplicate") run(rast_duplicate, a, g, b, true);
    else if (name == "rast_fill_pad") run(rast_fill_pad, a, g, b, true);
    else if (name == "rast_bitonic_step") run(rast_bitonic_step, a, g, b, true);
    else if (name == "rast_tile_ranges") run(rast_tile_ranges, a, g, b, true);
    else if (name == "rast_render_fwd") run(rast_render_fwd, a, g, b, false);
    else if (name == "rast_render_bwd") run(rast_render_bwd, a, g, b, false);
    else if (name == "rast_preprocess_bwd") run(rast_preprocess_bwd, a, g, b, true);
    else if (name == "rast_unpack_cols") run(rast_unpack_cols, a, g, b, true);
    else if (name == "rast_pack_cols") run(rast_pack_cols, a, g, b, true);
    else abort();
    return 0;
}
}
