// What the CPU and CUDA kernels of mlca share: GELU (the exact erf form, as F.gelu's default) and
// its derivative in the accumulation type, the layout of a row of weight gradients, the kernels'
// defensive argument checks and the split of the summed row into the gradient tensors.
#pragma once

#include <ATen/ATen.h>
#include <c10/macros/Macros.h>

#include <cmath>
#include <cstdint>
#include <optional>
#include <tuple>

#include "common.h"

namespace mixer_nerf {
namespace mlca {

C10_HOST_DEVICE inline float erf_of(float x) { return ::erff(x); }
C10_HOST_DEVICE inline double erf_of(double x) { return ::erf(x); }
C10_HOST_DEVICE inline float exp_of(float x) { return ::expf(x); }
C10_HOST_DEVICE inline double exp_of(double x) { return ::exp(x); }

// GELU(x) = x Phi(x) = x (1 + erf(x / sqrt 2)) / 2.
template <typename acc>
C10_HOST_DEVICE inline acc gelu(acc x) {
  return acc(0.5) * x * (acc(1) + erf_of(x * acc(0.70710678118654752440)));
}

// GELU(x) and GELU'(x) = Phi(x) + x phi(x) together. For large |x| the x^2 in phi may overflow
// to inf: exp(-inf) = 0 and x 0 = 0, so every finite x gives a finite derivative.
template <typename acc>
C10_HOST_DEVICE inline void gelu_and_grad(acc x, acc& value, acc& grad) {
  const acc cdf = acc(0.5) * (acc(1) + erf_of(x * acc(0.70710678118654752440)));
  value = x * cdf;
  grad = cdf + x * (acc(0.39894228040143267794) * exp_of(acc(-0.5) * x * x));
}

template <typename acc>
C10_HOST_DEVICE inline acc gelu_grad(acc x) {
  acc value, grad;
  gelu_and_grad(x, value, grad);
  return grad;
}

// The model's channels C and token width D (positions and directions are 3-vectors): the sizes the
// kernels compile in as constants (CPU: C; CUDA: C and D for float32). CUDA also compiles
// mlca_channels = 3 (tokens kept at the coordinates' width) in.
constexpr int kExactChannels = 8, kExactTokenDim = 3, kNarrowChannels = 3;

// T tokens of D values lifted to C channels, and the layout of a row of weight gradients:
// dW_t (T*T), db_t (T), dW_c (C*C), db_c (C), dlift (C*D), each row-major.
struct Sizes {
  int64_t T, C, D;
  C10_HOST_DEVICE int64_t token_bias() const { return T * T; }
  C10_HOST_DEVICE int64_t channel_weight() const { return token_bias() + T; }
  C10_HOST_DEVICE int64_t channel_bias() const { return channel_weight() + C * C; }
  C10_HOST_DEVICE int64_t lift() const { return channel_bias() + C; }
  C10_HOST_DEVICE int64_t params() const { return lift() + C * D; }
};

// grad_encoded (absent when not asked for), grad_lift, grad_token_weight, grad_token_bias,
// grad_channel_weight, grad_channel_bias.
using Grads = std::tuple<std::optional<at::Tensor>, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

inline Sizes check_args(const at::Tensor& encoded, const at::Tensor& lift, const at::Tensor& token_weight,
                        const at::Tensor& token_bias, const at::Tensor& channel_weight,
                        const at::Tensor& channel_bias, c10::DeviceType device) {
  for (const at::Tensor* t : {&encoded, &lift, &token_weight, &token_bias, &channel_weight, &channel_bias}) {
    MIXER_NERF_CHECK(t->device() == encoded.device() && t->device().type() == device, "mlca: every tensor must be on ",
                     device, " with encoded, got ", t->device(), " and ", encoded.device());
    MIXER_NERF_CHECK(t->is_contiguous(), "mlca: every tensor must be contiguous");
    MIXER_NERF_CHECK(t->scalar_type() == encoded.scalar_type(), "mlca: every tensor must have the dtype of encoded (",
                     encoded.scalar_type(), "), got ", t->scalar_type());
  }
  MIXER_NERF_CHECK(lift.dim() == 2 && token_weight.dim() == 2, "mlca: lift and token_weight must be matrices");
  const Sizes s{token_weight.size(0), lift.size(0), lift.size(1)};
  MIXER_NERF_CHECK(encoded.dim() == 2 && encoded.size(1) == s.T * s.D, "mlca: encoded must have shape (N, ",
                   s.T * s.D, "), got ", encoded.sizes());
  MIXER_NERF_CHECK(token_weight.sizes() == at::IntArrayRef({s.T, s.T}) && token_bias.sizes() == at::IntArrayRef({s.T}) &&
                       channel_weight.sizes() == at::IntArrayRef({s.C, s.C}) &&
                       channel_bias.sizes() == at::IntArrayRef({s.C}),
                   "mlca: weights of inconsistent shapes");
  return s;
}

inline void check_grad_out(const at::Tensor& grad_out, const at::Tensor& encoded, const Sizes& s) {
  MIXER_NERF_CHECK(grad_out.device() == encoded.device(), "grad_out must be on the device of encoded");
  MIXER_NERF_CHECK(grad_out.is_contiguous(), "grad_out must be contiguous");
  MIXER_NERF_CHECK(grad_out.sizes() == at::IntArrayRef({encoded.size(0), s.T * s.C}), "grad_out must have shape ",
                   std::vector<int64_t>{encoded.size(0), s.T * s.C}, ", got ", grad_out.sizes());
  MIXER_NERF_CHECK(grad_out.scalar_type() == encoded.scalar_type(), "grad_out must have the dtype of encoded");
}

// The weight gradients from their summed row (params(), accumulation dtype), in the weights' dtype.
inline Grads split_grads(const at::Tensor& total, std::optional<at::Tensor> grad_encoded, const Sizes& s,
                         c10::ScalarType dtype) {
  const at::Tensor row = total.to(dtype);
  auto part = [&](int64_t begin, int64_t end, at::IntArrayRef shape) {
    return row.slice(0, begin, end).view(shape).clone();
  };
  return {std::move(grad_encoded),
          part(s.lift(), s.params(), {s.C, s.D}),
          part(0, s.token_bias(), {s.T, s.T}),
          part(s.token_bias(), s.channel_weight(), {s.T}),
          part(s.channel_weight(), s.channel_bias(), {s.C, s.C}),
          part(s.channel_bias(), s.lift(), {s.C})};
}

}  // namespace mlca
}  // namespace mixer_nerf
