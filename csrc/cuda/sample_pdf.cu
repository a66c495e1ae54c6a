// sample_pdf and hierarchical_samples on CUDA. The math is sample_pdf_math.h, shared with the CPU
// kernels, so both build the same CDF bit for bit and pick the same bins.
//
// Forward: one warp per ray, its data staged in shared memory with coalesced loads. Lane 0 sums
// the CDF sequentially (a tree scan would not be exactly flat over zero-weight bins, nor even
// monotone, and the sum is short); then each lane takes samples n = lane, lane + 32, ...: binary
// search of its bin, one division. hierarchical_samples merges without sorting: the fine sample
// n lands at n + #{coarse <= it} and coarse depth j at j + #{fine < it}, both binary searches in
// shared memory, written straight into the ray's output row.
//
// Backward (sample_pdf only; NeRF's fine depths carry no gradient): one thread per ray running
// the O(B + N) reverse pass of sample_pdf_ray_backward, its CDF scratch in global memory.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>  // = at::cuda::getCurrentCUDAStream, without the cuSPARSE/cuBLAS headers

#include <tuple>

#include "common.h"
#include "sample_pdf_math.h"

namespace mixer_nerf {
namespace {

using namespace sample_pdf_math;

constexpr int kWarpSize = 32;
constexpr int kMaxWarpsPerBlock = 8;
constexpr int kBackwardThreads = 128;
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

// Shared memory of one warp, in accumulation-type elements: cdf (B+1), padded weights (B),
// edges (B+1); when merging also the coarse depths (S = B+2) and the fine samples (N).
struct WarpLayout {
  int num_bins;
  int coarse;  // 0 unless merging
  int samples;
  __host__ __device__ int elements() const { return 3 * num_bins + 2 + (coarse ? coarse + samples : 0); }
};

template <typename scalar_t, bool kMerge>
__global__ void sample_forward_kernel(const scalar_t* __restrict__ edges_or_z, const scalar_t* __restrict__ weights,
                                      const acc_t<scalar_t>* __restrict__ u, int64_t u_row_stride,
                                      scalar_t* __restrict__ out, int64_t rays, WarpLayout layout,
                                      acc_t<scalar_t> pad) {
  using acc = acc_t<scalar_t>;
  extern __shared__ __align__(16) unsigned char shared_raw[];
  const int warp = threadIdx.x / kWarpSize, lane = threadIdx.x % kWarpSize;
  const int64_t ray = int64_t(blockIdx.x) * (blockDim.x / kWarpSize) + warp;
  if (ray >= rays) return;  // whole warps only: blockDim is a multiple of 32

  const int B = layout.num_bins, S = layout.coarse, N = layout.samples;
  acc* cdf = reinterpret_cast<acc*>(shared_raw) + int64_t(warp) * layout.elements();
  acc* w = cdf + B + 1;
  acc* edges = w + B;
  acc* z = edges + B + 1;  // merging only
  acc* fine = z + S;       // merging only

  // Coarse weights keep S per row and the bins use weights[:, 1:-1].
  const scalar_t* weights_row = kMerge ? weights + ray * S + 1 : weights + ray * B;
  for (int k = lane; k < B; k += kWarpSize) w[k] = PaddedWeights<acc, scalar_t>{weights_row, pad}(k);
  if constexpr (kMerge) {
    const scalar_t* z_row = edges_or_z + ray * S;
    for (int j = lane; j < S; j += kWarpSize) z[j] = static_cast<acc>(z_row[j]);
    __syncwarp();
    for (int k = lane; k <= B; k += kWarpSize) edges[k] = MidpointEdges<acc, acc>{z}(k);
  } else {
    const scalar_t* bins_row = edges_or_z + ray * (B + 1);
    for (int k = lane; k <= B; k += kWarpSize) edges[k] = static_cast<acc>(bins_row[k]);
  }
  __syncwarp();
  const PaddedWeights<acc, acc> padded{w, acc(0)};  // already padded and flushed: unchanged
  if (lane == 0) build_cdf(padded, B, cdf);
  __syncwarp();

  const acc total = cdf[B];
  const bool uniform = no_pdf(total);
  const GivenEdges<acc, acc> given{edges};
  const acc* u_row = u + ray * u_row_stride;
  const int64_t out_row = ray * (int64_t(N) + S);
  for (int n = lane; n < N; n += kWarpSize) {
    const acc un = u_row[n];
    acc s;
    if (uniform) {
      s = sample_uniform(un, B, given);
    } else {
      const acc v = un * total;
      s = sample_in_bin(v, find_bin(cdf, B, v), cdf, padded, given);
    }
    if constexpr (kMerge) fine[n] = s;
    else out[out_row + n] = static_cast<scalar_t>(s);
  }
  if constexpr (kMerge) {
    __syncwarp();
    // Ties put the coarse depth first, like the CPU kernel; the values are equal either way.
    for (int n = lane; n < N; n += kWarpSize) {
      out[out_row + n + count_before<true>(z, S, fine[n])] = static_cast<scalar_t>(fine[n]);
    }
    const scalar_t* z_row = edges_or_z + ray * S;
    for (int j = lane; j < S; j += kWarpSize) out[out_row + j + count_before<false>(fine, N, z[j])] = z_row[j];
  }
}

template <typename scalar_t>
__global__ void sample_pdf_backward_kernel(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ bins,
                                           const scalar_t* __restrict__ weights,
                                           const acc_t<scalar_t>* __restrict__ u, int64_t u_row_stride,
                                           int64_t rays, int num_bins, int num_samples, acc_t<scalar_t> pad,
                                           acc_t<scalar_t>* __restrict__ scratch, scalar_t* __restrict__ grad_bins,
                                           scalar_t* __restrict__ grad_weights) {
  const int64_t ray = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (ray >= rays) return;
  const int64_t edges = num_bins + 1;
  sample_pdf_ray_backward(grad + ray * num_samples, bins + ray * edges, weights + ray * num_bins,
                          u + ray * u_row_stride, num_bins, num_samples, pad, scratch + ray * edges,
                          grad_bins + ray * edges, grad_weights + ray * num_bins);
}

// Launches the forward kernel with as many warps per block as fit the default shared memory
// (at least one, opting in to more shared memory for very long rays).
template <typename scalar_t, bool kMerge>
void launch_forward(const at::Tensor& edges_or_z, const at::Tensor& weights, const at::Tensor& u,
                    const RayBatch& batch, WarpLayout layout, double weight_padding, at::Tensor& out) {
  using acc = acc_t<scalar_t>;
  const size_t warp_bytes = size_t(layout.elements()) * sizeof(acc);
  const int warps = int(std::max<size_t>(1, std::min<size_t>(kMaxWarpsPerBlock, kDefaultSharedBytes / warp_bytes)));
  const size_t shared = warps * warp_bytes;
  auto kernel = sample_forward_kernel<scalar_t, kMerge>;
  if (shared > kDefaultSharedBytes) {
    int device = 0, optin = 0;
    C10_CUDA_CHECK(cudaGetDevice(&device));
    C10_CUDA_CHECK(cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin, device));
    TORCH_CHECK(shared <= size_t(optin), "sample_pdf: ", layout.elements(), " bins and samples per ray need ",
                shared, " bytes of shared memory, more than the GPU's ", optin);
    C10_CUDA_CHECK(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, int(shared)));
  }
  const int64_t blocks = (batch.rays + warps - 1) / warps;
  kernel<<<blocks, warps * kWarpSize, shared, c10::cuda::getCurrentCUDAStream()>>>(
      edges_or_z.data_ptr<scalar_t>(), weights.data_ptr<scalar_t>(), u.data_ptr<acc>(), batch.u_row_stride,
      out.data_ptr<scalar_t>(), batch.rays, layout, static_cast<acc>(weight_padding));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

at::Tensor sample_pdf_fwd_cuda(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& u,
                               double weight_padding) {
  const RayBatch batch = check_batch(bins, weights, u, at::kCUDA);
  check_bins(bins, weights);
  const c10::cuda::CUDAGuard guard(bins.device());
  at::Tensor samples = at::empty({batch.rays, batch.samples}, bins.options());
  if (samples.numel() == 0) return samples;
  const WarpLayout layout{int(weights.size(1)), 0, int(batch.samples)};
  MIXER_NERF_DISPATCH_FLOATING(bins.scalar_type(), "sample_pdf_fwd_cuda", [&] {
    launch_forward<scalar_t, false>(bins, weights, u, batch, layout, weight_padding, samples);
  });
  return samples;
}

at::Tensor hierarchical_samples_fwd_cuda(const at::Tensor& z_coarse, const at::Tensor& weights, const at::Tensor& u,
                                         double weight_padding) {
  const RayBatch batch = check_batch(z_coarse, weights, u, at::kCUDA);
  check_coarse(z_coarse, weights);
  const c10::cuda::CUDAGuard guard(z_coarse.device());
  const int coarse = int(z_coarse.size(1));
  at::Tensor merged = at::empty({batch.rays, coarse + batch.samples}, z_coarse.options());
  if (batch.rays == 0) return merged;
  const WarpLayout layout{coarse - 2, coarse, int(batch.samples)};
  MIXER_NERF_DISPATCH_FLOATING(z_coarse.scalar_type(), "hierarchical_samples_fwd_cuda", [&] {
    launch_forward<scalar_t, true>(z_coarse, weights, u, batch, layout, weight_padding, merged);
  });
  return merged;
}

std::tuple<at::Tensor, at::Tensor> sample_pdf_bwd_cuda(const at::Tensor& grad_samples, const at::Tensor& bins,
                                                       const at::Tensor& weights, const at::Tensor& u,
                                                       double weight_padding) {
  const RayBatch batch = check_batch(bins, weights, u, at::kCUDA);
  check_bins(bins, weights);
  check_grad(grad_samples, bins, batch);
  const c10::cuda::CUDAGuard guard(bins.device());
  at::Tensor grad_bins = at::empty_like(bins);
  at::Tensor grad_weights = at::empty_like(weights);
  if (batch.rays == 0) return {grad_bins, grad_weights};
  const int num_bins = int(weights.size(1));
  MIXER_NERF_DISPATCH_FLOATING(bins.scalar_type(), "sample_pdf_bwd_cuda", [&] {
    using acc = acc_t<scalar_t>;
    at::Tensor scratch = at::empty({batch.rays, num_bins + 1}, bins.options().dtype(c10::CppTypeToScalarType<acc>::value));
    const int64_t blocks = (batch.rays + kBackwardThreads - 1) / kBackwardThreads;
    sample_pdf_backward_kernel<scalar_t><<<blocks, kBackwardThreads, 0, c10::cuda::getCurrentCUDAStream()>>>(
        grad_samples.data_ptr<scalar_t>(), bins.data_ptr<scalar_t>(), weights.data_ptr<scalar_t>(), u.data_ptr<acc>(),
        batch.u_row_stride, batch.rays, num_bins, int(batch.samples), static_cast<acc>(weight_padding),
        scratch.data_ptr<acc>(), grad_bins.data_ptr<scalar_t>(), grad_weights.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {grad_bins, grad_weights};
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) {
  m.impl("sample_pdf_fwd", &sample_pdf_fwd_cuda);
  m.impl("sample_pdf_bwd", &sample_pdf_bwd_cuda);
  m.impl("hierarchical_samples_fwd", &hierarchical_samples_fwd_cuda);
}

}  // namespace mixer_nerf
