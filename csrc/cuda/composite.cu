// composite and composite_packed (volume rendering) on CUDA: one warp per ray, in either layout
// (a ray is a span of samples, ray_layout.h). A ray's samples go in chunks of
// 32 runs, each lane holding a run of consecutive samples (the warp's loads cover
// contiguous memory; per-lane sums over a run replace shuffles). The math and its numerics are
// those of csrc/composite.cpp (read its file comment first):
//   forward:  T_i = exp(-(carry + exclusive scan of tau)), w_i = T_i * -expm1(-tau_i);
//   backward: G_j = alpha_j g_j + exp(-tau_j) G_{j+1} is an affine recurrence, evaluated from
//             the last chunk to the first as a reverse warp scan of affine maps x -> a + b x;
//             dL/dtau_j = T_{j+1} (g_j - G_{j+1}).
// The backward needs the optical depth at the start of every chunk while walking chunks in
// reverse; subtracting sums would cancel after a 1e10-long interval, so a first forward pass
// keeps one value per chunk but the last in global scratch (a ray of <= 32 samples skips that
// pass; packed rays are mostly that short). No atomics.
//
// Like the CPU kernel, both passes compute in double for every input dtype (ray_acc) and round
// each output once: G starts at O(1) and is multiplied S times by exp(-tau_j), which rounds to 1
// in float32 in fog, so a float32 G would hold ~S ulps that g_j - G_{j+1} keeps where it is small
// (thin-media sigma gradients; docs/numerics.md, "Precision and accumulation"). Float32 results
// within half an ulp of the float64 truth (the error budget's rows) need every quantity to
// ~2^-32 before that rounding: float32 math (tau rounded, expf's 1-2 ulps) gives 1-3 ulps, and
// float-float would cost ~6-10 FP32 instructions an operation where a DFMA costs two (sm_90 has
// half as many FP64 lanes as FP32), in the registers of a double. So the arithmetic stays double.
// What changed is the transcendentals: libm's double exp/expm1 (special-case branches, integer
// range reduction: the backward was instruction-bound on them) are, for non-double inputs, one
// branch-free polynomial giving exp(-x) and -expm1(-x) together (neg_exp.cuh, ~2^-47 relative
// error, 2^-23 below a float32 ulp); float64 inputs keep libm. Per sample one such evaluation
// gives alpha_i and exp(-tau_i); T at the start of a lane's run is exp(-optical depth), never a
// long product, and T past a sample is that times exp(-tau_i) (at most kForwardRun products,
// each within an ulp of double; the same for float64 inputs). exp(-tau) is exact for thin
// samples (1 - alpha to double precision) and exactly 0 for tau = 1e18.
// The doubles cost FP64 math, not memory traffic (benchmarks/results/ops/).
#include <torch/library.h>

#include <ATen/ATen.h>
#include <c10/cuda/CUDAStream.h>  // = at::cuda::getCurrentCUDAStream, without the cuSPARSE/cuBLAS headers
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>

#include <optional>
#include <tuple>
#include <type_traits>

#include "common.h"
#include "composite.h"
#include "neg_exp.cuh"
#include "warp.cuh"

namespace mixer_nerf {
namespace {

constexpr int kMaxWarpsPerBlock = 8;
constexpr int kChannelsPerPass = 4;  // colour accumulators held in registers per forward pass
// A warp takes a ray in chunks of up to kChunk samples, each lane a run of ceil(n / 32) <= kMaxRun
// consecutive ones of a chunk of n: one scan per chunk, so a ray of <= 256 samples (every ray of
// the default samplers) costs two warp scans in either pass instead of two per 32 or 64 samples,
// which bounded both kernels by shuffle latency.
constexpr int kMaxRun = 8;
constexpr int kChunk = kWarpSize * kMaxRun;

using ray_acc = double;  // what both passes compute in (see the file comment)

// exp(-x) and alpha = -expm1(-x) of an optical thickness or depth x: libm for float64 inputs
// (gradcheck's), else neg_exp.cuh's polynomial, within ~2^-47 of them (see the file comment).
template <typename scalar_t>
__device__ __forceinline__ NegExp neg_exp(ray_acc x) {
  if constexpr (std::is_same_v<scalar_t, double>) {
    return {exp(-x), -expm1(-x)};
  } else {
    return neg_exp_poly(x);
  }
}

// A lane's run in the chunk of a ray's samples from `base`: samples [first, first + valid).
struct LaneRun {
  int64_t first;
  int valid;
};

__device__ __forceinline__ LaneRun lane_run(int64_t offset, int64_t count, int64_t base, int lane) {
  const int64_t n = count - base < kChunk ? count - base : kChunk;
  const int run = static_cast<int>((n + kWarpSize - 1) / kWarpSize);
  const int64_t start = int64_t(lane) * run;
  return {offset + base + start, static_cast<int>(start >= n ? 0 : (n - start < run ? n - start : run))};
}

// One sample's inputs and optical thickness (exact for float inputs: a double holds the product of
// two floats).
template <typename scalar_t>
struct Sample {
  using acc = acc_t<scalar_t>;
  acc sigma, t_start, t_end;
  ray_acc tau;
  __device__ __forceinline__ Sample(const CompositeInputs<scalar_t>& in, int64_t i)
      : sigma(in.sigmas[i]), t_start(in.t_starts[i]), t_end(in.t_ends[i]),
        tau(ray_acc(sigma) * (ray_acc(t_end) - ray_acc(t_start))) {}
  __device__ ray_acc length() const { return ray_acc(t_end) - ray_acc(t_start); }
  __device__ ray_acc midpoint() const { return ray_acc(0.5) * (ray_acc(t_start) + ray_acc(t_end)); }
};

// Sum of tau over a lane's run; ORs the InvalidInput bits of its samples into *invalid if given.
template <typename scalar_t>
__device__ ray_acc run_optical_thickness(const CompositeInputs<scalar_t>& in, LaneRun run, int32_t* invalid) {
  ray_acc total = 0;
  for (int j = 0; j < run.valid; ++j) {
    const Sample<scalar_t> s(in, run.first + j);
    total += s.tau;
    if (invalid) *invalid |= invalid_sample_bits(s.sigma, s.t_start, s.t_end);
  }
  return total;
}

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

// Forward of one ray by one warp: samples [offset, offset + count). Returns the InvalidInput
// bits of the lane's samples. A lane reads its run twice (its optical thickness, then the
// weights; the second read hits L1). Channels beyond kChannelsPerPass take further passes
// (re-reading sigma/t beats spilling).
template <typename scalar_t>
__device__ int32_t composite_forward_ray(const CompositeInputs<scalar_t>& in, const CompositeOutputs<scalar_t>& out,
                                         int64_t ray, int64_t offset, int64_t count, int lane) {
  const int64_t C = in.channels;
  int32_t invalid = 0;
  for (int64_t c0 = 0; c0 == 0 || c0 < C; c0 += kChannelsPerPass) {
    ray_acc color[kChannelsPerPass] = {};
    ray_acc depth = 0, optical_depth = 0;
    for (int64_t base = 0; base < count; base += kChunk) {
      const LaneRun run = lane_run(offset, count, base, lane);
      const ray_acc thickness = run_optical_thickness(in, run, c0 == 0 ? &invalid : nullptr);
      ray_acc transmittance = neg_exp<scalar_t>(run_optical_depth(thickness, lane, optical_depth)).exp;
      for (int j = 0; j < run.valid; ++j) {
        const int64_t i = run.first + j;
        const Sample<scalar_t> s(in, i);
        const NegExp sample = neg_exp<scalar_t>(s.tau);
        const ray_acc w = transmittance * sample.alpha;
        transmittance *= sample.exp;  // <= kMaxRun products within a run: see the file comment
        if (c0 == 0) {
          out.weights[i] = static_cast<scalar_t>(w);
          depth += w * s.midpoint();
        }
        const scalar_t* rgb = in.rgbs + i * C + c0;
#pragma unroll
        for (int c = 0; c < kChannelsPerPass; ++c) {
          if (c0 + c < C) color[c] += w * ray_acc(rgb[c]);
        }
      }
    }
    const NegExp ray_end = neg_exp<scalar_t>(optical_depth);
    const scalar_t* bg = in.background ? in.background + ray * in.background_stride : nullptr;
#pragma unroll
    for (int c = 0; c < kChannelsPerPass; ++c) {
      const ray_acc total = warp_sum(color[c]);
      if (lane == 0 && c0 + c < C) {
        out.color[ray * C + c0 + c] =
            static_cast<scalar_t>(total + (bg ? ray_end.exp * ray_acc(bg[c0 + c]) : ray_acc(0)));
      }
    }
    if (c0 == 0) {
      depth = warp_sum(depth);
      if (lane == 0) {
        out.depth[ray] = static_cast<scalar_t>(depth);
        out.opacity[ray] = static_cast<scalar_t>(ray_end.alpha);
      }
    }
  }
  return invalid;
}

// What the backward keeps of a sample between its forward and reverse walks over a lane's run:
// T before the sample and g (the weight's total upstream gradient). Laid out [run index][lane] in
// shared memory (conflict-free); alpha and exp(-tau) are recomputed instead (one neg_exp).
struct Kept {
  ray_acc transmittance, g;
};
using WarpStash = Kept[kMaxRun][kWarpSize];

// Backward of one ray by one warp; chunk_start is this ray's scratch, one entry per chunk but the
// last. Per chunk: each lane walks its run forward (T, w, g, the colour gradients, and the run's
// map G_after -> G_before composed), a reverse warp scan composes the later runs' maps, then each
// lane walks its run backward from G after the run, writing the sigma and t gradients.
template <typename scalar_t>
__device__ void composite_backward_ray(const CompositeInputs<scalar_t>& in, const CompositeGrads<scalar_t>& g,
                                       int64_t ray, int64_t offset, int64_t count, int lane,
                                       ray_acc* chunk_start, WarpStash& stash) {
  using acc = acc_t<scalar_t>;
  const int64_t C = in.channels;
  const int64_t chunks = (count + kChunk - 1) / kChunk;

  // Optical depth before every chunk but the last; the reverse pass below starts there and
  // finds the total (hence T past the last sample) itself.
  ray_acc optical_depth = 0;
  for (int64_t q = 0; q + 1 < chunks; ++q) {
    if (lane == 0) chunk_start[q] = optical_depth;
    optical_depth += warp_sum(run_optical_thickness(in, lane_run(offset, count, q * kChunk, lane), nullptr));
  }
  __syncwarp();  // orders lane 0's scratch writes before every lane's reads
  ray_acc total_optical_depth = optical_depth;  // final once the last chunk is added below

  const scalar_t* grad_color = g.color ? g.color + ray * C : nullptr;
  const ray_acc grad_depth = g.depth ? ray_acc(g.depth[ray]) : ray_acc(0);
  // G past the last sample: the background seen with weight T_S, minus the opacity gradient.
  ray_acc G = g.opacity ? -ray_acc(g.opacity[ray]) : ray_acc(0);
  if (in.background && grad_color) {
    const scalar_t* bg = in.background + ray * in.background_stride;
    for (int64_t c = 0; c < C; ++c) G += ray_acc(grad_color[c]) * ray_acc(bg[c]);
  }

  for (int64_t q = chunks - 1; q >= 0; --q) {
    const LaneRun run = lane_run(offset, count, q * kChunk, lane);
    const bool last = q == chunks - 1;
    ray_acc carry = last ? optical_depth : chunk_start[q];
    ray_acc transmittance =
        neg_exp<scalar_t>(run_optical_depth(run_optical_thickness(in, run, nullptr), lane, carry)).exp;
    if (last) total_optical_depth = carry;
    // The run's map x -> a + b x: sample j's G_j = alpha_j g_j + exp(-tau_j) G_{j+1}, composed first to last.
    ray_acc a = 0, b = 1;
    for (int j = 0; j < run.valid; ++j) {
      const int64_t i = run.first + j;
      const Sample<scalar_t> s(in, i);
      const NegExp sample = neg_exp<scalar_t>(s.tau);
      const ray_acc w = transmittance * sample.alpha;
      ray_acc g_in = grad_depth * s.midpoint() + (g.weights ? ray_acc(g.weights[i]) : ray_acc(0));
      const scalar_t* rgb = in.rgbs + i * C;
      for (int64_t c = 0; c < C; ++c) {
        const ray_acc gc = grad_color ? ray_acc(grad_color[c]) : ray_acc(0);
        g_in += gc * ray_acc(rgb[c]);
        g.rgbs[i * C + c] = static_cast<scalar_t>(gc * w);
      }
      stash[j][lane] = {transmittance, g_in};
      a += b * (sample.alpha * g_in);
      b *= sample.exp;
      transmittance *= sample.exp;  // a product, not exp(-(before + tau)): see the file comment
    }
    // Reverse inclusive warp scan: lane l ends with runs l, l+1, ..., 31 composed.
#pragma unroll
    for (int d = 1; d < kWarpSize; d <<= 1) {
      const ray_acc a_next = __shfl_down_sync(kFullMask, a, d);
      const ray_acc b_next = __shfl_down_sync(kFullMask, b, d);
      if (lane + d < kWarpSize) {
        a += b * a_next;
        b *= b_next;
      }
    }
    // G after this lane's run: the later lanes' composition applied to G after the chunk.
    const ray_acc a_later = __shfl_down_sync(kFullMask, a, 1), b_later = __shfl_down_sync(kFullMask, b, 1);
    ray_acc G_run = lane == kWarpSize - 1 ? G : a_later + b_later * G;
    G = __shfl_sync(kFullMask, a + b * G, 0);  // G before the chunk, for the next (earlier) chunk
    for (int j = run.valid - 1; j >= 0; --j) {
      const int64_t i = run.first + j;
      const Sample<scalar_t> s(in, i);
      const NegExp sample = neg_exp<scalar_t>(s.tau);
      const Kept kept = stash[j][lane];
      const ray_acc grad_tau = kept.transmittance * sample.exp * (kept.g - G_run);
      G_run = sample.alpha * kept.g + sample.exp * G_run;
      g.sigmas[i] = static_cast<scalar_t>(grad_tau * s.length());
      if (g.t_starts) {
        const ray_acc from_depth = ray_acc(0.5) * grad_depth * kept.transmittance * sample.alpha;
        g.t_starts[i] = static_cast<scalar_t>(from_depth - grad_tau * ray_acc(s.sigma));
        g.t_ends[i] = static_cast<scalar_t>(from_depth + grad_tau * ray_acc(s.sigma));
      }
    }
  }
  if (g.background_rows) {
    const ray_acc transmittance_end = neg_exp<scalar_t>(total_optical_depth).exp;
    for (int64_t c = lane; c < C; c += kWarpSize) {
      g.background_rows[ray * C + c] = static_cast<acc>(grad_color ? ray_acc(grad_color[c]) * transmittance_end : ray_acc(0));
    }
  }
}

template <typename scalar_t, typename Rays>
// 4 blocks per SM: 64 registers (80 without the bound capped occupancy at 3 blocks, and the
// forward is latency-bound), at the cost of <= 48 bytes of spills.
__global__ void __launch_bounds__(kMaxWarpsPerBlock* kWarpSize, 4)
    composite_fwd_kernel(CompositeInputs<scalar_t> in, CompositeOutputs<scalar_t> out, int64_t R, Rays rays) {
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + threadIdx.x / kWarpSize;
  if (ray >= R) return;  // whole warps leave together: the shuffles below see full warps
  const composite_layout::RaySpan span = rays(ray);
  const int lane = threadIdx.x % kWarpSize;
  int32_t invalid = composite_forward_ray(in, out, ray, span.offset, span.count, lane);
  if (lane == 0 && !rays.well_formed(ray, R)) invalid |= kBadOffsets;
  if (invalid) atomicOr(out.invalid, invalid);  // only for bad input: no contention otherwise
}

// Scratch of the backward: ray r's chunk starts from span.offset / kChunk + r. A ray of
// `count` samples from `offset` needs at most ceil(count / kChunk) entries, and the next
// ray's first entry is at least floor(count / kChunk) + 1 further on, so rays never
// overlap and N / kChunk + R entries hold them all.
int64_t scratch_entries(int64_t N, int64_t R) { return N / kChunk + R; }

template <typename scalar_t, typename Rays>
__global__ void __launch_bounds__(kMaxWarpsPerBlock* kWarpSize)
    composite_bwd_kernel(CompositeInputs<scalar_t> in, CompositeGrads<scalar_t> g, int64_t R, Rays rays,
                         ray_acc* scratch) {
  __shared__ WarpStash stash[kMaxWarpsPerBlock];
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + threadIdx.x / kWarpSize;
  if (ray >= R) return;
  const composite_layout::RaySpan span = rays(ray);
  composite_backward_ray(in, g, ray, span.offset, span.count, threadIdx.x % kWarpSize,
                         scratch + span.offset / kChunk + ray, stash[threadIdx.x / kWarpSize]);
}

unsigned blocks_for(int64_t R) {
  const int64_t blocks = (R + kMaxWarpsPerBlock - 1) / kMaxWarpsPerBlock;
  MIXER_NERF_CHECK(blocks <= int64_t(INT32_MAX), "composite: too many rays for one launch");
  return static_cast<unsigned>(blocks);
}

// The composite ops' CUDA kernels, for CompositeOps (composite.h).
struct Cuda {
  static constexpr at::DeviceType kind = at::kCUDA;

  template <typename Rays>
  static CompositeForward forward(const CompositeTensors& tensors, int64_t R, Rays rays) {
    const c10::cuda::CUDAGuard device_guard(tensors.sigmas.device());
    auto outputs = empty_outputs(tensors.sigmas, tensors.rgbs, R);
    if (R == 0) return outputs;
    MIXER_NERF_DISPATCH_FLOATING(tensors.sigmas.scalar_type(), "composite_fwd_cuda", [&] {
      const auto out = outputs_of<scalar_t>(outputs);
      composite_fwd_kernel<scalar_t><<<blocks_for(R), kMaxWarpsPerBlock * kWarpSize, 0,
                                       c10::cuda::getCurrentCUDAStream()>>>(
          tensors.pointers<scalar_t>(), out, R, rays);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
    return outputs;
  }

  template <typename Rays>
  static void backward(const Upstream& up, const CompositeTensors& tensors, CompositeGradTensors& grads, int64_t R,
                       Rays rays) {
    if (R == 0) return;
    const at::Tensor& sigmas = tensors.sigmas;
    const c10::cuda::CUDAGuard device_guard(sigmas.device());
    const at::Tensor scratch = at::empty({scratch_entries(sigmas.numel(), R)}, sigmas.options().dtype(at::kDouble));
    MIXER_NERF_DISPATCH_FLOATING(sigmas.scalar_type(), "composite_bwd_cuda", [&] {
      composite_bwd_kernel<scalar_t><<<blocks_for(R), kMaxWarpsPerBlock * kWarpSize, 0,
                                       c10::cuda::getCurrentCUDAStream()>>>(
          tensors.pointers<scalar_t>(), grads.pointers<scalar_t>(up), R, rays, scratch.data_ptr<ray_acc>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  }
};

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) { CompositeOps<Cuda>::register_ops(m); }

}  // namespace mixer_nerf
