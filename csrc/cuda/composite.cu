// composite (volume rendering) on CUDA: one warp per ray. A ray's samples go in chunks of
// 32 runs, each lane holding a run of consecutive samples (the warp's loads cover
// contiguous memory; per-lane sums over a run replace shuffles). The math and its numerics are
// those of csrc/composite.cpp (read its file comment first):
//   forward:  T_i = exp(-(carry + exclusive scan of tau)), w_i = T_i * -expm1(-tau_i);
//   backward: G_j = alpha_j g_j + exp(-tau_j) G_{j+1} is an affine recurrence, evaluated from
//             the last chunk to the first as a reverse warp scan of affine maps x -> a + b x;
//             dL/dtau_j = T_{j+1} (g_j - G_{j+1}).
// The backward needs the optical depth at the start of every chunk while walking chunks in
// reverse; subtracting sums would cancel after a 1e10-long interval, so a first forward pass
// keeps one value per chunk in shared memory. No atomics, no global scratch beyond outputs.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <c10/cuda/CUDAStream.h>  // = at::cuda::getCurrentCUDAStream, without the cuSPARSE/cuBLAS headers
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>

#include <optional>
#include <tuple>

#include "common.h"

namespace mixer_nerf {
namespace {

constexpr int kWarpSize = 32;
constexpr unsigned kFullMask = 0xffffffffu;
constexpr int kMaxWarpsPerBlock = 8;
constexpr int kChannelsPerPass = 4;  // colour accumulators held in registers per forward pass
// Consecutive samples per lane (a run). Longer runs mean fewer shuffles per sample; measured on
// an H100 at R=65536, S=192: forward 157 us with runs of 2 vs 177 us with 1; the backward, with
// more live values per sample, is fastest with 1 (269 us vs 367 us with 2).
constexpr int kForwardRun = 2;
constexpr int kBackwardRun = 1;
constexpr int kForwardChunk = kWarpSize * kForwardRun;
constexpr int kBackwardChunk = kWarpSize * kBackwardRun;
constexpr size_t kSharedBytes = 48 * 1024;

template <typename scalar_t>
struct CompositeInputs {
  const scalar_t* sigmas;      // (N)
  const scalar_t* rgbs;        // (N, C)
  const scalar_t* t_starts;    // (N)
  const scalar_t* t_ends;      // (N)
  const scalar_t* background;  // nullptr, or row r at background + r * background_stride
  int64_t background_stride;   // 0 for one background (C), C for one per ray (R, C)
  int64_t channels;
};

template <typename scalar_t>
struct CompositeOutputs {
  scalar_t* color;    // (R, C)
  scalar_t* depth;    // (R)
  scalar_t* opacity;  // (R)
  scalar_t* weights;  // (N)
};

// Upstream gradients (nullptr: zeros) and the gradients to write (grad_t_*: nullptr to skip).
template <typename scalar_t>
struct CompositeGrads {
  const scalar_t* color;
  const scalar_t* depth;
  const scalar_t* opacity;
  const scalar_t* weights;
  scalar_t* sigmas;
  scalar_t* rgbs;
  scalar_t* t_starts;
  scalar_t* t_ends;
  acc_t<scalar_t>* background_rows;  // (R, C) or nullptr
};

__device__ __forceinline__ float exp_(float x) { return expf(x); }
__device__ __forceinline__ double exp_(double x) { return exp(x); }
__device__ __forceinline__ float expm1_(float x) { return expm1f(x); }
__device__ __forceinline__ double expm1_(double x) { return expm1(x); }

template <typename T>
__device__ __forceinline__ T warp_inclusive_sum(T x, int lane) {
#pragma unroll
  for (int d = 1; d < kWarpSize; d <<= 1) {
    const T y = __shfl_up_sync(kFullMask, x, d);
    if (lane >= d) x += y;
  }
  return x;
}

template <typename T>
__device__ __forceinline__ T warp_sum(T x) {
#pragma unroll
  for (int d = kWarpSize / 2; d > 0; d >>= 1) x += __shfl_xor_sync(kFullMask, x, d);
  return x;
}

// A lane's run of K consecutive samples of a chunk. Samples past the ray's end hold
// an empty interval (tau = 0, g = 0), the identity of both scans.
template <typename scalar_t, int K>
struct LaneSamples {
  using acc = acc_t<scalar_t>;
  int64_t first;  // index of the run's first sample
  int valid;      // how many of the run's samples are in the ray
  acc sigma[K] = {}, t_start[K] = {}, t_end[K] = {}, tau[K] = {};
  acc total = 0;  // sum of tau over the run
  __device__ LaneSamples(const CompositeInputs<scalar_t>& in, int64_t offset, int64_t count, int64_t k)
      : first(offset + k), valid(static_cast<int>(k >= count ? 0 : (count - k < K ? count - k : K))) {
#pragma unroll
    for (int j = 0; j < K; ++j) {
      if (j < valid) {
        sigma[j] = in.sigmas[first + j];
        t_start[j] = in.t_starts[first + j];
        t_end[j] = in.t_ends[first + j];
        tau[j] = sigma[j] * (t_end[j] - t_start[j]);
        total += tau[j];
      }
    }
  }
  __device__ acc midpoint(int j) const { return acc(0.5) * (t_start[j] + t_end[j]); }
};

// Optical depth before a lane's run given the optical depth `carry` before the chunk; advances
// carry past the chunk. Exclusive by shuffling the inclusive scan up a lane: never subtracts.
template <typename acc>
__device__ __forceinline__ acc run_optical_depth(acc run_total, int lane, acc& carry) {
  const acc inclusive = warp_inclusive_sum(run_total, lane);
  const acc exclusive = __shfl_up_sync(kFullMask, inclusive, 1);
  const acc before = carry + (lane == 0 ? acc(0) : exclusive);
  carry += __shfl_sync(kFullMask, inclusive, kWarpSize - 1);
  return before;
}

// Forward of one ray by one warp: samples [offset, offset + count).
// Channels beyond kChannelsPerPass take further passes (re-reading sigma/t beats spilling).
template <typename scalar_t>
__device__ void composite_forward_ray(const CompositeInputs<scalar_t>& in, const CompositeOutputs<scalar_t>& out,
                                      int64_t ray, int64_t offset, int64_t count, int lane) {
  using acc = acc_t<scalar_t>;
  const int64_t C = in.channels;
  for (int64_t c0 = 0; c0 == 0 || c0 < C; c0 += kChannelsPerPass) {
    acc color[kChannelsPerPass] = {};
    acc depth = 0, optical_depth = 0;
    for (int64_t base = 0; base < count; base += kForwardChunk) {
      const LaneSamples<scalar_t, kForwardRun> s(in, offset, count, base + lane * kForwardRun);
      acc before = run_optical_depth(s.total, lane, optical_depth);
#pragma unroll
      for (int j = 0; j < kForwardRun; ++j) {
        if (j >= s.valid) break;
        const acc w = exp_(-before) * -expm1_(-s.tau[j]);
        before += s.tau[j];
        const int64_t i = s.first + j;
        if (c0 == 0) {
          out.weights[i] = static_cast<scalar_t>(w);
          depth += w * s.midpoint(j);
        }
        const scalar_t* rgb = in.rgbs + i * C + c0;
#pragma unroll
        for (int c = 0; c < kChannelsPerPass; ++c) {
          if (c0 + c < C) color[c] += w * acc(rgb[c]);
        }
      }
    }
    const acc transmittance = exp_(-optical_depth);
    const scalar_t* bg = in.background ? in.background + ray * in.background_stride : nullptr;
#pragma unroll
    for (int c = 0; c < kChannelsPerPass; ++c) {
      const acc total = warp_sum(color[c]);
      if (lane == 0 && c0 + c < C) {
        out.color[ray * C + c0 + c] = static_cast<scalar_t>(total + (bg ? transmittance * acc(bg[c0 + c]) : acc(0)));
      }
    }
    if (c0 == 0) {
      depth = warp_sum(depth);
      if (lane == 0) {
        out.depth[ray] = static_cast<scalar_t>(depth);
        out.opacity[ray] = static_cast<scalar_t>(-expm1_(-optical_depth));
      }
    }
  }
}

// Backward of one ray by one warp; chunk_start is this warp's shared scratch, one entry per chunk.
template <typename scalar_t>
__device__ void composite_backward_ray(const CompositeInputs<scalar_t>& in, const CompositeGrads<scalar_t>& g,
                                       int64_t ray, int64_t offset, int64_t count, int lane,
                                       acc_t<scalar_t>* chunk_start) {
  using acc = acc_t<scalar_t>;
  const int64_t C = in.channels;
  const int64_t chunks = (count + kBackwardChunk - 1) / kBackwardChunk;

  acc optical_depth = 0;
  for (int64_t q = 0; q < chunks; ++q) {
    if (lane == 0) chunk_start[q] = optical_depth;
    optical_depth += warp_sum(LaneSamples<scalar_t, kBackwardRun>(in, offset, count, q * kBackwardChunk + lane * kBackwardRun).total);
  }
  __syncwarp();
  const acc transmittance_end = exp_(-optical_depth);

  const scalar_t* grad_color = g.color ? g.color + ray * C : nullptr;
  const acc grad_depth = g.depth ? acc(g.depth[ray]) : acc(0);
  // G past the last sample: the background seen with weight T_S, minus the opacity gradient.
  acc G = g.opacity ? -acc(g.opacity[ray]) : acc(0);
  if (in.background && grad_color) {
    const scalar_t* bg = in.background + ray * in.background_stride;
    for (int64_t c = 0; c < C; ++c) G += acc(grad_color[c]) * acc(bg[c]);
  }
  if (g.background_rows) {
    for (int64_t c = lane; c < C; c += kWarpSize) {
      g.background_rows[ray * C + c] = grad_color ? acc(grad_color[c]) * transmittance_end : acc(0);
    }
  }

  for (int64_t q = chunks - 1; q >= 0; --q) {
    const LaneSamples<scalar_t, kBackwardRun> s(in, offset, count, q * kBackwardChunk + lane * kBackwardRun);
    acc carry = chunk_start[q];
    acc before = run_optical_depth(s.total, lane, carry);
    acc transmittance = exp_(-before);
    acc alpha[kBackwardRun], decay[kBackwardRun], g_in[kBackwardRun], t_after[kBackwardRun];
    acc w[kBackwardRun];
#pragma unroll
    for (int j = 0; j < kBackwardRun; ++j) {
      alpha[j] = 0, decay[j] = 1, g_in[j] = 0, t_after[j] = 0, w[j] = 0;
      if (j >= s.valid) continue;
      alpha[j] = -expm1_(-s.tau[j]);
      decay[j] = exp_(-s.tau[j]);
      before += s.tau[j];
      t_after[j] = exp_(-before);
      w[j] = transmittance * alpha[j];
      transmittance = t_after[j];
      const int64_t i = s.first + j;
      g_in[j] = grad_depth * s.midpoint(j) + (g.weights ? acc(g.weights[i]) : acc(0));
      const scalar_t* rgb = in.rgbs + i * C;
      for (int64_t c = 0; c < C; ++c) {
        const acc gc = grad_color ? acc(grad_color[c]) : acc(0);
        g_in[j] += gc * acc(rgb[c]);
        g.rgbs[i * C + c] = static_cast<scalar_t>(gc * w[j]);
      }
    }
    // The run's map x -> a + b x (its samples' maps composed), then a reverse inclusive warp scan:
    // lane l ends with runs l, l+1, ..., 31 composed.
    acc a = 0, b = 1;
#pragma unroll
    for (int j = kBackwardRun - 1; j >= 0; --j) {
      a = alpha[j] * g_in[j] + decay[j] * a;
      b *= decay[j];
    }
#pragma unroll
    for (int d = 1; d < kWarpSize; d <<= 1) {
      const acc a_next = __shfl_down_sync(kFullMask, a, d);
      const acc b_next = __shfl_down_sync(kFullMask, b, d);
      if (lane + d < kWarpSize) {
        a += b * a_next;
        b *= b_next;
      }
    }
    // G after this lane's run: the later lanes' composition applied to G after the chunk.
    const acc a_later = __shfl_down_sync(kFullMask, a, 1), b_later = __shfl_down_sync(kFullMask, b, 1);
    acc G_run = lane == kWarpSize - 1 ? G : a_later + b_later * G;
    G = __shfl_sync(kFullMask, a + b * G, 0);  // G before the chunk, for the next (earlier) chunk
#pragma unroll
    for (int j = kBackwardRun - 1; j >= 0; --j) {
      if (j >= s.valid) continue;
      const acc grad_tau = t_after[j] * (g_in[j] - G_run);
      G_run = alpha[j] * g_in[j] + decay[j] * G_run;
      const int64_t i = s.first + j;
      g.sigmas[i] = static_cast<scalar_t>(grad_tau * (s.t_end[j] - s.t_start[j]));
      if (g.t_starts) {
        const acc from_depth = acc(0.5) * grad_depth * w[j];
        g.t_starts[i] = static_cast<scalar_t>(from_depth - grad_tau * s.sigma[j]);
        g.t_ends[i] = static_cast<scalar_t>(from_depth + grad_tau * s.sigma[j]);
      }
    }
  }
}

template <typename scalar_t>
__global__ void __launch_bounds__(kMaxWarpsPerBlock* kWarpSize)
    composite_fwd_kernel(CompositeInputs<scalar_t> in, CompositeOutputs<scalar_t> out, int64_t R, int64_t S) {
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + threadIdx.x / kWarpSize;
  if (ray >= R) return;  // whole warps leave together: the shuffles below see full warps
  composite_forward_ray(in, out, ray, ray * S, S, threadIdx.x % kWarpSize);
}

template <typename scalar_t>
__global__ void __launch_bounds__(kMaxWarpsPerBlock* kWarpSize)
    composite_bwd_kernel(CompositeInputs<scalar_t> in, CompositeGrads<scalar_t> g, int64_t R, int64_t S) {
  extern __shared__ unsigned char shared_bytes[];
  using acc = acc_t<scalar_t>;
  const int warp = threadIdx.x / kWarpSize;
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + warp;
  if (ray >= R) return;
  acc* chunk_start = reinterpret_cast<acc*>(shared_bytes) + warp * ((S + kBackwardChunk - 1) / kBackwardChunk);
  composite_backward_ray(in, g, ray, ray * S, S, threadIdx.x % kWarpSize, chunk_start);
}

void check_inputs(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                  const at::Tensor& t_ends, const std::optional<at::Tensor>& background) {
  MIXER_NERF_CHECK_INPUT(sigmas, at::kCUDA);
  MIXER_NERF_CHECK_INPUT(rgbs, at::kCUDA);
  MIXER_NERF_CHECK_INPUT(t_starts, at::kCUDA);
  MIXER_NERF_CHECK_INPUT(t_ends, at::kCUDA);
  TORCH_CHECK(sigmas.dim() == 2 && rgbs.dim() == 3, "composite: sigmas (R, S) and rgbs (R, S, C) expected");
  TORCH_CHECK(rgbs.size(0) == sigmas.size(0) && rgbs.size(1) == sigmas.size(1), "composite: rgbs/sigmas mismatch");
  TORCH_CHECK(t_starts.sizes() == sigmas.sizes() && t_ends.sizes() == sigmas.sizes(),
              "composite: t_starts/t_ends must match sigmas");
  if (background) {
    MIXER_NERF_CHECK_INPUT(*background, at::kCUDA);
    const bool shared = background->dim() == 1 && background->size(0) == rgbs.size(2);
    const bool per_ray = background->dim() == 2 && background->size(0) == rgbs.size(0) &&
                         background->size(1) == rgbs.size(2);
    TORCH_CHECK(shared || per_ray, "composite: background must be (C) or (R, C)");
  }
}

template <typename scalar_t>
CompositeInputs<scalar_t> inputs_of(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                                    const at::Tensor& t_ends, const std::optional<at::Tensor>& background) {
  const bool per_ray = background && background->dim() == 2;
  return {sigmas.const_data_ptr<scalar_t>(),
          rgbs.const_data_ptr<scalar_t>(),
          t_starts.const_data_ptr<scalar_t>(),
          t_ends.const_data_ptr<scalar_t>(),
          background ? background->const_data_ptr<scalar_t>() : nullptr,
          per_ray ? rgbs.size(2) : 0,
          rgbs.size(2)};
}

unsigned blocks_for(int64_t R, int warps_per_block) {
  const int64_t blocks = (R + warps_per_block - 1) / warps_per_block;
  TORCH_CHECK(blocks <= int64_t(INT32_MAX), "composite: too many rays for one launch");
  return static_cast<unsigned>(blocks);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> composite_fwd_cuda(
    const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts, const at::Tensor& t_ends,
    const std::optional<at::Tensor>& background) {
  check_inputs(sigmas, rgbs, t_starts, t_ends, background);
  const c10::cuda::CUDAGuard device_guard(sigmas.device());
  const int64_t R = sigmas.size(0), S = sigmas.size(1), C = rgbs.size(2);
  at::Tensor color = at::empty({R, C}, sigmas.options());
  at::Tensor depth = at::empty({R}, sigmas.options());
  at::Tensor opacity = at::empty({R}, sigmas.options());
  at::Tensor weights = at::empty({R, S}, sigmas.options());
  if (R == 0) return {color, depth, opacity, weights};
  MIXER_NERF_DISPATCH_FLOATING(sigmas.scalar_type(), "composite_fwd_cuda", [&] {
    const CompositeOutputs<scalar_t> out{color.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                                         opacity.data_ptr<scalar_t>(), weights.data_ptr<scalar_t>()};
    composite_fwd_kernel<scalar_t>
        <<<blocks_for(R, kMaxWarpsPerBlock), kMaxWarpsPerBlock * kWarpSize, 0, c10::cuda::getCurrentCUDAStream()>>>(
            inputs_of<scalar_t>(sigmas, rgbs, t_starts, t_ends, background), out, R, S);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {color, depth, opacity, weights};
}

const void* data_or_null(const std::optional<at::Tensor>& t) { return t ? t->const_data_ptr() : nullptr; }

std::tuple<at::Tensor, at::Tensor, std::optional<at::Tensor>, std::optional<at::Tensor>, std::optional<at::Tensor>>
composite_bwd_cuda(const std::optional<at::Tensor>& grad_color, const std::optional<at::Tensor>& grad_depth,
                   const std::optional<at::Tensor>& grad_opacity, const std::optional<at::Tensor>& grad_weights,
                   const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                   const at::Tensor& t_ends, const std::optional<at::Tensor>& background, bool interval_grads) {
  check_inputs(sigmas, rgbs, t_starts, t_ends, background);
  const c10::cuda::CUDAGuard device_guard(sigmas.device());
  const int64_t R = sigmas.size(0), S = sigmas.size(1), C = rgbs.size(2);
  for (const auto* grad : {&grad_color, &grad_depth, &grad_opacity, &grad_weights}) {
    if (*grad) {
      const at::Tensor& upstream = **grad;
      MIXER_NERF_CHECK_INPUT(upstream, at::kCUDA);
      TORCH_CHECK(upstream.scalar_type() == sigmas.scalar_type(), "composite_bwd: gradient dtype mismatch");
    }
  }
  TORCH_CHECK(!grad_color || grad_color->sizes() == at::IntArrayRef({R, C}), "grad_color must be (R, C)");
  TORCH_CHECK(!grad_depth || grad_depth->sizes() == at::IntArrayRef({R}), "grad_depth must be (R)");
  TORCH_CHECK(!grad_opacity || grad_opacity->sizes() == at::IntArrayRef({R}), "grad_opacity must be (R)");
  TORCH_CHECK(!grad_weights || grad_weights->sizes() == sigmas.sizes(), "grad_weights must be (R, S)");

  at::Tensor grad_sigmas = at::empty_like(sigmas);
  at::Tensor grad_rgbs = at::empty_like(rgbs);
  std::optional<at::Tensor> grad_t_starts, grad_t_ends, grad_background;
  if (interval_grads) {
    grad_t_starts = at::empty_like(t_starts);
    grad_t_ends = at::empty_like(t_ends);
  }
  const at::ScalarType acc_type = at::toOpMathType(sigmas.scalar_type());
  at::Tensor background_rows;
  if (background) background_rows = at::empty({R, C}, sigmas.options().dtype(acc_type));

  if (R > 0) {
    MIXER_NERF_DISPATCH_FLOATING(sigmas.scalar_type(), "composite_bwd_cuda", [&] {
      using acc = acc_t<scalar_t>;
          const size_t per_warp = size_t((S + kBackwardChunk - 1) / kBackwardChunk) * sizeof(acc);
      const int warps = static_cast<int>(std::min<size_t>(kMaxWarpsPerBlock, kSharedBytes / std::max<size_t>(per_warp, 1)));
      TORCH_CHECK(warps >= 1, "composite_bwd: S = ", S, " samples per ray exceeds the CUDA kernel's limit of ",
                  kSharedBytes / sizeof(acc) * kBackwardChunk);
      const CompositeGrads<scalar_t> g{
          static_cast<const scalar_t*>(data_or_null(grad_color)),
          static_cast<const scalar_t*>(data_or_null(grad_depth)),
          static_cast<const scalar_t*>(data_or_null(grad_opacity)),
          static_cast<const scalar_t*>(data_or_null(grad_weights)),
          grad_sigmas.data_ptr<scalar_t>(),
          grad_rgbs.data_ptr<scalar_t>(),
          interval_grads ? grad_t_starts->data_ptr<scalar_t>() : nullptr,
          interval_grads ? grad_t_ends->data_ptr<scalar_t>() : nullptr,
          background ? background_rows.data_ptr<acc>() : nullptr};
      composite_bwd_kernel<scalar_t>
          <<<blocks_for(R, warps), warps * kWarpSize, warps * per_warp, c10::cuda::getCurrentCUDAStream()>>>(
              inputs_of<scalar_t>(sigmas, rgbs, t_starts, t_ends, background), g, R, S);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  }
  if (background) {
    grad_background = (background->dim() == 1 ? background_rows.sum(0) : background_rows).to(sigmas.scalar_type());
  }
  return {grad_sigmas, grad_rgbs, grad_t_starts, grad_t_ends, grad_background};
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) {
  m.impl("composite_fwd", &composite_fwd_cuda);
  m.impl("composite_bwd", &composite_bwd_cuda);
}

}  // namespace mixer_nerf
