// Host-side glue shared by the CPU and CUDA ray-marching kernels (ray_marching.cpp,
// cuda/ray_marching.cu): defensive input checks and the raw-pointer view of the tensors.
#pragma once

#include <ATen/ATen.h>

#include <cmath>
#include <limits>
#include <optional>
#include <tuple>

#include "common.h"
#include "ray_layout.h"
#include "ray_marching_math.h"

namespace mixer_nerf {

// Arithmetic type of the march: float for half/bfloat16/float rays, double for double.
inline at::ScalarType ray_marching_acc_type(at::ScalarType rays) {
  return rays == at::kDouble ? at::kDouble : at::kFloat;
}

inline void check_ray_marching_inputs(const at::Tensor& rays_o, const at::Tensor& rays_d, const at::Tensor& near,
                                      const at::Tensor& far, const std::optional<at::Tensor>& jitter,
                                      const at::Tensor& bitfield, const at::Tensor& aabb,
                                      at::IntArrayRef resolution, double step_size, double cone_angle,
                                      std::optional<int64_t> max_samples_per_ray, std::optional<int64_t> capacity,
                                      c10::DeviceType dev) {
  MIXER_NERF_CHECK_INPUT(rays_o, dev);
  MIXER_NERF_CHECK_INPUT(rays_d, dev);
  MIXER_NERF_CHECK_INPUT(near, dev);
  MIXER_NERF_CHECK_INPUT(far, dev);
  MIXER_NERF_CHECK_INPUT(bitfield, dev);
  MIXER_NERF_CHECK_INPUT(aabb, dev);
  const int64_t R = rays_o.size(0);
  MIXER_NERF_CHECK(rays_o.dim() == 2 && rays_o.size(1) == 3, "rays_o must be (R, 3)");
  MIXER_NERF_CHECK(rays_d.sizes() == rays_o.sizes(), "rays_d must be (R, 3) like rays_o");
  MIXER_NERF_CHECK(near.dim() == 1 && near.size(0) == R && far.dim() == 1 && far.size(0) == R, "near, far must be (R)");
  const auto dtype = rays_o.scalar_type();
  MIXER_NERF_CHECK(rays_d.scalar_type() == dtype && near.scalar_type() == dtype && far.scalar_type() == dtype,
              "rays_o, rays_d, near, far must share one dtype");
  if (jitter) {
    MIXER_NERF_CHECK_INPUT(*jitter, dev);
    MIXER_NERF_CHECK(jitter->dim() == 1 && jitter->size(0) == R && jitter->scalar_type() == dtype,
                "jitter must be (R) with the dtype of rays_o");
  }
  MIXER_NERF_CHECK(resolution.size() == 3 && resolution[0] > 0 && resolution[1] > 0 && resolution[2] > 0,
              "resolution must be 3 positive sizes");
  MIXER_NERF_CHECK(bitfield.scalar_type() == at::kByte && bitfield.dim() == 1 &&
                  bitfield.size(0) * 8 >= resolution[0] * resolution[1] * resolution[2],
              "bitfield must be uint8 with one bit per cell");
  MIXER_NERF_CHECK(aabb.numel() == 6 && aabb.scalar_type() == ray_marching_acc_type(dtype),
              "aabb must hold 6 values of the march's arithmetic type (float32, or float64 for float64 rays)");
  MIXER_NERF_CHECK(step_size > 0 && std::isfinite(step_size), "step_size must be positive and finite");
  MIXER_NERF_CHECK(cone_angle >= 0 && std::isfinite(cone_angle), "cone_angle must be non-negative and finite");
  MIXER_NERF_CHECK(!max_samples_per_ray || *max_samples_per_ray >= 1, "max_samples_per_ray must be >= 1");
  MIXER_NERF_CHECK(!capacity || *capacity >= 0, "capacity must be >= 0");
}

// transmittance_filter_fwd: filter_by_transmittance's mask (mixer_nerf/ops/ray_marching.py), one ray at a time:
// with tau_i = sigma_i (t_end_i - t_start_i) in double (NaN as 0, +inf as the largest double, at least 0),
// sample i is kept while the ray's optical depth before it is <= limit = -log(threshold) (threshold > 0),
// and, with alpha_threshold > 0, where 1 - exp(-tau_i) >= alpha_threshold. Each term of the depth is capped
// at limit + 1 (no decision changes: one such term already ends the ray). Rows past offsets[R] belong to
// no ray and are dropped.
template <typename scalar_t>
struct TransmittanceFilter {
  const scalar_t* sigmas;
  const scalar_t* t_starts;
  const scalar_t* t_ends;
  const int64_t* offsets;  // (R + 1), clamped into [0, N] here
  bool* keep;
  int64_t R, N;
  double limit;            // -log(threshold); +inf without early termination
  double alpha_threshold;  // 0: no alpha test

  C10_HOST_DEVICE int64_t offset(int64_t r) const { return composite_layout::PackedRays::clamp(offsets[r], 0, N); }
  C10_HOST_DEVICE double tau(int64_t i) const {
    // the gap rounded to scalar_t, as the reference's
    const double t = double(sigmas[i]) * double(scalar_t(t_ends[i] - t_starts[i]));
    if (t != t) return 0.0;
    return t > 1.7976931348623157e308 ? 1.7976931348623157e308 : (t < 0 ? 0.0 : t);
  }
  // Ray r's rows; `keep` starts all false, so rows no ray covers stay dropped.
  C10_HOST_DEVICE void ray(int64_t r) const {
    double depth = 0;
    for (int64_t i = offset(r), end = offset(r + 1); i < end; ++i) {
      const double t = tau(i);
      keep[i] = depth <= limit && (alpha_threshold <= 0 || -::expm1(-t) >= alpha_threshold);
      depth += t < limit + 1 ? t : limit + 1;
    }
  }
};

// The filter's inputs checked (sigmas, t_starts, t_ends (N) of one floating dtype, offsets (R + 1) int64, all
// on `dev`) and its output, all false.
template <typename scalar_t>
TransmittanceFilter<scalar_t> transmittance_filter(const at::Tensor& sigmas, const at::Tensor& t_starts,
                                                   const at::Tensor& t_ends, const at::Tensor& offsets,
                                                   double threshold, double alpha_threshold, const at::Tensor& keep) {
  return {sigmas.const_data_ptr<scalar_t>(), t_starts.const_data_ptr<scalar_t>(), t_ends.const_data_ptr<scalar_t>(),
          offsets.const_data_ptr<int64_t>(), keep.data_ptr<bool>(), offsets.size(0) - 1, sigmas.size(0),
          threshold > 0 ? -std::log(threshold) : std::numeric_limits<double>::infinity(), alpha_threshold};
}

inline at::Tensor check_transmittance_filter(const at::Tensor& sigmas, const at::Tensor& t_starts,
                                             const at::Tensor& t_ends, const at::Tensor& offsets, double threshold,
                                             double alpha_threshold, at::DeviceType dev) {
  MIXER_NERF_CHECK_INPUT(sigmas, dev);
  MIXER_NERF_CHECK_INPUT(t_starts, dev);
  MIXER_NERF_CHECK_INPUT(t_ends, dev);
  MIXER_NERF_CHECK_INPUT(offsets, dev);
  MIXER_NERF_CHECK(sigmas.dim() == 1 && t_starts.sizes() == sigmas.sizes() && t_ends.sizes() == sigmas.sizes() &&
                       t_starts.scalar_type() == sigmas.scalar_type() && t_ends.scalar_type() == sigmas.scalar_type(),
                   "transmittance_filter_fwd: sigmas, t_starts, t_ends must be (N) of one dtype");
  MIXER_NERF_CHECK(offsets.scalar_type() == at::kLong && offsets.dim() == 1 && offsets.size(0) >= 1 &&
                       offsets.device() == sigmas.device(),
                   "transmittance_filter_fwd: offsets must be (R+1) int64 on the device of sigmas");
  MIXER_NERF_CHECK(threshold >= 0 && threshold <= 1 && alpha_threshold >= 0 && alpha_threshold <= 1,
                   "transmittance_filter_fwd: thresholds must lie in [0, 1]");
  return at::zeros({sigmas.size(0)}, sigmas.options().dtype(at::kBool));
}

// select_fixed_fwd: PackedSamples.select_fixed (mixer_nerf/ops/ray_marching.py) without a host sync. With
// `end` = offsets[R] (clamped into [0, N]) and `before[i]` the kept rows among rows < i (i <= end), kept row
// i < end goes to row before[i] of `capacity` rows if it fits; rows from total = before[end] on are zero;
// offsets become min(before[offsets[r]], capacity). `inclusive` is the running count of `keep` over all N rows
// (rows past end do not change it below end). Item j of max(N, capacity, R + 1) does row j's share of each.
template <typename scalar_t>
struct SelectFixed {
  const bool* keep;
  const int64_t* inclusive;  // (N)
  const scalar_t* t_starts;
  const scalar_t* t_ends;
  const int64_t* ray_indices;
  const int64_t* offsets;  // (R + 1)
  scalar_t* out_t_starts;  // (capacity)
  scalar_t* out_t_ends;
  int64_t* out_ray_indices;
  int64_t* out_offsets;  // (R + 1)
  int64_t* total;        // (1)
  int64_t R, N, capacity;

  C10_HOST_DEVICE int64_t items() const {
    const int64_t a = N > capacity ? N : capacity;
    return a > R + 1 ? a : R + 1;
  }
  C10_HOST_DEVICE int64_t clamp_row(int64_t o) const { return composite_layout::PackedRays::clamp(o, 0, N); }
  C10_HOST_DEVICE int64_t before(int64_t i) const { return i == 0 ? 0 : inclusive[i - 1]; }
  C10_HOST_DEVICE void write(int64_t j) const {
    const int64_t end = clamp_row(offsets[R]), kept = before(end);
    if (j < N && j < end && keep[j]) {
      const int64_t place = before(j);
      if (place < capacity) {
        out_t_starts[place] = t_starts[j];
        out_t_ends[place] = t_ends[j];
        out_ray_indices[place] = ray_indices[j];
      }
    }
    if (j < capacity && j >= kept) {
      out_t_starts[j] = scalar_t(0);
      out_t_ends[j] = scalar_t(0);
      out_ray_indices[j] = 0;
    }
    if (j <= R) {
      const int64_t row = clamp_row(offsets[j]), o = before(row < end ? row : end);
      out_offsets[j] = o < capacity ? o : capacity;
    }
    if (j == 0) *total = kept;
  }
};

using SelectFixedOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

// select_fixed_fwd's checks, outputs (t_starts, t_ends, ray_indices, offsets, total) and the running count of
// `keep`, then `launch(SelectFixed<scalar_t>)` in the samples' dtype.
template <typename Launch>
SelectFixedOutputs select_fixed(const at::Tensor& keep, const at::Tensor& t_starts, const at::Tensor& t_ends,
                                const at::Tensor& ray_indices, const at::Tensor& offsets, int64_t capacity,
                                at::DeviceType dev, Launch&& launch) {
  MIXER_NERF_CHECK_INPUT(keep, dev);
  MIXER_NERF_CHECK_INPUT(t_starts, dev);
  MIXER_NERF_CHECK_INPUT(t_ends, dev);
  MIXER_NERF_CHECK_INPUT(ray_indices, dev);
  MIXER_NERF_CHECK_INPUT(offsets, dev);
  const int64_t N = keep.size(0);
  MIXER_NERF_CHECK(keep.scalar_type() == at::kBool && keep.dim() == 1 && t_starts.sizes() == keep.sizes() &&
                       t_ends.sizes() == keep.sizes() && ray_indices.sizes() == keep.sizes() &&
                       t_ends.scalar_type() == t_starts.scalar_type() && ray_indices.scalar_type() == at::kLong,
                   "select_fixed_fwd: keep (N) bool, t_starts and t_ends (N) of one dtype, ray_indices (N) int64");
  MIXER_NERF_CHECK(offsets.scalar_type() == at::kLong && offsets.dim() == 1 && offsets.size(0) >= 1,
                   "select_fixed_fwd: offsets must be (R+1) int64");
  MIXER_NERF_CHECK(capacity >= 0, "select_fixed_fwd: capacity must be >= 0");
  const at::Tensor inclusive = at::cumsum(keep, 0, at::kLong);
  const at::Tensor starts = at::empty({capacity}, t_starts.options()), ends = at::empty({capacity}, t_ends.options()),
                   rays = at::empty({capacity}, ray_indices.options()), new_offsets = at::empty_like(offsets),
                   total = at::empty({1}, offsets.options());
  MIXER_NERF_DISPATCH_FLOATING(t_starts.scalar_type(), "select_fixed_fwd", [&] {
    launch(SelectFixed<scalar_t>{keep.const_data_ptr<bool>(), inclusive.const_data_ptr<int64_t>(),
                                 t_starts.const_data_ptr<scalar_t>(), t_ends.const_data_ptr<scalar_t>(),
                                 ray_indices.const_data_ptr<int64_t>(), offsets.const_data_ptr<int64_t>(),
                                 starts.data_ptr<scalar_t>(), ends.data_ptr<scalar_t>(), rays.data_ptr<int64_t>(),
                                 new_offsets.data_ptr<int64_t>(), total.data_ptr<int64_t>(), offsets.size(0) - 1, N,
                                 capacity});
  });
  return {starts, ends, rays, new_offsets, total};
}

// padding_rays_fwd: FixedSamples.with_padding_rays's layout (mixer_nerf/ops/ray_marching.py), made
// where the rows are, without reading their count back. With `end` = offsets[R] (clamped into [0, N]),
// row i >= end belongs to padding ray R + (i - end) / rows_per_ray, and padding ray k = 1..P ends at
// min(end + k * rows_per_ray, N). Item j of max(N, R + 1 + P) writes row j's ray and offset j.
struct PaddingLayout {
  const int64_t* offsets;      // (R + 1)
  const int64_t* ray_indices;  // (N)
  int64_t* out_ray_indices;    // (N)
  int64_t* out_offsets;        // (R + 1 + P)
  int64_t R, N, P, rows_per_ray;

  C10_HOST_DEVICE int64_t items() const { return N > R + 1 + P ? N : R + 1 + P; }
  C10_HOST_DEVICE int64_t end() const { return composite_layout::PackedRays::clamp(offsets[R], 0, N); }
  C10_HOST_DEVICE void write(int64_t j, int64_t end) const {
    if (j < N) out_ray_indices[j] = j < end ? ray_indices[j] : R + (j - end) / rows_per_ray;
    if (j <= R) {
      out_offsets[j] = offsets[j];
    } else if (j < R + 1 + P) {
      const int64_t e = end + (j - R) * rows_per_ray;
      out_offsets[j] = e < N ? e : N;
    }
  }
};

// offsets (R + 1) and ray_indices (N) int64 on `dev`; the layout with ceil(N / rows_per_ray) padding rays.
inline PaddingLayout padding_layout(const at::Tensor& offsets, const at::Tensor& ray_indices, int64_t rows_per_ray,
                                    at::Tensor& out_ray_indices, at::Tensor& out_offsets, at::DeviceType dev) {
  MIXER_NERF_CHECK_INPUT(offsets, dev);
  MIXER_NERF_CHECK_INPUT(ray_indices, dev);
  MIXER_NERF_CHECK(offsets.scalar_type() == at::kLong && offsets.dim() == 1 && offsets.size(0) >= 1 &&
                       ray_indices.scalar_type() == at::kLong && ray_indices.dim() == 1 &&
                       offsets.device() == ray_indices.device(),
                   "padding_rays_fwd: offsets (R+1) and ray_indices (N) must be int64 on one device");
  MIXER_NERF_CHECK(rows_per_ray >= 1, "padding_rays_fwd: rows_per_ray must be >= 1");
  const int64_t R = offsets.size(0) - 1, N = ray_indices.size(0), P = (N + rows_per_ray - 1) / rows_per_ray;
  out_ray_indices = at::empty({N}, ray_indices.options());
  out_offsets = at::empty({R + 1 + P}, offsets.options());
  return {offsets.const_data_ptr<int64_t>(), ray_indices.const_data_ptr<int64_t>(),
          out_ray_indices.data_ptr<int64_t>(), out_offsets.data_ptr<int64_t>(), R, N, P, rows_per_ray};
}

// An output of `rows` samples; with a capacity its rows past the samples stay zero (zero-length
// intervals at t = 0 of ray 0).
inline at::Tensor padded_rows(int64_t rows, std::optional<int64_t> capacity, const at::TensorOptions& options) {
  return capacity ? at::zeros({rows}, options) : at::empty({rows}, options);
}

template <typename scalar_t, typename T>
ray_marching_math::MarchInputs<scalar_t, T> march_inputs(const at::Tensor& rays_o, const at::Tensor& rays_d,
                                                         const at::Tensor& near, const at::Tensor& far,
                                                         const std::optional<at::Tensor>& jitter,
                                                         const at::Tensor& bitfield, const at::Tensor& aabb,
                                                         at::IntArrayRef resolution, double step_size,
                                                         double cone_angle, std::optional<int64_t> max_samples) {
  return {rays_o.data_ptr<scalar_t>(),
          rays_d.data_ptr<scalar_t>(),
          near.data_ptr<scalar_t>(),
          far.data_ptr<scalar_t>(),
          jitter ? jitter->data_ptr<scalar_t>() : nullptr,
          bitfield.data_ptr<uint8_t>(),
          aabb.data_ptr<T>(),
          {resolution[0], resolution[1], resolution[2]},
          T(step_size),
          T(cone_angle),
          max_samples.value_or(std::numeric_limits<int64_t>::max())};
}

}  // namespace mixer_nerf
