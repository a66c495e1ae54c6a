// bias_grad and relu_bias_bwd on the CPU: the backward of a linear layer's bias, for
// ops.linear and ops.linear_relu (mixer_nerf/ops/linear_relu.py). With g the upstream gradient
// (N, C) and y the layer's ReLU output:
//
//   bias_grad:      db_c = sum_i g_ic
//   relu_bias_bwd:  m_ic = (y_ic <= 0 ? 0 : g_ic)   (torch's threshold_backward: a NaN output passes)
//                   db_c = sum_i m_ic
//
// One pass over g: relu_bias_bwd writes the masked gradient and sums it in the same loop, where
// the eager backward ran a mask pass, a fill of ones and a GEMV. Rows go in bands of
// bias_grad::kBandRows, each band summed in acc_t, then the bands in order: deterministic and
// independent of the thread count. The CUDA kernels (csrc/cuda/bias_grad.cu) sum in other bands.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <vector>

#include "bias_grad.h"
#include "common.h"

namespace mixer_nerf {
namespace {

struct Cpu {
  static constexpr at::DeviceType kind = at::kCPU;
  template <bool kRelu>
  static at::Tensor column_sums(const at::Tensor& grad, const at::Tensor* out, at::Tensor* masked);
};

template <bool kRelu>
at::Tensor Cpu::column_sums(const at::Tensor& grad, const at::Tensor* out, at::Tensor* masked) {
  const int64_t N = grad.size(0), C = grad.size(1);
  at::Tensor sums = at::empty({C}, grad.options());
  MIXER_NERF_DISPATCH_FLOATING(grad.scalar_type(), "bias_grad_cpu", [&] {
    using acc = acc_t<scalar_t>;
    const int64_t rows = bias_grad::band_rows(N, INT64_MAX), bands = N ? (N + rows - 1) / rows : 0;
    std::vector<acc> partials(bands * C, acc(0));
    const scalar_t* g = grad.const_data_ptr<scalar_t>();
    const scalar_t* y = kRelu ? out->const_data_ptr<scalar_t>() : nullptr;
    scalar_t* m = kRelu ? masked->data_ptr<scalar_t>() : nullptr;
    at::parallel_for(0, bands, 1, [&](int64_t first, int64_t last) {
      for (int64_t b = first; b < last; ++b) {
        acc* sum = partials.data() + b * C;
        for (int64_t i = b * rows; i < std::min(N, (b + 1) * rows); ++i) {
          for (int64_t c = 0; c < C; ++c) {
            scalar_t v = g[i * C + c];
            if constexpr (kRelu) {
              v = y[i * C + c] <= scalar_t(0) ? scalar_t(0) : v;
              m[i * C + c] = v;
            }
            sum[c] += acc(v);
          }
        }
      }
    });
    scalar_t* db = sums.data_ptr<scalar_t>();
    for (int64_t c = 0; c < C; ++c) {
      acc total = 0;
      for (int64_t b = 0; b < bands; ++b) total += partials[b * C + c];
      db[c] = static_cast<scalar_t>(total);
    }
  });
  return sums;
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CPU, m) { bias_grad::BiasGradOps<Cpu>::register_ops(m); }

}  // namespace mixer_nerf
