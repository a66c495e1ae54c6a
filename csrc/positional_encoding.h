// What the CPU and CUDA kernels of positional_encoding share: their host-side checks. Python
// (mixer_nerf/ops/positional_encoding.py) validates first, with clear messages; these only keep a
// direct call of an op from reading out of bounds.
#pragma once

#include <ATen/ATen.h>

#include <cstdint>
#include <vector>

#include "common.h"

namespace mixer_nerf {
namespace positional_encoding {

// x (..., D) with D > 0 on `device`, num_freqs >= 0.
inline void check_args(const at::Tensor& x, int64_t num_freqs, at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(x, device);
  MIXER_NERF_CHECK(x.dim() >= 1 && x.size(-1) > 0, "x must have shape (..., D) with D > 0, got ", x.sizes());
  MIXER_NERF_CHECK(num_freqs >= 0, "num_freqs must be non-negative, got ", num_freqs);
}

// The shape of x's encoding: x's, with the last dimension `width`.
inline std::vector<int64_t> encoded_shape(const at::Tensor& x, int64_t width) {
  std::vector<int64_t> shape = x.sizes().vec();
  shape.back() = width;
  return shape;
}

// The upstream gradient of x's encoding: its shape, x's dtype and device.
inline void check_grad_out(const at::Tensor& grad_out, const at::Tensor& x, int64_t width, at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(grad_out, device);
  const std::vector<int64_t> shape = encoded_shape(x, width);
  MIXER_NERF_CHECK(grad_out.sizes().vec() == shape, "grad_out must have shape ", shape, ", got ", grad_out.sizes());
  MIXER_NERF_CHECK(grad_out.scalar_type() == x.scalar_type(), "grad_out must have the dtype of x");
  MIXER_NERF_CHECK(grad_out.device() == x.device(), "grad_out must be on the device of x");
}

}  // namespace positional_encoding
}  // namespace mixer_nerf
