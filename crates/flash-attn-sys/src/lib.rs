//! The C entry point of scripts/build-flash-attn's `libflashattention.a`: `run_mha` of candle-flash-attn
//! 0.11.1's `kernels/flash_api.cu` (FlashAttention-2 forward), declared here with that signature. The library
//! holds only the head-dim-64, non-causal f16/bf16 kernels; every other dispatch target is a stub that aborts.
//! Only linked with the `link` feature; `mvsplat360-nn`'s `flash_attn` module is the caller and checks the limits.
//!
//! # Safety contract (the library reports no errors)
//! The library's error checks evaluate and discard CUDA errors, so a launch that fails (too large a grid, a GPU
//! without the SASS it holds, a wrong context) leaves `o_ptr` unwritten and returns normally. Callers must pass:
//! device pointers of the current context, 16-byte aligned (strides multiples of 8 elements), `d == 64`,
//! `d_rounded == 64`, `b ≤ 65535` and `h ≤ 65535` (grid y/z), `h % h_k == 0`, `is_causal == 0`, windows −1,
//! `softcap == 0`, null alibi / cu_seqlens / block_table / mm_prefix_ranges, `page_block_size == −1`, a
//! `softmax_lse_ptr` of `b·h·seqlen_q` f32, and a `CUstream` (as `stream_ptr`) of that context.

use core::ffi::{c_int, c_void};

extern "C" {
    /// FlashAttention-2 forward: `o = softmax(q·kᵀ·softmax_scale)·v` per (batch, head), strides in elements.
    pub fn run_mha(
        q_ptr: *const c_void,
        k_ptr: *const c_void,
        v_ptr: *const c_void,
        o_ptr: *const c_void,
        softmax_lse_ptr: *const c_void,
        alibi_slopes_ptr: *const c_void,
        cu_seqlens_q_ptr: *const i32,
        cu_seqlens_k_ptr: *const i32,
        q_batch_stride: u32,
        k_batch_stride: u32,
        v_batch_stride: u32,
        o_batch_stride: u32,
        alibi_slopes_batch_stride: u32,
        q_row_stride: u32,
        k_row_stride: u32,
        v_row_stride: u32,
        o_row_stride: u32,
        q_head_stride: u32,
        k_head_stride: u32,
        v_head_stride: u32,
        o_head_stride: u32,
        b: u32,
        h: u32,
        h_k: u32,
        d: u32,
        d_rounded: u32,
        softmax_scale: f32,
        seqlen_q: u32,
        seqlen_k: u32,
        seqlen_q_rounded: u32,
        seqlen_k_rounded: u32,
        total_q: u32,
        is_bf16: c_int,
        is_causal: c_int,
        unpadded_lse: c_int,
        window_size_left: c_int,
        window_size_right: c_int,
        softcap: f32,
        block_table_ptr: *const i32,
        block_table_batch_stride: u32,
        page_block_size: c_int,
        mm_prefix_ranges_ptr: *const i32,
        mm_prefix_range_batch_stride: u32,
        max_mm_prefix_ranges: c_int,
        stream_ptr: *mut c_void,
    );
}
