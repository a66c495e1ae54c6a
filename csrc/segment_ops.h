// What the CPU and CUDA kernels of segment_mean and ray_scale share: their host-side checks and
// the bit their forwards report bad offsets by. Python (mixer_nerf/ops/segment_ops.py) validates
// shapes first, with clear messages; these only keep a direct call of an op from reading out of
// bounds. Rows are spanned per ray by composite_layout::PackedRays (ray_layout.h), which clamps
// unchecked offsets into [0, N].
#pragma once

#include <ATen/ATen.h>

#include <cstdint>

#include "common.h"

namespace mixer_nerf {
namespace segment_ops {

// The forwards' `invalid` output (1) int32: offsets a validation would reject (not from 0 to N, or
// decreasing), found while the kernel reads them anyway, so a GPU checks them without a host sync.
enum InvalidInput : int32_t { kBadOffsets = 4 };

// rows (N, C) and offsets (R+1) int64, both on `device` (one device); returns R.
inline int64_t check_rows(const char* op, const at::Tensor& rows, const at::Tensor& offsets, at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(rows, device);
  MIXER_NERF_CHECK_INPUT(offsets, device);
  MIXER_NERF_CHECK(rows.dim() == 2, op, ": rows must be (N, C), got ", rows.sizes());
  MIXER_NERF_CHECK(offsets.scalar_type() == at::kLong && offsets.dim() == 1 && offsets.size(0) >= 1, op,
                   ": offsets must be (R+1) int64");
  MIXER_NERF_CHECK(offsets.device() == rows.device(), op, ": offsets on ", offsets.device(), ", rows on ",
                   rows.device());
  return offsets.size(0) - 1;
}

// A per-ray tensor (R, C) like `rows` in dtype and device.
inline void check_per_ray(const char* op, const at::Tensor& per_ray, const at::Tensor& rows, int64_t rays,
                          at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(per_ray, device);
  MIXER_NERF_CHECK(per_ray.device() == rows.device(), op, ": tensors on ", per_ray.device(), " and ", rows.device());
  MIXER_NERF_CHECK(per_ray.scalar_type() == rows.scalar_type(), op, ": dtype ", per_ray.scalar_type(), " vs ",
                   rows.scalar_type());
  MIXER_NERF_CHECK(per_ray.dim() == 2 && per_ray.size(0) == rays && per_ray.size(1) == rows.size(1), op,
                   ": per-ray tensor of shape ", per_ray.sizes(), ", expected [", rays, ", ", rows.size(1), "]");
}

// A per-row tensor (N, C) like `rows` (an upstream gradient, say).
inline void check_like_rows(const char* op, const at::Tensor& t, const at::Tensor& rows, at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(t, device);
  MIXER_NERF_CHECK(t.device() == rows.device(), op, ": tensors on ", t.device(), " and ", rows.device());
  MIXER_NERF_CHECK(t.scalar_type() == rows.scalar_type(), op, ": dtype ", t.scalar_type(), " vs ", rows.scalar_type());
  MIXER_NERF_CHECK(t.sizes() == rows.sizes(), op, ": shape ", t.sizes(), " vs ", rows.sizes());
}

}  // namespace segment_ops
}  // namespace mixer_nerf
