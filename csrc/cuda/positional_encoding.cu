// CUDA kernels of positional_encoding: x (N, D) -> (N, D * (include_input + 2 * num_freqs)), rows
// [x, sin(f0 x), cos(f0 x), sin(f1 x), cos(f1 x), ...] with f_k = scale * 2^k.
//
// The op moves far more bytes than it reads (a 63-wide row per 3 inputs), so the output must be
// written coalesced. A block encodes a tile of whole points into shared memory, one thread per
// (point, feature) computing every octave of its sin/cos once, then the block copies the tile's
// rows -- one contiguous span of global memory -- out with consecutive threads on consecutive
// addresses. The backward mirrors it: the grad_out tile is read contiguously into shared memory,
// then each thread sums its feature's terms. Rows too wide for shared memory take direct kernels.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>  // = at::cuda::getCurrentCUDAStream, without the cuSPARSE/cuBLAS headers

#include <algorithm>
#include <cstdint>

#include "common.h"
#include "positional_encoding.h"
#include "positional_encoding_math.h"

namespace mixer_nerf {
namespace {

namespace pem = positional_encoding_math;

constexpr int kThreads = 256;
constexpr int64_t kTileBytes = 48 * 1024;  // shared memory per block without an opt-in

struct Encoding {
  int64_t points;     // N
  int64_t dims;       // D
  int64_t num_freqs;  // F
  bool include_input;
  double scale;
  pem::HalfTurns turns;  // scale / pi

  C10_HOST_DEVICE int64_t width() const { return dims * ((include_input ? 1 : 0) + 2 * num_freqs); }
};

// Writes x's block (if any) and every sin/cos of one feature into row[0], row[D], row[2D], ...
// (row points at the feature's column of its output row, in shared or global memory).
template <typename scalar_t>
__device__ void encode_feature(scalar_t x, scalar_t* row, const Encoding& e) {
  using acc = acc_t<scalar_t>;
  int64_t col = 0;
  if (e.include_input) {
    row[0] = x;
    col = e.dims;
  }
  const double xs = pem::bounded_input(static_cast<acc>(x), e.turns.hi);
  double hi = e.turns.hi, lo = e.turns.lo;  // c 2^k, doubled per octave (exact)
  for (int64_t k = 0; k < e.num_freqs; ++k, hi *= 2, lo *= 2, col += 2 * e.dims) {
    acc s, c;
    pem::sincospi<acc>(__dmul_rn(hi, xs), __dmul_rn(lo, xs), s, c);  // rounded products, as on the CPU
    row[col] = static_cast<scalar_t>(s);
    row[col + e.dims] = static_cast<scalar_t>(c);
  }
}

// d/dx of one feature: grad[x] + sum_k scale 2^k (grad[sin_k] cos - grad[cos_k] sin), sin/cos
// recomputed from x; row as in encode_feature, holding grad_out.
template <typename scalar_t>
__device__ scalar_t encode_feature_backward(scalar_t x, const scalar_t* row, const Encoding& e) {
  using acc = acc_t<scalar_t>;
  acc grad = 0;
  int64_t col = 0;
  if (e.include_input) {
    grad = static_cast<acc>(row[0]);
    col = e.dims;
  }
  const double xs = pem::bounded_input(static_cast<acc>(x), e.turns.hi);
  double hi = e.turns.hi, lo = e.turns.lo;
  acc freq = static_cast<acc>(e.scale);
  for (int64_t k = 0; k < e.num_freqs; ++k, hi *= 2, lo *= 2, freq *= 2, col += 2 * e.dims) {
    acc s, c;
    pem::sincospi<acc>(__dmul_rn(hi, xs), __dmul_rn(lo, xs), s, c);
    grad += freq * (static_cast<acc>(row[col]) * c - static_cast<acc>(row[col + e.dims]) * s);
  }
  return static_cast<scalar_t>(grad);
}

// Copies `count` elements between a tile and global memory: 16-byte accesses when both ends are
// 16-byte aligned (every full tile is, see tile_points), four of them in flight per thread, so
// enough loads are outstanding to stream at full bandwidth.
template <typename scalar_t>
__device__ void copy_tile(scalar_t* __restrict__ dst, const scalar_t* __restrict__ src, int count) {
  int done = 0;
  if (((reinterpret_cast<uintptr_t>(dst) | reinterpret_cast<uintptr_t>(src)) & 15) == 0) {
    constexpr int kPerVector = 16 / sizeof(scalar_t), kUnroll = 4;
    const int vectors = count / kPerVector;
    auto* dst4 = reinterpret_cast<uint4*>(dst);
    const auto* src4 = reinterpret_cast<const uint4*>(src);
    for (int base = threadIdx.x; base < vectors; base += kUnroll * blockDim.x) {
      uint4 v[kUnroll];
#pragma unroll
      for (int u = 0; u < kUnroll; ++u) {
        if (base + u * blockDim.x < vectors) v[u] = src4[base + u * blockDim.x];
      }
#pragma unroll
      for (int u = 0; u < kUnroll; ++u) {
        if (base + u * blockDim.x < vectors) dst4[base + u * blockDim.x] = v[u];
      }
    }
    done = vectors * kPerVector;
  }
  for (int i = done + threadIdx.x; i < count; i += blockDim.x) dst[i] = src[i];
}

// Shared-memory tile of `tile_points` whole output rows, typed for scalar_t.
template <typename scalar_t>
__device__ scalar_t* tile_memory() {
  extern __shared__ __align__(16) unsigned char tile_bytes[];
  return reinterpret_cast<scalar_t*>(tile_bytes);
}

template <typename scalar_t>
__global__ void encode_tiles(const scalar_t* __restrict__ x, scalar_t* __restrict__ out, Encoding e,
                             int tile_points) {
  scalar_t* tile = tile_memory<scalar_t>();
  const int64_t first = static_cast<int64_t>(blockIdx.x) * tile_points;
  const int points = static_cast<int>(e.points - first < tile_points ? e.points - first : tile_points);
  const int D = static_cast<int>(e.dims), W = static_cast<int>(e.width());
  for (int j = threadIdx.x; j < points * D; j += blockDim.x) {
    const int p = j / D;
    encode_feature(x[first * D + j], tile + p * W + (j - p * D), e);
  }
  __syncthreads();
  copy_tile(out + first * W, tile, points * W);
}

template <typename scalar_t>
__global__ void encode_tiles_backward(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ x,
                                      scalar_t* __restrict__ grad_x, Encoding e, int tile_points) {
  scalar_t* tile = tile_memory<scalar_t>();
  const int64_t first = static_cast<int64_t>(blockIdx.x) * tile_points;
  const int points = static_cast<int>(e.points - first < tile_points ? e.points - first : tile_points);
  const int D = static_cast<int>(e.dims), W = static_cast<int>(e.width());
  copy_tile(tile, grad + first * W, points * W);
  __syncthreads();
  for (int j = threadIdx.x; j < points * D; j += blockDim.x) {
    const int p = j / D;
    grad_x[first * D + j] = encode_feature_backward(x[first * D + j], tile + p * W + (j - p * D), e);
  }
}

// Rows wider than shared memory: one thread per (point, feature) straight on global memory.
template <typename scalar_t>
__global__ void encode_direct(const scalar_t* __restrict__ x, scalar_t* __restrict__ out, Encoding e) {
  const int64_t total = e.points * e.dims, stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < total; i += stride) {
    const int64_t p = i / e.dims;
    encode_feature(x[i], out + p * e.width() + (i - p * e.dims), e);
  }
}

template <typename scalar_t>
__global__ void encode_direct_backward(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ x,
                                       scalar_t* __restrict__ grad_x, Encoding e) {
  const int64_t total = e.points * e.dims, stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < total; i += stride) {
    const int64_t p = i / e.dims;
    grad_x[i] = encode_feature_backward(x[i], grad + p * e.width() + (i - p * e.dims), e);
  }
}

// Whole points per tile (0: a row does not fit, use the direct kernels): about one per thread and
// feature, rounded down to a multiple of 8 where possible so that every tile starts 16-byte
// aligned (8 rows of 2-byte elements are a multiple of 16 bytes).
int tile_points(const Encoding& e, int64_t element_bytes) {
  const int64_t row_bytes = std::max<int64_t>(1, e.width()) * element_bytes;
  int64_t points = std::min<int64_t>(std::max<int64_t>(1, kThreads / e.dims), kTileBytes / row_bytes);
  if (points >= 8) points -= points % 8;
  return static_cast<int>(points);
}

int direct_blocks(const Encoding& e) {
  const int64_t blocks = (e.points * e.dims + kThreads - 1) / kThreads;
  return static_cast<int>(std::min<int64_t>(blocks, 65535));
}

Encoding encoding_of(const at::Tensor& x, int64_t num_freqs, bool include_input, double scale) {
  positional_encoding::check_args(x, num_freqs, at::kCUDA);
  const int64_t dims = x.size(-1);
  return {x.numel() / dims, dims, num_freqs, include_input, scale, pem::half_turns(scale)};
}

at::Tensor positional_encoding_fwd_cuda(const at::Tensor& x, int64_t num_freqs, bool include_input, double scale) {
  const Encoding e = encoding_of(x, num_freqs, include_input, scale);
  at::Tensor out = at::empty(positional_encoding::encoded_shape(x, e.width()), x.options());
  if (out.numel() == 0) return out;
  const c10::cuda::CUDAGuard guard(x.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  MIXER_NERF_DISPATCH_FLOATING(x.scalar_type(), "positional_encoding_fwd_cuda", [&] {
    const scalar_t* xp = x.const_data_ptr<scalar_t>();
    scalar_t* op = out.mutable_data_ptr<scalar_t>();
    const int tile = tile_points(e, sizeof(scalar_t));
    if (tile > 0) {
      const auto blocks = static_cast<unsigned>((e.points + tile - 1) / tile);
      encode_tiles<scalar_t><<<blocks, kThreads, tile * e.width() * sizeof(scalar_t), stream>>>(xp, op, e, tile);
    } else {
      encode_direct<scalar_t><<<direct_blocks(e), kThreads, 0, stream>>>(xp, op, e);
    }
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

at::Tensor positional_encoding_bwd_cuda(const at::Tensor& grad_out, const at::Tensor& x, int64_t num_freqs,
                                        bool include_input, double scale) {
  const Encoding e = encoding_of(x, num_freqs, include_input, scale);
  positional_encoding::check_grad_out(grad_out, x, e.width(), at::kCUDA);
  at::Tensor grad_x = at::empty_like(x);
  if (grad_x.numel() == 0) return grad_x;
  const c10::cuda::CUDAGuard guard(x.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  MIXER_NERF_DISPATCH_FLOATING(x.scalar_type(), "positional_encoding_bwd_cuda", [&] {
    const scalar_t* gp = grad_out.const_data_ptr<scalar_t>();
    const scalar_t* xp = x.const_data_ptr<scalar_t>();
    scalar_t* gxp = grad_x.mutable_data_ptr<scalar_t>();
    const int tile = tile_points(e, sizeof(scalar_t));
    if (tile > 0) {
      const auto blocks = static_cast<unsigned>((e.points + tile - 1) / tile);
      encode_tiles_backward<scalar_t>
          <<<blocks, kThreads, tile * e.width() * sizeof(scalar_t), stream>>>(gp, xp, gxp, e, tile);
    } else {
      encode_direct_backward<scalar_t><<<direct_blocks(e), kThreads, 0, stream>>>(gp, xp, gxp, e);
    }
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return grad_x;
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) {
  m.impl("positional_encoding_fwd", &positional_encoding_fwd_cuda);
  m.impl("positional_encoding_bwd", &positional_encoding_bwd_cuda);
}

}  // namespace mixer_nerf
