// ray_marching on the CPU: rays in parallel, two passes (count the kept samples of every ray,
// exclusive scan into offsets, march again writing them; into `capacity` rows when given). The march itself is in
// ray_marching_math.h, shared with the CUDA kernel. Not differentiable: no backward.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <optional>
#include <tuple>

#include "common.h"
#include "ray_marching.h"
#include "ray_marching_math.h"

namespace mixer_nerf {
namespace {

using namespace ray_marching_math;

// A ray costs from a handful of cell lookups (a miss) to a few hundred samples.
constexpr int64_t kRayGrain = 64;

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> ray_marching_fwd_cpu(
    const at::Tensor& rays_o, const at::Tensor& rays_d, const at::Tensor& near, const at::Tensor& far,
    const std::optional<at::Tensor>& jitter, const at::Tensor& bitfield, const at::Tensor& aabb,
    at::IntArrayRef resolution, double step_size, double cone_angle, std::optional<int64_t> max_samples_per_ray,
    std::optional<int64_t> capacity) {
  check_ray_marching_inputs(rays_o, rays_d, near, far, jitter, bitfield, aabb, resolution, step_size, cone_angle,
                            max_samples_per_ray, capacity, at::kCPU);
  const int64_t R = rays_o.size(0);
  const auto index_options = rays_o.options().dtype(at::kLong);
  at::Tensor offsets = at::zeros({R + 1}, index_options);
  at::Tensor t_starts, t_ends, ray_indices, total;
  MIXER_NERF_DISPATCH_FLOATING(rays_o.scalar_type(), "ray_marching_fwd_cpu", [&] {
    using T = acc_t<scalar_t>;
    const auto in = march_inputs<scalar_t, T>(rays_o, rays_d, near, far, jitter, bitfield, aabb, resolution,
                                              step_size, cone_angle, max_samples_per_ray);
    int64_t* counts = offsets.data_ptr<int64_t>() + 1;
    at::parallel_for(0, R, kRayGrain, [&](int64_t begin, int64_t end) {
      CountOnly<T> count;
      for (int64_t r = begin; r < end; ++r) counts[r] = in.march(r, count);
    });
    for (int64_t r = 1; r < R; ++r) counts[r] += counts[r - 1];  // counts become offsets[1:]
    total = offsets.narrow(0, R, 1).clone();
    const int64_t rows = capacity.value_or(total.item<int64_t>());
    t_starts = padded_rows(rows, capacity, rays_o.options());
    t_ends = padded_rows(rows, capacity, rays_o.options());
    ray_indices = padded_rows(rows, capacity, index_options);
    const int64_t* first = offsets.data_ptr<int64_t>();
    const int64_t cap = capacity.value_or(-1);
    at::parallel_for(0, R, kRayGrain, [&](int64_t begin, int64_t end) {
      for (int64_t r = begin; r < end; ++r) {
        WriteSamples<scalar_t, T> write{t_starts.data_ptr<scalar_t>(), t_ends.data_ptr<scalar_t>(),
                                        ray_indices.data_ptr<int64_t>(), first[r], rows_before(first[r], cap), r};
        in.march(r, write);
      }
    });
  });
  if (capacity) offsets.clamp_max_(*capacity);
  return {t_starts, t_ends, ray_indices, offsets, total};
}

at::Tensor transmittance_filter_fwd_cpu(const at::Tensor& sigmas, const at::Tensor& t_starts, const at::Tensor& t_ends,
                                        const at::Tensor& offsets, double threshold, double alpha_threshold) {
  at::Tensor keep = check_transmittance_filter(sigmas, t_starts, t_ends, offsets, threshold, alpha_threshold, at::kCPU);
  MIXER_NERF_DISPATCH_FLOATING(sigmas.scalar_type(), "transmittance_filter_fwd_cpu", [&] {
    const auto filter =
        transmittance_filter<scalar_t>(sigmas, t_starts, t_ends, offsets, threshold, alpha_threshold, keep);
    at::parallel_for(0, filter.R, kRayGrain, [&](int64_t first, int64_t last) {
      for (int64_t r = first; r < last; ++r) filter.ray(r);
    });
  });
  return keep;
}

SelectFixedOutputs select_fixed_fwd_cpu(const at::Tensor& keep, const at::Tensor& t_starts, const at::Tensor& t_ends,
                                        const at::Tensor& ray_indices, const at::Tensor& offsets, int64_t capacity) {
  return select_fixed(keep, t_starts, t_ends, ray_indices, offsets, capacity, at::kCPU, [](const auto& select) {
    at::parallel_for(0, select.items(), 4096, [&](int64_t first, int64_t last) {
      for (int64_t j = first; j < last; ++j) select.write(j);
    });
  });
}

std::tuple<at::Tensor, at::Tensor> padding_rays_fwd_cpu(const at::Tensor& offsets, const at::Tensor& ray_indices,
                                                        int64_t rows_per_ray) {
  at::Tensor out_ray_indices, out_offsets;
  const PaddingLayout layout =
      padding_layout(offsets, ray_indices, rows_per_ray, out_ray_indices, out_offsets, at::kCPU);
  const int64_t end = layout.end();
  at::parallel_for(0, layout.items(), 4096, [&](int64_t first, int64_t last) {
    for (int64_t j = first; j < last; ++j) layout.write(j, end);
  });
  return {out_ray_indices, out_offsets};
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CPU, m) {
  m.impl("ray_marching_fwd", &ray_marching_fwd_cpu);
  m.impl("padding_rays_fwd", &padding_rays_fwd_cpu);
  m.impl("transmittance_filter_fwd", &transmittance_filter_fwd_cpu);
  m.impl("select_fixed_fwd", &select_fixed_fwd_cpu);
}

}  // namespace mixer_nerf
