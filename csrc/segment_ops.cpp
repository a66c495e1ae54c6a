// segment_mean and ray_scale on the CPU: the squeeze and the excitation of squeeze-and-excitation
// on packed samples (mixer_nerf/model/squeeze_excitation.py). Ray r owns rows
// offsets[r]:offsets[r+1] of an (N, C) tensor; with n_r rows, g the upstream gradient:
//
//   segment_mean:  m_r = (1 / n_r) sum_{i in r} v_i   (0 for a ray with no row)
//                  dv_i = g_{ray(i)} / n_{ray(i)}
//   ray_scale:     out_i = f_i * s_{ray(i)}
//                  df_i = g_i * s_{ray(i)},   ds_r = sum_{i in r} g_i * f_i
//
// Every kernel walks one ray's rows, rays in parallel: each output row has one writer and every
// sum is taken in row order, so results are deterministic (no atomics) and independent of the
// thread count. Sums accumulate in acc_t (float for half/bfloat16/float, double for double) and
// are rounded to the input dtype once; products are formed in acc_t too, so a bfloat16 output is
// the correctly rounded product, as torch's own bfloat16 multiply gives. The CUDA kernels
// (csrc/cuda/segment_ops.cu) compute the same sums, in another (fixed) order.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <tuple>
#include <vector>

#include "common.h"
#include "ray_layout.h"
#include "segment_ops.h"

namespace mixer_nerf {
namespace {

using composite_layout::PackedRays;
using composite_layout::RaySpan;

// Rays per parallel task: about 16k elements each, so short rays do not each pay a task.
int64_t ray_grain(int64_t elements, int64_t rays) {
  return std::max<int64_t>(1, 16384 * std::max<int64_t>(1, rays) / std::max<int64_t>(1, elements));
}

// The forwards' `invalid` output, the kBadOffsets bit OR-ed in by any ray whose offsets are bad.
struct OffsetsFinding {
  std::atomic<int32_t> bits{0};
  void check(const PackedRays& rays, int64_t ray) {
    if (!rays.well_formed(ray, rays.num_rays)) bits.fetch_or(segment_ops::kBadOffsets, std::memory_order_relaxed);
  }
  at::Tensor tensor(const at::Tensor& like) const { return at::full({1}, bits.load(), like.options().dtype(at::kInt)); }
};

std::tuple<at::Tensor, at::Tensor> segment_mean_fwd_cpu(const at::Tensor& values, const at::Tensor& offsets) {
  const int64_t R = segment_ops::check_rows("segment_mean_fwd", values, offsets, at::kCPU);
  const int64_t N = values.size(0), C = values.size(1);
  at::Tensor out = at::empty({R, C}, values.options());
  OffsetsFinding finding;
  MIXER_NERF_DISPATCH_FLOATING(values.scalar_type(), "segment_mean_fwd_cpu", [&] {
    using acc = acc_t<scalar_t>;
    const PackedRays rays{offsets.const_data_ptr<int64_t>(), N, R};
    const scalar_t* v = values.const_data_ptr<scalar_t>();
    scalar_t* mean = out.data_ptr<scalar_t>();
    at::parallel_for(0, R, ray_grain(N * C, R), [&](int64_t begin, int64_t end) {
      std::vector<acc> sum(C);
      for (int64_t r = begin; r < end; ++r) {
        const RaySpan span = rays(r);
        finding.check(rays, r);
        std::fill(sum.begin(), sum.end(), acc(0));
        for (int64_t i = span.offset; i < span.offset + span.count; ++i) {
          for (int64_t c = 0; c < C; ++c) sum[c] += acc(v[i * C + c]);
        }
        for (int64_t c = 0; c < C; ++c) {
          mean[r * C + c] = static_cast<scalar_t>(span.count ? sum[c] / acc(span.count) : acc(0));
        }
      }
    });
  });
  return {out, finding.tensor(values)};
}

at::Tensor segment_mean_bwd_cpu(const at::Tensor& grad, const at::Tensor& offsets, int64_t num_rows) {
  const int64_t R = segment_ops::check_rows("segment_mean_bwd", grad, offsets, at::kCPU);
  MIXER_NERF_CHECK(grad.size(0) == R && num_rows >= 0, "segment_mean_bwd: grad must be (R, C), num_rows >= 0");
  const int64_t C = grad.size(1);
  at::Tensor grad_values = at::empty({num_rows, C}, grad.options());
  MIXER_NERF_DISPATCH_FLOATING(grad.scalar_type(), "segment_mean_bwd_cpu", [&] {
    using acc = acc_t<scalar_t>;
    const PackedRays rays{offsets.const_data_ptr<int64_t>(), num_rows, R};
    const scalar_t* g = grad.const_data_ptr<scalar_t>();
    scalar_t* dv = grad_values.data_ptr<scalar_t>();
    at::parallel_for(0, R, ray_grain(num_rows * C, R), [&](int64_t begin, int64_t end) {
      std::vector<scalar_t> row(C);
      for (int64_t r = begin; r < end; ++r) {
        const RaySpan span = rays(r);
        if (span.count == 0) continue;
        for (int64_t c = 0; c < C; ++c) row[c] = static_cast<scalar_t>(acc(g[r * C + c]) / acc(span.count));
        for (int64_t i = span.offset; i < span.offset + span.count; ++i) std::copy(row.begin(), row.end(), dv + i * C);
      }
    });
  });
  return grad_values;
}

std::tuple<at::Tensor, at::Tensor> ray_scale_fwd_cpu(const at::Tensor& features, const at::Tensor& scale,
                                                     const at::Tensor& offsets) {
  const int64_t R = segment_ops::check_rows("ray_scale_fwd", features, offsets, at::kCPU);
  segment_ops::check_per_ray("ray_scale_fwd", scale, features, R, at::kCPU);
  const int64_t N = features.size(0), C = features.size(1);
  at::Tensor out = at::empty_like(features);
  OffsetsFinding finding;
  MIXER_NERF_DISPATCH_FLOATING(features.scalar_type(), "ray_scale_fwd_cpu", [&] {
    using acc = acc_t<scalar_t>;
    const PackedRays rays{offsets.const_data_ptr<int64_t>(), N, R};
    const scalar_t* f = features.const_data_ptr<scalar_t>();
    const scalar_t* s = scale.const_data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    at::parallel_for(0, R, ray_grain(N * C, R), [&](int64_t begin, int64_t end) {
      for (int64_t r = begin; r < end; ++r) {
        const RaySpan span = rays(r);
        finding.check(rays, r);
        const scalar_t* s_r = s + r * C;
        for (int64_t i = span.offset; i < span.offset + span.count; ++i) {
          for (int64_t c = 0; c < C; ++c) o[i * C + c] = static_cast<scalar_t>(acc(f[i * C + c]) * acc(s_r[c]));
        }
      }
    });
  });
  return {out, finding.tensor(features)};
}

std::tuple<at::Tensor, at::Tensor> ray_scale_bwd_cpu(const at::Tensor& grad_out, const at::Tensor& features,
                                                     const at::Tensor& scale, const at::Tensor& offsets) {
  const int64_t R = segment_ops::check_rows("ray_scale_bwd", features, offsets, at::kCPU);
  segment_ops::check_per_ray("ray_scale_bwd", scale, features, R, at::kCPU);
  segment_ops::check_like_rows("ray_scale_bwd", grad_out, features, at::kCPU);
  const int64_t N = features.size(0), C = features.size(1);
  at::Tensor grad_features = at::empty_like(features), grad_scale = at::empty_like(scale);
  MIXER_NERF_DISPATCH_FLOATING(features.scalar_type(), "ray_scale_bwd_cpu", [&] {
    using acc = acc_t<scalar_t>;
    const PackedRays rays{offsets.const_data_ptr<int64_t>(), N, R};
    const scalar_t* g = grad_out.const_data_ptr<scalar_t>();
    const scalar_t* f = features.const_data_ptr<scalar_t>();
    const scalar_t* s = scale.const_data_ptr<scalar_t>();
    scalar_t* df = grad_features.data_ptr<scalar_t>();
    scalar_t* ds = grad_scale.data_ptr<scalar_t>();
    at::parallel_for(0, R, ray_grain(N * C, R), [&](int64_t begin, int64_t end) {
      std::vector<acc> sum(C);
      for (int64_t r = begin; r < end; ++r) {
        const RaySpan span = rays(r);
        const scalar_t* s_r = s + r * C;
        std::fill(sum.begin(), sum.end(), acc(0));
        for (int64_t i = span.offset; i < span.offset + span.count; ++i) {
          for (int64_t c = 0; c < C; ++c) {
            const acc g_ic = acc(g[i * C + c]);
            df[i * C + c] = static_cast<scalar_t>(g_ic * acc(s_r[c]));
            sum[c] += g_ic * acc(f[i * C + c]);
          }
        }
        for (int64_t c = 0; c < C; ++c) ds[r * C + c] = static_cast<scalar_t>(sum[c]);
      }
    });
  });
  return {grad_features, grad_scale};
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CPU, m) {
  m.impl("segment_mean_fwd", &segment_mean_fwd_cpu);
  m.impl("segment_mean_bwd", &segment_mean_bwd_cpu);
  m.impl("ray_scale_fwd", &ray_scale_fwd_cpu);
  m.impl("ray_scale_bwd", &ray_scale_bwd_cpu);
}

}  // namespace mixer_nerf
