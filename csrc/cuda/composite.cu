// composite and composite_packed (volume rendering) on CUDA: one warp per ray, in either layout
// (a ray is a span of samples, ray_layout.h). A ray's samples go in chunks of
// 32 runs, each lane holding a run of consecutive samples (the warp's loads cover
// contiguous memory; per-lane sums over a run replace shuffles). The quantities are those of
// csrc/composite.cpp (read its file comment first), in forms that suit a warp's scans:
//   forward:  T_i = carry * exclusive product scan of exp(-tau), w_i = T_i * -expm1(-tau_i),
//             opacity = -expm1(-sum of tau) (not 1 - T: exact for thin rays);
//   backward: dL/dtau_j = T_{j+1} g_j - S_{j+1}, S_{j+1} = sum_{k>j} w_k g_k + T_S G_end, a
//             suffix sum evaluated from the last chunk to the first as a reverse warp scan.
//             The CPU kernel's affine recurrence G_j = alpha_j g_j + exp(-tau_j) G_{j+1} (with
//             T_{j+1} G_{j+1} = S_{j+1}) is the same quantity; in double both round to the same
//             float32 gradients on every error-budget distribution, and a scan step here moves
//             one double where the affine maps' composition moves two.
// The backward needs T at the start of every chunk while walking chunks in reverse; dividing
// would fail where T underflows, so the forward, which finds T there anyway, writes one per
// backward chunk (the op's chunk_transmittances output, saved for the backward: a
// second pass over sigma and t would cost the backward a sixth of its instructions). No atomics.
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
// gives alpha_i and exp(-tau_i), and T is a product of exp(-tau) (scans of products, one per chunk,
// in place of an exp of the optical depth per lane): each factor is within 2^-47 of the truth, so
// T_i is within i * 2^-47 (2^-39 at i = 192, 2^-34 at 8192), far below a float32 ulp (2^-24) and
// exactly 0 past a sample with tau >= 708. Not float32's classic prod(1 - alpha + 1e-10): every
// factor is exp(-tau) itself, in double, exact for thin samples (1 - alpha to double precision).
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
// Consecutive samples per lane (a run). Longer runs mean fewer shuffles per sample; measured on
// an H100 at R=65536, S=192: forward 157 us with runs of 2 vs 177 us with 1; the backward, with
// more live values per sample, is fastest with 1 (269 us vs 367 us with 2).
constexpr int kForwardRun = 2;
constexpr int kBackwardRun = 1;
constexpr int kForwardChunk = kWarpSize * kForwardRun;
constexpr int kBackwardChunk = kWarpSize * kBackwardRun;

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

// How many of a run of K samples from sample k of a ray of `count` lie in the ray.
template <int K>
__device__ __forceinline__ int valid_in_run(int64_t count, int64_t k) {
  return static_cast<int>(k >= count ? 0 : (count - k < K ? count - k : K));
}

// A lane's run of K consecutive samples of a chunk. Samples past the ray's end hold
// an empty interval (tau = 0, g = 0), the identity of both scans.
template <typename scalar_t, int K>
struct LaneSamples {
  using acc = acc_t<scalar_t>;
  int64_t first;  // index of the run's first sample
  int valid;      // how many of the run's samples are in the ray
  acc sigma[K] = {}, t_start[K] = {}, t_end[K] = {};
  ray_acc tau[K] = {};  // exact for float inputs: a double holds the product of two floats
  ray_acc total = 0;    // sum of tau over the run
  __device__ LaneSamples(const CompositeInputs<scalar_t>& in, int64_t offset, int64_t count, int64_t k)
      : first(offset + k), valid(valid_in_run<K>(count, k)) {
#pragma unroll
    for (int j = 0; j < K; ++j) {
      if (j < valid) {
        sigma[j] = in.sigmas[first + j];
        t_start[j] = in.t_starts[first + j];
        t_end[j] = in.t_ends[first + j];
      }
    }
    sum_optical_thickness();
  }
  // From values loaded earlier (zeros past the ray's end), e.g. a chunk ahead.
  __device__ LaneSamples(int64_t offset, int64_t count, int64_t k, const acc (&sigma_)[K], const acc (&t_start_)[K],
                         const acc (&t_end_)[K])
      : first(offset + k), valid(valid_in_run<K>(count, k)) {
#pragma unroll
    for (int j = 0; j < K; ++j) sigma[j] = sigma_[j], t_start[j] = t_start_[j], t_end[j] = t_end_[j];
    sum_optical_thickness();
  }
  __device__ void sum_optical_thickness() {
#pragma unroll
    for (int j = 0; j < K; ++j) {
      if (j < valid) {
        tau[j] = ray_acc(sigma[j]) * (ray_acc(t_end[j]) - ray_acc(t_start[j]));
        total += tau[j];
      }
    }
  }
  // exp(-tau) and alpha of each sample into `sample` (past the ray's end: 1 and 0); returns the
  // product of exp(-tau) over the run.
  __device__ ray_acc neg_exps(NegExp (&sample)[K]) const {
    ray_acc run_decay = 1;
#pragma unroll
    for (int j = 0; j < K; ++j) {
      sample[j] = j < valid ? neg_exp<scalar_t>(tau[j]) : NegExp{1, 0};
      run_decay *= sample[j].exp;
    }
    return run_decay;
  }
  __device__ ray_acc midpoint(int j) const { return ray_acc(0.5) * (ray_acc(t_start[j]) + ray_acc(t_end[j])); }
  __device__ int32_t invalid_bits() const {
    int32_t bits = 0;
#pragma unroll
    for (int j = 0; j < K; ++j) {
      if (j < valid) bits |= invalid_sample_bits(sigma[j], t_start[j], t_end[j]);
    }
    return bits;
  }
};

// T before a lane's run given T before the chunk (`carry`) and the run's product of exp(-tau);
// advances carry past the chunk. Exclusive by shuffling the inclusive product scan up a lane.
__device__ __forceinline__ ray_acc run_transmittance(ray_acc run_decay, int lane, ray_acc& carry) {
  const ray_acc inclusive = warp_inclusive_scan(run_decay, lane, Times{});
  const ray_acc exclusive = __shfl_up_sync(kFullMask, inclusive, 1);
  const ray_acc before = carry * (lane == 0 ? ray_acc(1) : exclusive);
  carry *= __shfl_sync(kFullMask, inclusive, kWarpSize - 1);
  return before;
}

static_assert(kBackwardChunk % kForwardRun == 0, "a backward chunk starts at some lane's run");

// Forward of one ray by one warp: samples [offset, offset + count); chunk_start is this ray's
// entries of chunk_transmittances. Returns the InvalidInput bits of the lane's samples. Channels
// beyond kChannelsPerPass take further passes (re-reading sigma/t beats spilling).
template <typename scalar_t, int kC>  // kC: as composite_backward_ray's
__device__ int32_t composite_forward_ray(const CompositeInputs<scalar_t>& in, const CompositeOutputs<scalar_t>& out,
                                         int64_t ray, int64_t offset, int64_t count, int lane,
                                         ray_acc* chunk_start) {
  static_assert(kC <= kChannelsPerPass, "a compiled channel count takes one pass");
  const int64_t C = kC > 0 ? kC : in.channels;
  int32_t invalid = 0;
  for (int64_t c0 = 0; c0 == 0 || c0 < C; c0 += kChannelsPerPass) {
    ray_acc color[kChannelsPerPass] = {};
    ray_acc depth = 0;
    ray_acc lane_optical_depth = 0;  // over the lane's runs: summed over the warp for the opacity
    ray_acc transmittance_before_chunk = 1;
    for (int64_t base = 0; base < count; base += kForwardChunk) {
      const int64_t k = base + lane * kForwardRun;
      const LaneSamples<scalar_t, kForwardRun> s(in, offset, count, k);
      // The run's colours, read before the scan: below the stores of the weights and chunk_start
      // the compiler must keep them (it cannot tell the arrays apart), and the warp waited on them.
      acc_t<scalar_t> run_rgb[kForwardRun][kC > 0 ? kC : 1] = {};
      if constexpr (kC > 0) {
#pragma unroll
        for (int j = 0; j < kForwardRun; ++j) {
          if (j >= s.valid) continue;
#pragma unroll
          for (int c = 0; c < kC; ++c) run_rgb[j][c] = in.rgbs[(s.first + j) * kC + c];
        }
      }
      NegExp sample[kForwardRun];
      const ray_acc run_decay = s.neg_exps(sample);
      lane_optical_depth += s.total;
      ray_acc transmittance = run_transmittance(run_decay, lane, transmittance_before_chunk);
      if (c0 == 0) {
        invalid |= s.invalid_bits();
        if (k % kBackwardChunk == 0 && k < count) chunk_start[k / kBackwardChunk] = transmittance;
      }
#pragma unroll
      for (int j = 0; j < kForwardRun; ++j) {
        if (j >= s.valid) break;
        const ray_acc w = transmittance * sample[j].alpha;
        transmittance *= sample[j].exp;
        const int64_t i = s.first + j;
        if (c0 == 0) {
          out.weights[i] = static_cast<scalar_t>(w);
          depth += w * s.midpoint(j);
        }
        if constexpr (kC > 0) {
#pragma unroll
          for (int c = 0; c < kC; ++c) color[c] += w * ray_acc(run_rgb[j][c]);
        } else {
          const scalar_t* rgb = in.rgbs + i * C + c0;
#pragma unroll
          for (int c = 0; c < kChannelsPerPass; ++c) {
            if (c0 + c < C) color[c] += w * ray_acc(rgb[c]);
          }
        }
      }
    }
    const NegExp ray_end = neg_exp<scalar_t>(warp_sum(lane_optical_depth));
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

// What the backward reads of one chunk's samples (a lane's run; zeros past the ray's end) and the
// transmittance before the chunk. Loaded a chunk ahead of its use: the backward stalls mostly on
// these loads (ncu: L1TEX scoreboard waits are half its cycles between instructions). Colours only
// where the channel count is compiled in (kC > 0); other counts read them as they go.
template <typename scalar_t, int kC, int K>
struct ChunkLoads {
  using acc = acc_t<scalar_t>;
  acc sigma[K] = {}, t_start[K] = {}, t_end[K] = {}, weight_grad[K] = {};
  acc rgb[K][kC > 0 ? kC : 1] = {};
  ray_acc transmittance_before = 0;
  ChunkLoads() = default;
  __device__ ChunkLoads(const CompositeInputs<scalar_t>& in, const CompositeGrads<scalar_t>& g, int64_t offset,
                        int64_t count, int64_t q, int lane, const ray_acc* chunk_start) {
    const int64_t k = q * kWarpSize * K + lane * K;
    const int valid = valid_in_run<K>(count, k);
    transmittance_before = chunk_start[q];
#pragma unroll
    for (int j = 0; j < K; ++j) {
      if (j >= valid) continue;
      const int64_t i = offset + k + j;
      sigma[j] = in.sigmas[i];
      t_start[j] = in.t_starts[i];
      t_end[j] = in.t_ends[i];
      if (g.weights) weight_grad[j] = g.weights[i];
#pragma unroll
      for (int c = 0; c < kC; ++c) rgb[j][c] = in.rgbs[i * kC + c];
    }
  }
};

// Backward of one ray by one warp; chunk_start holds the transmittance before each chunk (the forward's).

// kC: the channel count compiled in (its loops unrolled, the colour gradient held in registers), or
// 0 for any count, read from the inputs.
template <typename scalar_t, int kC>
__device__ void composite_backward_ray(const CompositeInputs<scalar_t>& in, const CompositeGrads<scalar_t>& g,
                                       int64_t ray, int64_t offset, int64_t count, int lane,
                                       const ray_acc* chunk_start) {
  using acc = acc_t<scalar_t>;
  const int64_t C = kC > 0 ? kC : in.channels;
  const int64_t chunks = (count + kBackwardChunk - 1) / kBackwardChunk;

  const scalar_t* grad_color = g.color ? g.color + ray * C : nullptr;
  const ray_acc grad_depth = g.depth ? ray_acc(g.depth[ray]) : ray_acc(0);
  const bool t_grads = g.t_starts != nullptr;
  ray_acc color_grad[kC > 0 ? kC : 1];
#pragma unroll
  for (int c = 0; c < kC; ++c) color_grad[c] = grad_color ? ray_acc(grad_color[c]) : ray_acc(0);
  // G past the last sample: the background seen with weight T_S, minus the opacity gradient.
  ray_acc G_end = g.opacity ? -ray_acc(g.opacity[ray]) : ray_acc(0);
  if (in.background && grad_color) {
    const scalar_t* bg = in.background + ray * in.background_stride;
    for (int64_t c = 0; c < C; ++c) G_end += ray_acc(grad_color[c]) * ray_acc(bg[c]);
  }
  ray_acc transmittance_end = 1;  // T_S: 1 for a ray without samples, else found with the last chunk
  ray_acc after_chunk = 0;        // S past the chunk: sum of w_k g_k over later samples, plus T_S G_end

  ChunkLoads<scalar_t, kC, kBackwardRun> next;
  if (chunks > 0) next = ChunkLoads<scalar_t, kC, kBackwardRun>(in, g, offset, count, chunks - 1, lane, chunk_start);
  for (int64_t q = chunks - 1; q >= 0; --q) {
    const ChunkLoads<scalar_t, kC, kBackwardRun> loaded = next;
    if (q > 0) next = ChunkLoads<scalar_t, kC, kBackwardRun>(in, g, offset, count, q - 1, lane, chunk_start);
    const LaneSamples<scalar_t, kBackwardRun> s(offset, count, q * kBackwardChunk + lane * kBackwardRun, loaded.sigma,
                                                loaded.t_start, loaded.t_end);
    NegExp sample[kBackwardRun];
    const ray_acc run_decay = s.neg_exps(sample);
    ray_acc transmittance_after_chunk = loaded.transmittance_before;
    ray_acc transmittance = run_transmittance(run_decay, lane, transmittance_after_chunk);
    if (q == chunks - 1) {
      transmittance_end = transmittance_after_chunk;
      after_chunk = transmittance_end * G_end;
    }
    ray_acc g_in[kBackwardRun], t_after[kBackwardRun], w[kBackwardRun];
    ray_acc run_sum = 0;  // sum of w_k g_k over the lane's run
#pragma unroll
    for (int j = 0; j < kBackwardRun; ++j) {
      g_in[j] = 0, t_after[j] = 0, w[j] = 0;
      if (j >= s.valid) continue;
      t_after[j] = transmittance * sample[j].exp;
      w[j] = transmittance * sample[j].alpha;
      transmittance = t_after[j];
      const int64_t i = s.first + j;
      g_in[j] = grad_depth * s.midpoint(j) + ray_acc(loaded.weight_grad[j]);
      scalar_t* rgb_grad = g.rgbs + i * C;
      if constexpr (kC > 0) {
#pragma unroll
        for (int c = 0; c < kC; ++c) {
          g_in[j] += color_grad[c] * ray_acc(loaded.rgb[j][c]);
          rgb_grad[c] = static_cast<scalar_t>(color_grad[c] * w[j]);
        }
      } else {
        const scalar_t* rgb = in.rgbs + i * C;
        for (int64_t c = 0; c < C; ++c) {
          const ray_acc gc = grad_color ? ray_acc(grad_color[c]) : ray_acc(0);
          g_in[j] += gc * ray_acc(rgb[c]);
          rgb_grad[c] = static_cast<scalar_t>(gc * w[j]);
        }
      }
      run_sum += w[j] * g_in[j];
    }
    // S past this lane's run: S past the chunk plus the later lanes' run sums (a reverse warp scan,
    // shifted down a lane: never a subtraction).
    const ray_acc suffix = warp_reverse_inclusive_scan(run_sum, lane);
    const ray_acc later = __shfl_down_sync(kFullMask, suffix, 1);
    ray_acc after_sample = after_chunk + (lane == kWarpSize - 1 ? ray_acc(0) : later);
    after_chunk += __shfl_sync(kFullMask, suffix, 0);
#pragma unroll
    for (int j = kBackwardRun - 1; j >= 0; --j) {
      if (j >= s.valid) continue;
      const ray_acc grad_tau = t_after[j] * g_in[j] - after_sample;
      after_sample += w[j] * g_in[j];
      const int64_t i = s.first + j;
      g.sigmas[i] = static_cast<scalar_t>(grad_tau * (ray_acc(s.t_end[j]) - ray_acc(s.t_start[j])));
      if (t_grads) {
        const ray_acc from_depth = ray_acc(0.5) * grad_depth * w[j];
        g.t_starts[i] = static_cast<scalar_t>(from_depth - grad_tau * ray_acc(s.sigma[j]));
        g.t_ends[i] = static_cast<scalar_t>(from_depth + grad_tau * ray_acc(s.sigma[j]));
      }
    }
  }
  if (g.background_rows) {
    for (int64_t c = lane; c < C; c += kWarpSize) {
      g.background_rows[ray * C + c] = static_cast<acc>(grad_color ? ray_acc(grad_color[c]) * transmittance_end : ray_acc(0));
    }
  }
}

// chunk_transmittances: ray r's chunks from span.offset / kBackwardChunk + r. A ray of `count`
// samples from `offset` needs at most ceil(count / kBackwardChunk) entries, and the next ray's
// first entry is at least floor(count / kBackwardChunk) + 1 further on, so rays never overlap and
// N / kBackwardChunk + R entries hold them all.
__device__ __forceinline__ int64_t chunk_entries_before(composite_layout::RaySpan span, int64_t ray) {
  return span.offset / kBackwardChunk + ray;
}

template <typename scalar_t, int kC, typename Rays>
// 4 blocks per SM: 64 registers (80 without the bound capped occupancy at 3 blocks, and the
// forward is latency-bound), at the cost of <= 48 bytes of spills.
__global__ void __launch_bounds__(kMaxWarpsPerBlock* kWarpSize, 4)
    composite_fwd_kernel(CompositeInputs<scalar_t> in, CompositeOutputs<scalar_t> out, int64_t R, Rays rays) {
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + threadIdx.x / kWarpSize;
  if (ray >= R) return;  // whole warps leave together: the shuffles below see full warps
  const composite_layout::RaySpan span = rays(ray);
  const int lane = threadIdx.x % kWarpSize;
  ray_acc* chunk_start = out.chunk_transmittances + chunk_entries_before(span, ray);
  int32_t invalid = composite_forward_ray<scalar_t, kC>(in, out, ray, span.offset, span.count, lane, chunk_start);
  // A zero in the ray's entry past its chunks, where it has one: every output element is written.
  const int64_t owned = chunk_entries_before({span.offset + span.count, 0}, ray + 1) - chunk_entries_before(span, ray);
  for (int64_t q = (span.count + kBackwardChunk - 1) / kBackwardChunk + lane; q < owned; q += kWarpSize) {
    chunk_start[q] = 0;
  }
  if (lane == 0 && !rays.well_formed(ray, R)) invalid |= kBadOffsets;
  if (invalid) atomicOr(out.invalid, invalid);  // only for bad input: no contention otherwise
}

template <typename scalar_t, int kC, typename Rays>
// 4 blocks per SM, as the forward: the loads a chunk ahead took the dense float32 kernel from 64 to
// 80 registers (3 blocks) without the bound, none spilled with it (the packed one spills 24 bytes).
__global__ void __launch_bounds__(kMaxWarpsPerBlock* kWarpSize, 4)
    composite_bwd_kernel(CompositeInputs<scalar_t> in, CompositeGrads<scalar_t> g, int64_t R, Rays rays,
                         const ray_acc* chunk_transmittances) {
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + threadIdx.x / kWarpSize;
  if (ray >= R) return;
  const composite_layout::RaySpan span = rays(ray);
  composite_backward_ray<scalar_t, kC>(in, g, ray, span.offset, span.count, threadIdx.x % kWarpSize,
                         chunk_transmittances + chunk_entries_before(span, ray));
}

unsigned blocks_for(int64_t R) {
  const int64_t blocks = (R + kMaxWarpsPerBlock - 1) / kMaxWarpsPerBlock;
  MIXER_NERF_CHECK(blocks <= int64_t(INT32_MAX), "composite: too many rays for one launch");
  return static_cast<unsigned>(blocks);
}

// The composite ops' CUDA kernels, for CompositeOps (composite.h).
struct Cuda {
  static constexpr at::DeviceType kind = at::kCUDA;
  static int64_t chunk_transmittance_entries(int64_t N, int64_t R) { return N / kBackwardChunk + R; }

  template <typename Rays>
  static CompositeForward forward(const CompositeTensors& tensors, int64_t R, Rays rays) {
    const c10::cuda::CUDAGuard device_guard(tensors.sigmas.device());
    auto outputs = empty_outputs(tensors.sigmas, tensors.rgbs, R, chunk_transmittance_entries(tensors.sigmas.numel(), R));
    if (R == 0) return outputs;
    MIXER_NERF_DISPATCH_FLOATING(tensors.sigmas.scalar_type(), "composite_fwd_cuda", [&] {
      const auto out = outputs_of<scalar_t>(outputs);
      // RGB, what every renderer composites, with its channels compiled in; any other count read.
      auto* kernel = tensors.rgbs.size(-1) == 3 ? composite_fwd_kernel<scalar_t, 3, Rays>
                                                : composite_fwd_kernel<scalar_t, 0, Rays>;
      kernel<<<blocks_for(R), kMaxWarpsPerBlock * kWarpSize, 0, c10::cuda::getCurrentCUDAStream()>>>(
          tensors.pointers<scalar_t>(), out, R, rays);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
    return outputs;
  }

  template <typename Rays>
  static void backward(const Upstream& up, const CompositeTensors& tensors, const at::Tensor& chunk_transmittances,
                       CompositeGradTensors& grads, int64_t R, Rays rays) {
    if (R == 0) return;
    const at::Tensor& sigmas = tensors.sigmas;
    const c10::cuda::CUDAGuard device_guard(sigmas.device());
    MIXER_NERF_DISPATCH_FLOATING(sigmas.scalar_type(), "composite_bwd_cuda", [&] {
      // RGB, what every renderer composites, with its channels compiled in; any other count read.
      auto* kernel = tensors.rgbs.size(-1) == 3 ? composite_bwd_kernel<scalar_t, 3, Rays>
                                                : composite_bwd_kernel<scalar_t, 0, Rays>;
      kernel<<<blocks_for(R), kMaxWarpsPerBlock * kWarpSize, 0, c10::cuda::getCurrentCUDAStream()>>>(
          tensors.pointers<scalar_t>(), grads.pointers<scalar_t>(up), R, rays, chunk_transmittances.const_data_ptr<ray_acc>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  }
};

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) { CompositeOps<Cuda>::register_ops(m); }

}  // namespace mixer_nerf
