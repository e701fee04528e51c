// CPU emulation of the half-precision subset fused.cu uses (cuda_fp16.h / cuda_bf16.h under nvcc):
// storage types holding the IEEE binary16 / bfloat16 bits, and the conversions, float → half rounding to
// nearest, ties to even, as the __float2half / __float2bfloat16 intrinsics do. Include after
// crates/splat/cuda/emulate.h.
#pragma once

#include <cstdint>
#include <cstring>

struct __half {
    uint16_t bits;
};

struct __nv_bfloat16 {
    uint16_t bits;
};

namespace emu {

inline uint32_t f32_bits(float f) {
    uint32_t u;
    std::memcpy(&u, &f, 4);
    return u;
}

inline float f32_from(uint32_t u) {
    float f;
    std::memcpy(&f, &u, 4);
    return f;
}

}  // namespace emu

inline float __half2float(__half h) {
    const uint32_t sign = (uint32_t)(h.bits & 0x8000u) << 16;
    const uint32_t exp = (h.bits >> 10) & 0x1fu;
    uint32_t man = h.bits & 0x3ffu;
    if (exp == 0x1f) return emu::f32_from(sign | 0x7f800000u | (man << 13));  // inf / NaN
    if (exp != 0) return emu::f32_from(sign | ((exp + 112) << 23) | (man << 13));
    if (man == 0) return emu::f32_from(sign);
    // Subnormal: man · 2^-24, exact in f32.
    const float v = (float)man * 5.9604644775390625e-8f;
    return sign ? -v : v;
}

inline __half __float2half(float f) {
    const uint32_t u = emu::f32_bits(f);
    const uint16_t sign = (uint16_t)((u >> 16) & 0x8000u);
    const uint32_t a = u & 0x7fffffffu;
    if (a >= 0x7f800000u) return {(uint16_t)(sign | 0x7c00u | (a > 0x7f800000u ? 0x200u : 0u))};  // inf / NaN
    // ≥ 65520 rounds to infinity (65504 is the largest finite half, 65520 the midpoint to the next binade).
    if (a >= 0x477ff000u) return {(uint16_t)(sign | 0x7c00u)};
    const int e = (int)(a >> 23) - 127;
    if (e >= -14) {
        // Normal: drop 13 mantissa bits with round-to-nearest-even; a carry into the exponent is correct.
        const uint32_t r = a + 0xfffu + ((a >> 13) & 1u);
        return {(uint16_t)(sign | (((r >> 13) - (112u << 10)) & 0x7fffu))};
    }
    if (e < -25) return {sign};  // below half the smallest subnormal (2^-25): rounds to zero
    // Subnormal: value = m · 2^(e−23) with the implicit bit; in units of 2^-24 that is m >> (−e − 1).
    const uint32_t m = (a & 0x7fffffu) | 0x800000u;
    const int shift = -e - 1;  // 14 ..= 24
    const uint32_t q = m >> shift, rest = m & ((1u << shift) - 1), half = 1u << (shift - 1);
    const uint32_t rounded = q + (rest > half || (rest == half && (q & 1u)) ? 1u : 0u);
    return {(uint16_t)(sign | rounded)};
}

inline float __bfloat162float(__nv_bfloat16 h) { return emu::f32_from((uint32_t)h.bits << 16); }

inline __nv_bfloat16 __float2bfloat16(float f) {
    const uint32_t u = emu::f32_bits(f);
    if ((u & 0x7fffffffu) > 0x7f800000u) return {(uint16_t)((u >> 16) | 0x40u)};  // quiet NaN
    return {(uint16_t)((u + 0x7fffu + ((u >> 16) & 1u)) >> 16)};
}
