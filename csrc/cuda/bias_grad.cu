// bias_grad and relu_bias_bwd on CUDA; the math is that of csrc/bias_grad.cpp (read its file
// comment first). Two launches, no atomics: band_sums_kernel gives each block a band of rows,
// which it masks (relu_bias_bwd) and sums per column into one row of `partials` (acc_t); then
// columns::sum_rows_kernel adds those rows in band order into the bias gradient. Deterministic. Threads
// walk the rows as the segment ops do (columns.cuh): x over 16-byte columns, y over rows, the
// band's sums reduced across y in a fixed order. Memory-bound: g read once (and the mask written
// once), where the eager backward read it again in a GEMV.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <c10/cuda/CUDAStream.h>  // = at::cuda::getCurrentCUDAStream, without the cuSPARSE/cuBLAS headers
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>

#include <cuda_runtime.h>

#include <cstdint>

#include "bias_grad.h"
#include "columns.cuh"
#include "common.h"

namespace mixer_nerf {
namespace {

using columns::block_for;
using columns::Column;
using columns::kThreads;
using columns::sum_over_rows;
using columns::with_column_width;

constexpr int kBandsPerSM = 4;  // blocks of the first pass per SM: enough resident to hide latency

// Rows [band * rows, (band + 1) * rows) of g (N rows of `cols` columns): masked where y <= 0
// (kRelu) and summed per channel into partials[band].
template <typename scalar_t, int V, bool kRelu>
__global__ void __launch_bounds__(kThreads)
    band_sums_kernel(const scalar_t* grad, const scalar_t* out, scalar_t* masked, int64_t N, int64_t cols,
                     int64_t rows, acc_t<scalar_t>* partials) {
  using acc = acc_t<scalar_t>;
  using column = Column<scalar_t, V>;
  __shared__ acc scratch[V * kThreads];
  const int64_t begin = int64_t(blockIdx.x) * rows, end = begin + rows < N ? begin + rows : N;
  const column* g_rows = reinterpret_cast<const column*>(grad);
  const column* y_rows = reinterpret_cast<const column*>(out);
  column* m_rows = reinterpret_cast<column*>(masked);
  // Columns in passes of blockDim.x; every thread runs every pass (sum_over_rows synchronises).
  for (int64_t first = 0; first < cols; first += blockDim.x) {
    const int64_t c = first + threadIdx.x;
    acc sum[V] = {};
    if (c < cols) {
#pragma unroll 4
      for (int64_t i = begin + threadIdx.y; i < end; i += blockDim.y) {
        column g = g_rows[i * cols + c];
        if constexpr (kRelu) {
          const column y = y_rows[i * cols + c];
#pragma unroll
          for (int j = 0; j < V; ++j) g.v[j] = y.v[j] <= scalar_t(0) ? scalar_t(0) : g.v[j];
          m_rows[i * cols + c] = g;
        }
#pragma unroll
        for (int j = 0; j < V; ++j) sum[j] += acc(g.v[j]);
      }
    }
    sum_over_rows<acc, V>(sum, scratch);
    if (c < cols && threadIdx.y == 0) {
#pragma unroll
      for (int j = 0; j < V; ++j) partials[int64_t(blockIdx.x) * cols * V + c * V + j] = sum[j];
    }
  }
}

struct Cuda {
  static constexpr at::DeviceType kind = at::kCUDA;
  template <bool kRelu>
  static at::Tensor column_sums(const at::Tensor& grad, const at::Tensor* out, at::Tensor* masked);
};

template <bool kRelu>
at::Tensor Cuda::column_sums(const at::Tensor& grad, const at::Tensor* out, at::Tensor* masked) {
  const c10::cuda::CUDAGuard device_guard(grad.device());
  const int64_t N = grad.size(0), C = grad.size(1);
  if (N == 0 || C == 0) return at::zeros({C}, grad.options());
  int sms = 0;
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, grad.device().index()));
  const int64_t rows = bias_grad::band_rows(N, int64_t(kBandsPerSM) * sms), bands = (N + rows - 1) / rows;
  const auto acc_type = grad.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  at::Tensor partials = at::empty({bands, C}, grad.options().dtype(acc_type));
  at::Tensor sums = at::empty({C}, grad.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  MIXER_NERF_DISPATCH_FLOATING(grad.scalar_type(), "bias_grad_cuda", [&] {
    using acc = acc_t<scalar_t>;
    const scalar_t* g = grad.const_data_ptr<scalar_t>();
    const scalar_t* y = kRelu ? out->const_data_ptr<scalar_t>() : nullptr;
    scalar_t* m = kRelu ? masked->data_ptr<scalar_t>() : nullptr;
    with_column_width<scalar_t>(C, {g, y, m}, [&](auto width) {
      constexpr int V = decltype(width)::value;
      band_sums_kernel<scalar_t, V, kRelu><<<static_cast<unsigned>(bands), block_for(C / V), 0, stream>>>(
          g, y, m, N, C / V, rows, partials.data_ptr<acc>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
    const columns::Destinations<scalar_t, 1> db{{sums.data_ptr<scalar_t>()}, {0, C}};
    columns::sum_rows_kernel<<<columns::sum_rows_grid(C), columns::sum_rows_block(), 0, stream>>>(
        partials.const_data_ptr<acc>(), bands, C, db);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return sums;
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) { bias_grad::BiasGradOps<Cuda>::register_ops(m); }

}  // namespace mixer_nerf
