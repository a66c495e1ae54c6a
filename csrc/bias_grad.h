// What the CPU and CUDA kernels of bias_grad and relu_bias_bwd share: the host-side checks, the
// ops themselves around each device's column sums, and the band of rows each partial sum covers.
// The callers are ops.linear / ops.linear_relu's backward (mixer_nerf/ops/linear_relu.py), which
// hand over contiguous tensors of one dtype.
#pragma once

#include <ATen/ATen.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <tuple>

#include "common.h"

namespace mixer_nerf {
namespace bias_grad {

// grad (N, C) floating, contiguous, on `device`; `out` (relu_bias_bwd's ReLU output) like it.
inline void check_args(const char* op, const at::Tensor& grad, const at::Tensor* out, at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(grad, device);
  MIXER_NERF_CHECK(grad.dim() == 2 && at::isFloatingType(grad.scalar_type()), op,
                   ": grad must be a floating (N, C) tensor, got ", grad.sizes());
  if (out != nullptr) {
    MIXER_NERF_CHECK_INPUT((*out), device);
    MIXER_NERF_CHECK(out->device() == grad.device() && out->scalar_type() == grad.scalar_type() &&
                         out->sizes() == grad.sizes(),
                     op, ": out must be like grad (", grad.sizes(), "), got ", out->sizes());
  }
}

// Rows per partial sum: bands of a fixed height, so that the CPU's sums do not depend on its
// thread count; the GPU takes taller bands where there are more than `max_bands` of them.
constexpr int64_t kBandRows = 256;

inline int64_t band_rows(int64_t N, int64_t max_bands) {
  const int64_t bands = std::min(std::max<int64_t>((N + kBandRows - 1) / kBandRows, 1), max_bands);
  return std::max<int64_t>((N + bands - 1) / bands, 1);
}

// The two ops of one device: the shared checks, then Device::column_sums<kRelu>(grad, out, masked)
// (the bias gradient; with kRelu it also writes the masked gradient), which the device's source
// registers with register_ops.
template <typename Device>
struct BiasGradOps {
  static at::Tensor bias_grad(const at::Tensor& grad) {
    check_args("bias_grad", grad, nullptr, Device::kind);
    return Device::template column_sums<false>(grad, nullptr, nullptr);
  }

  static std::tuple<at::Tensor, at::Tensor> relu_bias_bwd(const at::Tensor& grad, const at::Tensor& out) {
    check_args("relu_bias_bwd", grad, &out, Device::kind);
    at::Tensor masked = at::empty_like(grad);
    at::Tensor sums = Device::template column_sums<true>(grad, &out, &masked);
    return {masked, sums};
  }

  static void register_ops(torch::Library& m) {
    m.impl("bias_grad", &bias_grad);
    m.impl("relu_bias_bwd", &relu_bias_bwd);
  }
};

}  // namespace bias_grad
}  // namespace mixer_nerf
