// segment_mean and ray_scale on CUDA; the math is that of csrc/segment_ops.cpp (read its file
// comment first): per-ray means and per-ray channel scales of packed rows (N, C), ray r owning
// rows offsets[r]:offsets[r+1], with hand-written backwards.
//
// One block per ray. Its threads form a (x, y) grid: x over channel columns, y over the ray's
// rows (row i goes to y = i mod blockDim.y). A ray's rows are contiguous, so a warp's loads cover
// consecutive bytes. A column is 16 bytes of channels (8 half/bfloat16, 4 float, 2 double) read
// and written as one vector where C and every pointer allow it, else one channel. blockDim.x is
// the columns rounded up to a power of two (at most the block), so that C = 256 in bfloat16 is 32
// columns by 8 rows, C = 1 is 1 column by 256 rows. The work is memory-bound: every (N, C) tensor
// is read or written once, the (R, C) ones once per ray.
//
// Sums over a ray's rows (segment_mean, the scale gradient) accumulate in acc_t per thread, then
// across y in shared memory in a fixed tree order: deterministic, no atomics. Elementwise
// outputs (ray_scale, the values gradient) need no communication.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <c10/cuda/CUDAStream.h>  // = at::cuda::getCurrentCUDAStream, without the cuSPARSE/cuBLAS headers
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>

#include <cstdint>
#include <tuple>

#include "columns.cuh"
#include "common.h"
#include "ray_layout.h"
#include "segment_ops.h"

namespace mixer_nerf {
namespace {

using composite_layout::PackedRays;
using composite_layout::RaySpan;
using columns::block_for;
using columns::Column;
using columns::kThreads;
using columns::sum_over_rows;
using columns::with_column_width;

// One thread of a ray's block ORs kBadOffsets into `invalid` if the ray's offsets are bad (no
// contention: only bad input writes).
__device__ __forceinline__ void report_bad_offsets(const PackedRays& rays, int64_t ray, int32_t* invalid) {
  if (threadIdx.x == 0 && threadIdx.y == 0 && !rays.well_formed(ray, rays.num_rays)) {
    atomicOr(invalid, segment_ops::kBadOffsets);
  }
}

template <typename scalar_t, int V>
__global__ void __launch_bounds__(kThreads)
    segment_mean_fwd_kernel(const scalar_t* values, PackedRays rays, int64_t cols, scalar_t* mean, int32_t* invalid) {
  using acc = acc_t<scalar_t>;
  using column = Column<scalar_t, V>;
  __shared__ acc scratch[V * kThreads];
  const int64_t ray = blockIdx.x;
  const RaySpan span = rays(ray);
  report_bad_offsets(rays, ray, invalid);
  const column* rows = reinterpret_cast<const column*>(values) + span.offset * cols;
  // Columns in passes of blockDim.x; every thread runs every pass (sum_over_rows synchronises).
  for (int64_t first = 0; first < cols; first += blockDim.x) {
    const int64_t c = first + threadIdx.x;
    acc sum[V] = {};
    if (c < cols) {
#pragma unroll 4
      for (int64_t i = threadIdx.y; i < span.count; i += blockDim.y) {
        const column x = rows[i * cols + c];
#pragma unroll
        for (int j = 0; j < V; ++j) sum[j] += acc(x.v[j]);
      }
    }
    sum_over_rows<acc, V>(sum, scratch);
    if (c < cols && threadIdx.y == 0) {
      column m;
#pragma unroll
      for (int j = 0; j < V; ++j) m.v[j] = static_cast<scalar_t>(span.count ? sum[j] / acc(span.count) : acc(0));
      reinterpret_cast<column*>(mean)[ray * cols + c] = m;
    }
  }
}

template <typename scalar_t, int V>
__global__ void __launch_bounds__(kThreads)
    segment_mean_bwd_kernel(const scalar_t* grad, PackedRays rays, int64_t cols, scalar_t* grad_values) {
  using acc = acc_t<scalar_t>;
  using column = Column<scalar_t, V>;
  const int64_t ray = blockIdx.x;
  const RaySpan span = rays(ray);
  if (span.count == 0) return;
  column* rows = reinterpret_cast<column*>(grad_values) + span.offset * cols;
  for (int64_t c = threadIdx.x; c < cols; c += blockDim.x) {
    const column g = reinterpret_cast<const column*>(grad)[ray * cols + c];
    column share;
#pragma unroll
    for (int j = 0; j < V; ++j) share.v[j] = static_cast<scalar_t>(acc(g.v[j]) / acc(span.count));
    for (int64_t i = threadIdx.y; i < span.count; i += blockDim.y) rows[i * cols + c] = share;
  }
}

template <typename scalar_t, int V>
__global__ void __launch_bounds__(kThreads)
    ray_scale_fwd_kernel(const scalar_t* features, const scalar_t* scale, PackedRays rays, int64_t cols, scalar_t* out,
                         int32_t* invalid) {
  using acc = acc_t<scalar_t>;
  using column = Column<scalar_t, V>;
  const int64_t ray = blockIdx.x;
  const RaySpan span = rays(ray);
  report_bad_offsets(rays, ray, invalid);  // before the return: a bad ray may clamp to no rows
  if (span.count == 0) return;
  const column* rows = reinterpret_cast<const column*>(features) + span.offset * cols;
  column* out_rows = reinterpret_cast<column*>(out) + span.offset * cols;
  for (int64_t c = threadIdx.x; c < cols; c += blockDim.x) {
    const column s = reinterpret_cast<const column*>(scale)[ray * cols + c];
#pragma unroll 4
    for (int64_t i = threadIdx.y; i < span.count; i += blockDim.y) {
      const column f = rows[i * cols + c];
      column o;
#pragma unroll
      for (int j = 0; j < V; ++j) o.v[j] = static_cast<scalar_t>(acc(f.v[j]) * acc(s.v[j]));
      out_rows[i * cols + c] = o;
    }
  }
}

template <typename scalar_t, int V>
__global__ void __launch_bounds__(kThreads)
    ray_scale_bwd_kernel(const scalar_t* grad_out, const scalar_t* features, const scalar_t* scale, PackedRays rays,
                         int64_t cols, scalar_t* grad_features, scalar_t* grad_scale) {
  using acc = acc_t<scalar_t>;
  using column = Column<scalar_t, V>;
  __shared__ acc scratch[V * kThreads];
  const int64_t ray = blockIdx.x;
  const RaySpan span = rays(ray);
  const int64_t begin = span.offset * cols;  // the ray's first column
  const column* g_rows = reinterpret_cast<const column*>(grad_out) + begin;
  const column* f_rows = reinterpret_cast<const column*>(features) + begin;
  column* df_rows = reinterpret_cast<column*>(grad_features) + begin;
  for (int64_t first = 0; first < cols; first += blockDim.x) {
    const int64_t c = first + threadIdx.x;
    acc sum[V] = {};
    if (c < cols) {
      const column s = reinterpret_cast<const column*>(scale)[ray * cols + c];
#pragma unroll 4
      for (int64_t i = threadIdx.y; i < span.count; i += blockDim.y) {
        const column g = g_rows[i * cols + c], f = f_rows[i * cols + c];
        column df;
#pragma unroll
        for (int j = 0; j < V; ++j) {
          df.v[j] = static_cast<scalar_t>(acc(g.v[j]) * acc(s.v[j]));
          sum[j] += acc(g.v[j]) * acc(f.v[j]);
        }
        df_rows[i * cols + c] = df;
      }
    }
    sum_over_rows<acc, V>(sum, scratch);
    if (c < cols && threadIdx.y == 0) {
      column ds;
#pragma unroll
      for (int j = 0; j < V; ++j) ds.v[j] = static_cast<scalar_t>(sum[j]);
      reinterpret_cast<column*>(grad_scale)[ray * cols + c] = ds;
    }
  }
}

unsigned grid_for(int64_t rays) {
  MIXER_NERF_CHECK(rays <= int64_t(INT32_MAX), "segment ops: too many rays for one launch (", rays, ")");
  return static_cast<unsigned>(rays);
}

std::tuple<at::Tensor, at::Tensor> segment_mean_fwd_cuda(const at::Tensor& values, const at::Tensor& offsets) {
  const int64_t R = segment_ops::check_rows("segment_mean_fwd", values, offsets, at::kCUDA);
  const c10::cuda::CUDAGuard device_guard(values.device());
  const int64_t N = values.size(0), C = values.size(1);
  at::Tensor mean = at::empty({R, C}, values.options());
  at::Tensor invalid = at::zeros({1}, values.options().dtype(at::kInt));
  if (R == 0) return {mean, invalid};
  MIXER_NERF_DISPATCH_FLOATING(values.scalar_type(), "segment_mean_fwd_cuda", [&] {
    const scalar_t* v = values.const_data_ptr<scalar_t>();
    scalar_t* m = mean.data_ptr<scalar_t>();
    with_column_width<scalar_t>(C, {v, m}, [&](auto width) {
      constexpr int V = decltype(width)::value;
      segment_mean_fwd_kernel<scalar_t, V><<<grid_for(R), block_for(C / V), 0, c10::cuda::getCurrentCUDAStream()>>>(
          v, PackedRays{offsets.const_data_ptr<int64_t>(), N, R}, C / V, m, invalid.data_ptr<int32_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  });
  return {mean, invalid};
}

at::Tensor segment_mean_bwd_cuda(const at::Tensor& grad, const at::Tensor& offsets, int64_t num_rows) {
  const int64_t R = segment_ops::check_rows("segment_mean_bwd", grad, offsets, at::kCUDA);
  MIXER_NERF_CHECK(grad.size(0) == R && num_rows >= 0, "segment_mean_bwd: grad must be (R, C), num_rows >= 0");
  const c10::cuda::CUDAGuard device_guard(grad.device());
  const int64_t C = grad.size(1);
  at::Tensor grad_values = at::empty({num_rows, C}, grad.options());
  if (R == 0) return grad_values;
  MIXER_NERF_DISPATCH_FLOATING(grad.scalar_type(), "segment_mean_bwd_cuda", [&] {
    const scalar_t* g = grad.const_data_ptr<scalar_t>();
    scalar_t* dv = grad_values.data_ptr<scalar_t>();
    with_column_width<scalar_t>(C, {g, dv}, [&](auto width) {
      constexpr int V = decltype(width)::value;
      segment_mean_bwd_kernel<scalar_t, V><<<grid_for(R), block_for(C / V), 0, c10::cuda::getCurrentCUDAStream()>>>(
          g, PackedRays{offsets.const_data_ptr<int64_t>(), num_rows, R}, C / V, dv);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  });
  return grad_values;
}

std::tuple<at::Tensor, at::Tensor> ray_scale_fwd_cuda(const at::Tensor& features, const at::Tensor& scale,
                                                      const at::Tensor& offsets) {
  const int64_t R = segment_ops::check_rows("ray_scale_fwd", features, offsets, at::kCUDA);
  segment_ops::check_per_ray("ray_scale_fwd", scale, features, R, at::kCUDA);
  const c10::cuda::CUDAGuard device_guard(features.device());
  const int64_t N = features.size(0), C = features.size(1);
  at::Tensor out = at::empty_like(features);
  at::Tensor invalid = at::zeros({1}, features.options().dtype(at::kInt));
  if (R == 0) return {out, invalid};
  MIXER_NERF_DISPATCH_FLOATING(features.scalar_type(), "ray_scale_fwd_cuda", [&] {
    const scalar_t* f = features.const_data_ptr<scalar_t>();
    const scalar_t* s = scale.const_data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    with_column_width<scalar_t>(C, {f, s, o}, [&](auto width) {
      constexpr int V = decltype(width)::value;
      ray_scale_fwd_kernel<scalar_t, V><<<grid_for(R), block_for(C / V), 0, c10::cuda::getCurrentCUDAStream()>>>(
          f, s, PackedRays{offsets.const_data_ptr<int64_t>(), N, R}, C / V, o, invalid.data_ptr<int32_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  });
  return {out, invalid};
}

std::tuple<at::Tensor, at::Tensor> ray_scale_bwd_cuda(const at::Tensor& grad_out, const at::Tensor& features,
                                                      const at::Tensor& scale, const at::Tensor& offsets) {
  const int64_t R = segment_ops::check_rows("ray_scale_bwd", features, offsets, at::kCUDA);
  segment_ops::check_per_ray("ray_scale_bwd", scale, features, R, at::kCUDA);
  segment_ops::check_like_rows("ray_scale_bwd", grad_out, features, at::kCUDA);
  const c10::cuda::CUDAGuard device_guard(features.device());
  const int64_t N = features.size(0), C = features.size(1);
  at::Tensor grad_features = at::empty_like(features), grad_scale = at::empty_like(scale);
  if (R == 0) return {grad_features, grad_scale};
  MIXER_NERF_DISPATCH_FLOATING(features.scalar_type(), "ray_scale_bwd_cuda", [&] {
    const scalar_t* g = grad_out.const_data_ptr<scalar_t>();
    const scalar_t* f = features.const_data_ptr<scalar_t>();
    const scalar_t* s = scale.const_data_ptr<scalar_t>();
    scalar_t* df = grad_features.data_ptr<scalar_t>();
    scalar_t* ds = grad_scale.data_ptr<scalar_t>();
    with_column_width<scalar_t>(C, {g, f, s, df, ds}, [&](auto width) {
      constexpr int V = decltype(width)::value;
      ray_scale_bwd_kernel<scalar_t, V><<<grid_for(R), block_for(C / V), 0, c10::cuda::getCurrentCUDAStream()>>>(
          g, f, s, PackedRays{offsets.const_data_ptr<int64_t>(), N, R}, C / V, df, ds);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  });
  return {grad_features, grad_scale};
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) {
  m.impl("segment_mean_fwd", &segment_mean_fwd_cuda);
  m.impl("segment_mean_bwd", &segment_mean_bwd_cuda);
  m.impl("ray_scale_fwd", &ray_scale_fwd_cuda);
  m.impl("ray_scale_bwd", &ray_scale_bwd_cuda);
}

}  // namespace mixer_nerf
