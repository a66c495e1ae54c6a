// sample_pdf (dense or packed bins) and hierarchical_samples on CUDA: one warp per ray, its data
// staged in shared memory by coalesced loads (packed rays size it by the longest ray, so the
// per-ray limits on bins are the dense ones). The math is sample_pdf_math.h, shared with the CPU
// kernels: both build the same CDF bit for bit (in build_cdf's groups, one lane per group; a tree
// scan would be neither exactly flat over zero-weight bins nor even monotone) and pick the same bins.
//
// Forward: each lane takes samples n = lane, lane + 32, ...: binary search of its bin, one
// division. hierarchical_samples merges without sorting: fine sample n lands at
// n + #{coarse <= it} and coarse depth j at j + #{fine < it}, both binary searches in shared
// memory, written straight into the ray's output row.
//
// Backward (sample_pdf only; NeRF's fine depths carry no gradient), O(B + N) per ray: samples are
// sorted, so their bins are too, and each chunk of 32 samples reduces its per-bin sums (edge
// gradients, a_n and a_n t_n of sample_pdf_ray_backward) with a segmented warp scan keyed by bin;
// the last lane of each segment adds them into shared per-bin sums, chunk after chunk. A reverse
// warp scan over the bins then gives dL/dw_i = sum a_n u_n - sum_{bins above i} a - sum_i a t.
// No atomics anywhere: the results do not depend on scheduling.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/cuda/CUDAGeneratorImpl.h>
#include <ATen/cuda/PhiloxUtils.cuh>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>  // = at::cuda::getCurrentCUDAStream, without the cuSPARSE/cuBLAS headers

#include <algorithm>
#include <climits>
#include <optional>
#include <mutex>
#include <tuple>

#include "common.h"
#include "philox.cuh"
#include "sample_pdf.h"
#include "sample_pdf_math.h"
#include "warp.cuh"

namespace mixer_nerf {
namespace {

using namespace sample_pdf;
using namespace sample_pdf_math;

constexpr int kMaxWarpsPerBlock = 8;
constexpr size_t kDefaultSharedBytes = 48 * 1024;

// #{i < n : a[i] <= x} (kInclusive) or #{i < n : a[i] < x}, for sorted a.
template <bool kInclusive, typename acc_t>
__device__ int count_before(const acc_t* a, int n, acc_t x) {
  int lo = 0, hi = n;
  while (lo < hi) {
    const int mid = (lo + hi) / 2;
    if (kInclusive ? a[mid] <= x : a[mid] < x) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

// Shared memory of one warp: the CDF (B+1, cdf_t), `tail` elements of tail_t for the kernel's
// own use, then in the accumulation type the padded weights (B) and the edges (B+1). Each warp's
// region is a multiple of 16 bytes and the CDF and tail come first, so every double is aligned.
struct WarpLayout {
  int num_bins;
  int tail;
  template <typename acc_t, typename tail_t>
  __host__ __device__ size_t bytes() const {
    const size_t acc_elements = 2 * size_t(num_bins) + 1;
    return (sizeof(cdf_t) * (num_bins + 1) + sizeof(tail_t) * size_t(tail) + sizeof(acc_t) * acc_elements + 15) /
           16 * 16;
  }
};

template <typename acc_t, typename tail_t = acc_t>
struct WarpShared {
  cdf_t* cdf;     // (B+1)
  tail_t* tail;   // (layout.tail)
  acc_t* w;       // (B) padded, flushed
  acc_t* edges;   // (B+1)

  __device__ WarpShared(unsigned char* raw, const WarpLayout& layout, int warp) {
    cdf = reinterpret_cast<cdf_t*>(raw + warp * layout.bytes<acc_t, tail_t>());
    tail = reinterpret_cast<tail_t*>(cdf + layout.num_bins + 1);
    w = reinterpret_cast<acc_t*>(tail + layout.tail);
    edges = w + layout.num_bins;
  }
};

// build_cdf (sample_pdf_math.h) by a warp, in its order: lane g sums group g's weights, the groups'
// starts are chained through the lanes in group order, then each lane writes its group's CDF.
// Returns the total weight in every lane.
template <typename Weights>
__device__ cdf_t build_cdf_warp(Weights weights, int num_bins, cdf_t* cdf, int lane) {
  const int group = cdf_group_bins(num_bins), groups = (num_bins + group - 1) / group;
  const int first = lane * group, end = min(first + group, num_bins);  // lanes past the groups: empty
  cdf_t sum = 0;
  for (int k = first; k < end; ++k) sum += weights(k);
  cdf_t start = 0, running = 0;
  for (int g = 0; g < groups; ++g) {
    if (lane == g) start = running;
    running += __shfl_sync(kFullMask, sum, g);
  }
  if (lane == 0) cdf[0] = 0;
  cdf_t partial = 0;
  for (int k = first; k < end; ++k) {
    partial += weights(k);
    cdf[k + 1] = start + partial;
  }
  return running;
}

// Where a ray's positions come from: row `ray` of u (stride 0: one row for every ray), or, where
// u is null, drawn in the kernel: u_n = (n + xi_n) / N, xi_n uniform in [0, 1), value n % V of
// Philox block offset / 4 + n / V of sequence `ray` (V = philox::kValuesPerBlock of the
// accumulation type; the generator's offset counts 32-bit values, 4 a block), and written to
// `drawn` (R, N) unless it is null (sample_pdf's backward takes them).
template <typename acc>
struct Positions {
  const acc* u;
  int64_t u_row_stride;
  at::PhiloxCudaState philox;
  acc* drawn;
};

// A ray's N stratified positions drawn into `fine` (shared), V by each Philox block a lane draws.
template <typename acc>
__device__ void draw_positions(const Positions<acc>& positions, int64_t ray, int N, int lane, acc* fine) {
  constexpr int V = philox::kValuesPerBlock<acc>;
  const auto philox = at::cuda::philox::unpack(positions.philox);  // std::get: tuple assignment is host-only
  const uint64_t seed = std::get<0>(philox), offset = std::get<1>(philox);
  for (int block = lane; block * V < N; block += kWarpSize) {
    const uint4 bits = philox::block_bits(seed, offset / 4 + block, uint64_t(ray));
#pragma unroll
    for (int k = 0; k < V; ++k) {
      const int n = block * V + k;
      if (n >= N) break;
      const acc un = (acc(n) + philox::uniform<acc>(bits, k)) / acc(N);
      fine[n] = un;
      if (positions.drawn) positions.drawn[ray * N + n] = un;
    }
  }
}

// Forward. Tail: sample_pdf: u then samples (N); hierarchical_samples: the coarse depths (S), then
// u then the fine samples (N). `rows` places sample_pdf's bins (layout.num_bins is the most any
// ray has); hierarchical_samples' rows are (R, S) coarse depths and weights. Unless `invalid` is
// null, the InvalidInput bits of the values read are OR-ed into it (sample_pdf.h). kDrawn: the
// positions are drawn by Philox (positions.u is not read), else read from positions.u; chosen at
// compile time, so that neither path holds the other's registers.
template <typename scalar_t, bool kMerge, bool kDrawn, typename Rows>
__global__ void sample_forward_kernel(int64_t rays, WarpLayout layout, Rows rows,
                                      const scalar_t* __restrict__ edges_or_z, const scalar_t* __restrict__ weights,
                                      Positions<acc_t<scalar_t>> positions, int num_samples,
                                      acc_t<scalar_t> pad, scalar_t* __restrict__ out, int32_t* invalid) {
  using acc = acc_t<scalar_t>;
  extern __shared__ __align__(16) unsigned char shared_raw[];
  const int warp = threadIdx.x / kWarpSize, lane = threadIdx.x % kWarpSize;
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + warp;
  if (ray >= rays) return;  // whole warps only: blockDim is a multiple of 32

  const int S = kMerge ? layout.num_bins + 2 : 0;
  // Coarse weights keep S per row and the bins use weights[:, 1:-1].
  const RayBins ray_bins = kMerge ? RayBins{ray * S + 1, ray * S, layout.num_bins} : rows(ray);
  const int B = ray_bins.num_bins, N = num_samples;
  const WarpShared<acc> sh(shared_raw, layout, warp);
  acc* z = sh.tail;         // (S), merging only
  acc* fine = sh.tail + S;  // (N): u, then the samples in place

  // Every load of the ray in one loop, so they are all in flight together.
  const scalar_t* weights_row = weights + ray_bins.weights;
  const scalar_t* edges_row = edges_or_z + ray_bins.edges;
  const acc* u_row = kDrawn ? nullptr : positions.u + ray * positions.u_row_stride;
  if constexpr (kDrawn) draw_positions(positions, ray, N, lane, fine);
  const int longest = max(max(B + 2, kDrawn ? 0 : N), 1);
  for (int i = lane; i < longest; i += kWarpSize) {
    if (i < B) sh.w[i] = PaddedWeights<acc, scalar_t>{weights_row, pad}(i);
    if (kMerge ? i < S : i <= B) (kMerge ? z : sh.edges)[i] = static_cast<acc>(edges_row[i]);
    if (!kDrawn && i < N) fine[i] = u_row[i];
  }
  __syncwarp();
  if constexpr (kMerge) {
    for (int k = lane; k <= B; k += kWarpSize) sh.edges[k] = MidpointEdges<acc, acc>{z}(k);
  }
  if (invalid) {  // the rows are in shared memory or cache already
    const int32_t bits =
        kMerge ? invalid_pdf_bits(z, S, weights + ray * S, S, lane, kWarpSize) |
                     invalid_position_bits(fine, N, lane, kWarpSize)
               : invalid_pdf_bits(sh.edges, B + 1, weights_row, B, lane, kWarpSize) |
                     (lane == 0 && !rows.well_formed(ray) ? kBadOffsets : 0);
    if (bits) atomicOr(invalid, bits);  // only for bad input: no contention otherwise
  }
  const PaddedWeights<acc, acc> padded{sh.w, acc(0)};  // already padded and flushed: unchanged
  const cdf_t total = build_cdf_warp(padded, B, sh.cdf, lane);
  __syncwarp();

  const bool nan_ray = nan_pdf(total), uniform = no_pdf<acc>(total);
  const GivenEdges<acc, acc> given{sh.edges};
  const int64_t out_row = ray * (int64_t(N) + S);
  for (int n = lane; n < N; n += kWarpSize) {
    const acc un = fine[n];
    const cdf_t v = cdf_t(un) * total;
    const acc s = nan_ray   ? not_a_number<acc>()
                  : uniform ? sample_uniform(un, B, given)
                            : sample_in_bin<acc>(v, find_bin(sh.cdf, B, v), sh.cdf, padded, given);
    if constexpr (kMerge) fine[n] = s;
    else out[out_row + n] = static_cast<scalar_t>(s);
  }
  if constexpr (kMerge) {
    __syncwarp();
    // Ties put the coarse depth first, like the CPU kernel; the values are equal either way. NaN
    // samples (all of a ray with a NaN weight) go after every coarse depth, as torch.sort puts
    // NaN last; no coarse depth counts them as smaller, so the positions stay a permutation.
    for (int n = lane; n < N; n += kWarpSize) {
      const acc s = fine[n];
      out[out_row + n + (s != s ? S : count_before<true>(z, S, s))] = static_cast<scalar_t>(s);
    }
    for (int j = lane; j < S; j += kWarpSize) {
      out[out_row + j + count_before<false>(fine, N, z[j])] = edges_row[j];
    }
  }
}

// Inclusive scan over lanes of the segments of equal (sorted) keys.
template <typename acc_t>
__device__ void segmented_scan(int key, int lane, acc_t& a, acc_t& b, acc_t& c, acc_t& d) {
#pragma unroll
  for (int offset = 1; offset < kWarpSize; offset *= 2) {
    const int key_up = __shfl_up_sync(kFullMask, key, offset);
    const acc_t a_up = __shfl_up_sync(kFullMask, a, offset), b_up = __shfl_up_sync(kFullMask, b, offset);
    const acc_t c_up = __shfl_up_sync(kFullMask, c, offset), d_up = __shfl_up_sync(kFullMask, d, offset);
    if (lane >= offset && key_up == key) a += a_up, b += b_up, c += c_up, d += d_up;
  }
}

// Backward. Tail: per bin, sum a, sum a t, gradient reaching its lower and its upper edge (4 B).
// Every term and sum is a double for every input dtype (grad_t), as in the CPU kernel's
// sample_pdf_ray_backward (see its comment): dL/dw_i is a difference of sums that largely cancel,
// which float32 sums made less accurate than the reference path on extreme PDFs. The doubles
// cost shuffles and shared memory, not memory traffic.
template <typename scalar_t, typename Rows>
__global__ void sample_pdf_backward_kernel(int64_t rays, WarpLayout layout, Rows rows, const scalar_t* __restrict__ grad,
                                           const scalar_t* __restrict__ bins, const scalar_t* __restrict__ weights,
                                           const acc_t<scalar_t>* __restrict__ u, int64_t u_row_stride,
                                           int num_samples, acc_t<scalar_t> pad, scalar_t* __restrict__ grad_bins,
                                           scalar_t* __restrict__ grad_weights) {
  using acc = acc_t<scalar_t>;
  extern __shared__ __align__(16) unsigned char shared_raw[];
  const int warp = threadIdx.x / kWarpSize, lane = threadIdx.x % kWarpSize;
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + warp;
  if (ray >= rays) return;

  const RayBins ray_bins = rows(ray);
  const int B = ray_bins.num_bins, N = num_samples;
  const WarpShared<acc, grad_t> sh(shared_raw, layout, warp);
  grad_t* bin_a = sh.tail;
  grad_t* bin_a_t = bin_a + B;
  grad_t* bin_lo = bin_a_t + B;
  grad_t* bin_hi = bin_lo + B;
  const scalar_t* grad_row = grad + ray * N;
  const acc* u_row = u + ray * u_row_stride;
  scalar_t* grad_bins_row = grad_bins + ray_bins.edges;
  scalar_t* grad_weights_row = grad_weights + ray_bins.weights;

  for (int i = lane; i <= B; i += kWarpSize) {
    if (i < B) {
      sh.w[i] = PaddedWeights<acc, scalar_t>{weights + ray_bins.weights, pad}(i);
      bin_a[i] = bin_a_t[i] = bin_lo[i] = bin_hi[i] = grad_t(0);
    }
    sh.edges[i] = static_cast<acc>(bins[ray_bins.edges + i]);
  }
  __syncwarp();
  const PaddedWeights<acc, acc> padded{sh.w, acc(0)};
  const cdf_t total = build_cdf_warp(padded, B, sh.cdf, lane);
  __syncwarp();

  if (nan_pdf(total)) {  // a NaN weight: NaN gradients for every weight and edge of the ray
    for (int i = lane; i <= B; i += kWarpSize) {
      if (i < B) grad_weights_row[i] = static_cast<scalar_t>(not_a_number<acc>());
      grad_bins_row[i] = static_cast<scalar_t>(not_a_number<acc>());
    }
    return;
  }
  if (no_pdf<acc>(total)) {  // s = e_0 + u (e_B - e_0): only the end edges get gradient
    grad_t first = 0, last = 0;
    for (int n = lane; n < N; n += kWarpSize) {
      const grad_t g = static_cast<grad_t>(grad_row[n]);
      first += g - g * u_row[n];
      last += g * u_row[n];
    }
    first = warp_sum(first);
    last = warp_sum(last);
    for (int i = lane; i <= B; i += kWarpSize) {  // a ray without bins: one edge gets both
      if (i < B) grad_weights_row[i] = scalar_t(0);
      grad_bins_row[i] = static_cast<scalar_t>((i == 0 ? first : grad_t(0)) + (i == B ? last : grad_t(0)));
    }
    return;
  }

  grad_t sum_a_u = 0;
  for (int base = 0; base < N; base += kWarpSize) {  // the same trip count in every lane
    const int n = base + lane;
    int key = INT_MAX;  // lanes past the end form their own segment and write nothing
    grad_t a = 0, a_t = 0, lo = 0, hi = 0;
    if (n < N) {
      const grad_t g = static_cast<grad_t>(grad_row[n]);
      const cdf_t v = cdf_t(u_row[n]) * total;
      key = find_bin(sh.cdf, B, v);
      const grad_t w_k = sh.w[key];
      const Fraction<grad_t> f = fraction_in_bin(v, sh.cdf[key], w_k);
      lo = g - g * f.t;
      hi = g * f.t;
      if (f.weighted) {
        a = g * (grad_t(sh.edges[key + 1]) - grad_t(sh.edges[key])) / w_k;
        a_t = a * f.t_raw;
        sum_a_u += a * u_row[n];
      }
    }
    segmented_scan(key, lane, a, a_t, lo, hi);
    const int key_down = __shfl_down_sync(kFullMask, key, 1);
    if (n < N && (lane == kWarpSize - 1 || key_down != key)) {
      bin_a[key] += a;
      bin_a_t[key] += a_t;
      bin_lo[key] += lo;
      bin_hi[key] += hi;
    }
    __syncwarp();  // a bin can continue in the next chunk
  }
  sum_a_u = warp_sum(sum_a_u);

  // dL/dw_i = sum a u - (sum of bin_a above i) - bin_a_t[i], from the last bin down: lane 0 takes
  // the highest bin of each chunk, and `above` carries the chunks already done.
  grad_t above = 0;
  for (int base = 0; base < B; base += kWarpSize) {
    const int i = B - 1 - base - lane;
    const grad_t inclusive = warp_inclusive_scan(i >= 0 ? bin_a[i] : grad_t(0), lane);
    const grad_t below = __shfl_up_sync(kFullMask, inclusive, 1);  // every lane: the mask says all 32
    const grad_t exclusive = lane == 0 ? grad_t(0) : below;
    if (i >= 0) {
      grad_weights_row[i] = sh.w[i] > 0 ? static_cast<scalar_t>(sum_a_u - (above + exclusive) - bin_a_t[i]) : scalar_t(0);
    }
    above += __shfl_sync(kFullMask, inclusive, kWarpSize - 1);
  }
  for (int e = lane; e <= B; e += kWarpSize) {
    grad_bins_row[e] = static_cast<scalar_t>((e < B ? bin_lo[e] : grad_t(0)) + (e > 0 ? bin_hi[e - 1] : grad_t(0)));
  }
}

// Launches a warp-per-ray kernel with as many warps per block as fit the default shared memory
// (at least one, opting in to more shared memory for very long rays).
template <typename acc, typename tail_t, typename Kernel, typename... Args>
void launch_warp_per_ray(Kernel kernel, const WarpLayout& layout, int64_t rays, Args... args) {
  if (rays == 0) return;
  const size_t warp_bytes = layout.bytes<acc, tail_t>();
  const int warps = int(std::max<size_t>(1, std::min<size_t>(kMaxWarpsPerBlock, kDefaultSharedBytes / warp_bytes)));
  const size_t shared = warps * warp_bytes;
  if (shared > kDefaultSharedBytes) {
    int device = 0, optin = 0;
    C10_CUDA_CHECK(cudaGetDevice(&device));
    C10_CUDA_CHECK(cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin, device));
    MIXER_NERF_CHECK(shared <= size_t(optin), "sample_pdf: ", layout.num_bins, " bins and ", layout.tail,
                " more values per ray need ", shared, " bytes of shared memory, more than the GPU's ", optin);
    C10_CUDA_CHECK(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, int(shared)));
  }
  const int64_t blocks = (rays + warps - 1) / warps;
  kernel<<<blocks, warps * kWarpSize, shared, c10::cuda::getCurrentCUDAStream()>>>(rays, layout, args...);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

// The most bins of any ray: dense, weights' width; packed, the longest ray (a host sync, after
// the outputs are allocated so that they are the first allocations of the op). The spans are
// those the kernels read, from offsets clamped as PackedBins clamps them (the first ray from 0,
// the last to N): unchecked offsets can neither overflow the differences nor make a ray longer
// than the shared memory sized for it, and no ray spans more than N < 2^30.
int max_bins_of(const at::Tensor& weights, const std::optional<at::Tensor>& offsets) {
  if (!offsets) return static_cast<int>(weights.size(1));
  const int64_t rays = offsets->size(0) - 1, total = weights.size(0);
  if (rays < 1) return 0;
  at::Tensor bounds = offsets->clamp(0, total);
  bounds.narrow(0, 0, 1).fill_(0);
  bounds.narrow(0, rays, 1).fill_(total);
  const int64_t most = (bounds.slice(0, 1) - bounds.slice(0, 0, -1)).max().item<int64_t>();
  return static_cast<int>(std::clamp<int64_t>(most, 0, total));
}

// The generator's Philox state for positions of `dtype` drawn in the kernel, `samples` per ray
// (Positions: a block of 4 values gives kValuesPerBlock of them), advancing it past them; the
// default CUDA generator if none is given.
at::PhiloxCudaState philox_for(std::optional<at::Generator> generator, int64_t samples, at::ScalarType dtype) {
  const int64_t per_block = at::toOpMathType(dtype) == at::kDouble ? philox::kValuesPerBlock<double>
                                                                    : philox::kValuesPerBlock<float>;
  auto* gen = at::get_generator_or_default<at::CUDAGeneratorImpl>(generator, at::cuda::detail::getDefaultCUDAGenerator());
  const std::lock_guard<std::mutex> lock(gen->mutex_);
  return gen->philox_cuda_state(4 * uint64_t((samples + per_block - 1) / per_block));
}

// The sample_pdf ops' CUDA kernels, for SamplePdfOps (sample_pdf.h).
struct Cuda {
  static constexpr at::DeviceType kind = at::kCUDA;

  template <typename Rows>
  static at::Tensor forward(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& u,
                            double weight_padding, const RayBatch& batch, Rows rows,
                            const std::optional<at::Tensor>& offsets) {
    const c10::cuda::CUDAGuard guard(bins.device());
    at::Tensor samples = at::empty({batch.rays, batch.samples}, bins.options());
    if (samples.numel() > 0) {
      sample(bins, weights, &u, {}, nullptr, weight_padding, batch, rows, offsets, samples, nullptr);
    }
    return samples;
  }

  template <typename Rows>
  static std::tuple<at::Tensor, at::Tensor, at::Tensor> forward_stratified(
      const at::Tensor& bins, const at::Tensor& weights, std::optional<at::Generator> generator,
      double weight_padding, bool keep_positions, const RayBatch& batch, Rows rows,
      const std::optional<at::Tensor>& offsets) {
    const c10::cuda::CUDAGuard guard(bins.device());
    at::Tensor samples = at::empty({batch.rays, batch.samples}, bins.options());
    at::Tensor u = at::empty({batch.rays, keep_positions ? batch.samples : 0},
                             bins.options().dtype(at::toOpMathType(bins.scalar_type())));
    at::Tensor invalid = at::zeros({1}, bins.options().dtype(at::kInt));
    if (batch.rays > 0) {  // even without samples: the values are still checked
      sample(bins, weights, nullptr, philox_for(generator, batch.samples, bins.scalar_type()), keep_positions ? &u : nullptr,
             weight_padding, batch, rows, offsets, samples, invalid.data_ptr<int32_t>());
    }
    return {samples, u, invalid};
  }

  // sample_pdf into `samples`, with positions from `u` (R, N) or (N), or drawn by `philox` (u
  // null) into `drawn`; `invalid`, unless null, gets the InvalidInput bits of the values read.
  template <typename Rows>
  static void sample(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor* u,
                     at::PhiloxCudaState philox, at::Tensor* drawn, double weight_padding, const RayBatch& batch,
                     Rows rows, const std::optional<at::Tensor>& offsets, at::Tensor& samples, int32_t* invalid) {
    const int max_bins = max_bins_of(weights, offsets);
    const int num_samples = int(batch.samples);
    MIXER_NERF_DISPATCH_FLOATING(bins.scalar_type(), "sample_pdf_fwd_cuda", [&] {
      using acc = acc_t<scalar_t>;
      const Positions<acc> positions{u ? u->data_ptr<acc>() : nullptr, batch.u_row_stride, philox,
                                     drawn ? drawn->data_ptr<acc>() : nullptr};
      launch_warp_per_ray<acc, acc>(u ? sample_forward_kernel<scalar_t, false, false, Rows>
                                      : sample_forward_kernel<scalar_t, false, true, Rows>,
                                    WarpLayout{max_bins, num_samples}, batch.rays, rows, bins.data_ptr<scalar_t>(),
                                    weights.data_ptr<scalar_t>(), positions, num_samples,
                                    static_cast<acc>(weight_padding), samples.data_ptr<scalar_t>(), invalid);
    });
  }

  template <typename Rows>
  static std::tuple<at::Tensor, at::Tensor> backward(const at::Tensor& grad_samples, const at::Tensor& bins,
                                                     const at::Tensor& weights, const at::Tensor& u,
                                                     double weight_padding, const RayBatch& batch, Rows rows,
                                                     const std::optional<at::Tensor>& offsets) {
    check_grad(grad_samples, bins, batch);
    const c10::cuda::CUDAGuard guard(bins.device());
    at::Tensor grad_bins = at::empty_like(bins);
    at::Tensor grad_weights = at::empty_like(weights);
    if (batch.rays == 0) return {grad_bins, grad_weights};
    const int max_bins = max_bins_of(weights, offsets);
    const int num_samples = int(batch.samples);
    MIXER_NERF_DISPATCH_FLOATING(bins.scalar_type(), "sample_pdf_bwd_cuda", [&] {
      using acc = acc_t<scalar_t>;
      launch_warp_per_ray<acc, grad_t>(sample_pdf_backward_kernel<scalar_t, Rows>, WarpLayout{max_bins, 4 * max_bins},
                               batch.rays, rows, grad_samples.data_ptr<scalar_t>(), bins.data_ptr<scalar_t>(),
                               weights.data_ptr<scalar_t>(), u.data_ptr<acc>(), batch.u_row_stride, num_samples,
                               static_cast<acc>(weight_padding), grad_bins.data_ptr<scalar_t>(),
                               grad_weights.data_ptr<scalar_t>());
    });
    return {grad_bins, grad_weights};
  }

  static std::tuple<at::Tensor, at::Tensor> hierarchical(const at::Tensor& z_coarse, const at::Tensor& weights,
                                                         const at::Tensor& u, double weight_padding,
                                                         const RayBatch& batch) {
    return merge(z_coarse, weights, &u, batch.samples, batch.u_row_stride, {}, weight_padding);
  }

  static std::tuple<at::Tensor, at::Tensor> hierarchical_stratified(const at::Tensor& z_coarse,
                                                                    const at::Tensor& weights,
                                                                    std::optional<at::Generator> generator,
                                                                    double weight_padding, const RayBatch& batch) {
    const c10::cuda::CUDAGuard guard(z_coarse.device());
    return merge(z_coarse, weights, nullptr, batch.samples, 0, philox_for(generator, batch.samples, z_coarse.scalar_type()),
                 weight_padding);
  }

  // hierarchical_samples with positions from `u` (R, N) or (N), or drawn by `philox` (u null).
  static std::tuple<at::Tensor, at::Tensor> merge(const at::Tensor& z_coarse, const at::Tensor& weights,
                                                  const at::Tensor* u, int64_t samples, int64_t u_row_stride,
                                                  at::PhiloxCudaState philox, double weight_padding) {
    const c10::cuda::CUDAGuard guard(z_coarse.device());
    const int64_t rays = z_coarse.size(0);
    const int coarse = int(z_coarse.size(1)), num_samples = int(samples);
    at::Tensor merged = at::empty({rays, coarse + samples}, z_coarse.options());
    at::Tensor invalid = at::zeros({1}, z_coarse.options().dtype(at::kInt));
    MIXER_NERF_DISPATCH_FLOATING(z_coarse.scalar_type(), "hierarchical_samples_fwd_cuda", [&] {
      using acc = acc_t<scalar_t>;
      launch_warp_per_ray<acc, acc>(u ? sample_forward_kernel<scalar_t, true, false, DenseBins>
                                      : sample_forward_kernel<scalar_t, true, true, DenseBins>,
                               WarpLayout{coarse - 2, coarse + num_samples}, rays, DenseBins{coarse - 2},
                               z_coarse.data_ptr<scalar_t>(), weights.data_ptr<scalar_t>(),
                               Positions<acc>{u ? u->data_ptr<acc>() : nullptr, u_row_stride, philox, nullptr},
                               num_samples,
                               static_cast<acc>(weight_padding), merged.data_ptr<scalar_t>(),
                               invalid.data_ptr<int32_t>());
    });
    return {merged, invalid};
  }
};

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) { SamplePdfOps<Cuda>::register_ops(m); }

}  // namespace mixer_nerf
