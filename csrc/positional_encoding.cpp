// CPU kernels of positional_encoding: x (N, D) -> (N, D * (include_input + 2 * num_freqs)), rows
// laid out [x, sin(f0 x), cos(f0 x), sin(f1 x), cos(f1 x), ...] with f_k = scale * 2^k.
// Points are processed in small tiles: the sin/cos of a whole tile are evaluated in one
// contiguous (vectorisable) loop per frequency, then scattered into the interleaved rows.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "common.h"
#include "positional_encoding.h"
#include "positional_encoding_math.h"

namespace mixer_nerf {
namespace {

namespace pem = positional_encoding_math;

constexpr int64_t kTileElements = 512;     // (point, feature) pairs evaluated per inner loop
constexpr int64_t kGrainOutputs = 1 << 15;  // output elements per parallel task, at least

struct Encoding {
  int64_t dims;       // D
  int64_t num_freqs;  // F
  bool include_input;
  double scale;

  int64_t width() const { return dims * ((include_input ? 1 : 0) + 2 * num_freqs); }
  // Column of the sin block of frequency k; its cos block follows, D columns later.
  int64_t sin_column(int64_t k) const { return ((include_input ? 1 : 0) + 2 * k) * dims; }
  int64_t grain() const { return std::max<int64_t>(1, kGrainOutputs / std::max<int64_t>(1, width())); }
  int64_t tile_points() const { return std::max<int64_t>(1, kTileElements / dims); }
};

template <typename scalar_t>
MIXER_NERF_CPU_CLONES void encode_points(const scalar_t* x, scalar_t* out, int64_t begin, int64_t end,
                                         const Encoding& enc) {
  using acc = acc_t<scalar_t>;
  const int64_t D = enc.dims, W = enc.width(), P = enc.tile_points();
  const pem::HalfTurns c = pem::half_turns(enc.scale);
  std::vector<double> xs(P * D);
  std::vector<acc> sn(P * D), cs(P * D);
  for (int64_t p0 = begin; p0 < end; p0 += P) {
    const int64_t np = std::min(P, end - p0), m = np * D;
    const scalar_t* xt = x + p0 * D;
    scalar_t* rows = out + p0 * W;
    for (int64_t j = 0; j < m; ++j) xs[j] = pem::bounded_input(static_cast<acc>(xt[j]), c.hi);
    if (enc.include_input) {
      for (int64_t p = 0; p < np; ++p) std::copy(xt + p * D, xt + (p + 1) * D, rows + p * W);
    }
    for (int64_t k = 0; k < enc.num_freqs; ++k) {
      // c 2^k x == (c 2^k) x exactly
      const double hi = std::ldexp(c.hi, static_cast<int>(k)), lo = std::ldexp(c.lo, static_cast<int>(k));
#pragma omp simd
      for (int64_t j = 0; j < m; ++j) pem::sincospi<acc>(hi * xs[j], lo * xs[j], sn[j], cs[j]);
      const int64_t col = enc.sin_column(k);
      for (int64_t p = 0; p < np; ++p) {
        scalar_t* row = rows + p * W + col;
        for (int64_t d = 0; d < D; ++d) {
          row[d] = static_cast<scalar_t>(sn[p * D + d]);
          row[D + d] = static_cast<scalar_t>(cs[p * D + d]);
        }
      }
    }
  }
}

// grad_x = grad[x block] + sum_k scale 2^k (grad[sin_k] cos - grad[cos_k] sin), with sin/cos
// recomputed from x rather than stored.
template <typename scalar_t>
MIXER_NERF_CPU_CLONES void encode_points_backward(const scalar_t* grad, const scalar_t* x, scalar_t* grad_x,
                                                  int64_t begin, int64_t end, const Encoding& enc) {
  using acc = acc_t<scalar_t>;
  const int64_t D = enc.dims, W = enc.width(), P = enc.tile_points();
  const pem::HalfTurns c = pem::half_turns(enc.scale);
  std::vector<double> xs(P * D);
  std::vector<acc> g(P * D), gs(P * D), gc(P * D);
  for (int64_t p0 = begin; p0 < end; p0 += P) {
    const int64_t np = std::min(P, end - p0), m = np * D;
    const scalar_t* rows = grad + p0 * W;
    for (int64_t j = 0; j < m; ++j) xs[j] = pem::bounded_input(static_cast<acc>(x[p0 * D + j]), c.hi);
    for (int64_t p = 0; p < np; ++p) {
      for (int64_t d = 0; d < D; ++d) g[p * D + d] = enc.include_input ? static_cast<acc>(rows[p * W + d]) : acc(0);
    }
    for (int64_t k = 0; k < enc.num_freqs; ++k) {
      const double hi = std::ldexp(c.hi, static_cast<int>(k)), lo = std::ldexp(c.lo, static_cast<int>(k));
      const acc freq = static_cast<acc>(std::ldexp(enc.scale, static_cast<int>(k)));
      const int64_t col = enc.sin_column(k);
      for (int64_t p = 0; p < np; ++p) {
        const scalar_t* row = rows + p * W + col;
        for (int64_t d = 0; d < D; ++d) {
          gs[p * D + d] = static_cast<acc>(row[d]);
          gc[p * D + d] = static_cast<acc>(row[D + d]);
        }
      }
#pragma omp simd
      for (int64_t j = 0; j < m; ++j) {
        acc s, co;
        pem::sincospi<acc>(hi * xs[j], lo * xs[j], s, co);
        g[j] += freq * (gs[j] * co - gc[j] * s);
      }
    }
    for (int64_t j = 0; j < m; ++j) grad_x[p0 * D + j] = static_cast<scalar_t>(g[j]);
  }
}

at::Tensor positional_encoding_fwd_cpu(const at::Tensor& x, int64_t num_freqs, bool include_input, double scale) {
  positional_encoding::check_args(x, num_freqs, at::kCPU);
  const Encoding enc{x.size(-1), num_freqs, include_input, scale};
  at::Tensor out = at::empty(positional_encoding::encoded_shape(x, enc.width()), x.options());
  const int64_t n = x.numel() / enc.dims;
  MIXER_NERF_DISPATCH_FLOATING(x.scalar_type(), "positional_encoding_fwd_cpu", [&] {
    const scalar_t* xp = x.const_data_ptr<scalar_t>();
    scalar_t* op = out.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, n, enc.grain(), [&](int64_t begin, int64_t end) { encode_points(xp, op, begin, end, enc); });
  });
  return out;
}

at::Tensor positional_encoding_bwd_cpu(const at::Tensor& grad_out, const at::Tensor& x, int64_t num_freqs,
                                       bool include_input, double scale) {
  positional_encoding::check_args(x, num_freqs, at::kCPU);
  const Encoding enc{x.size(-1), num_freqs, include_input, scale};
  positional_encoding::check_grad_out(grad_out, x, enc.width(), at::kCPU);
  at::Tensor grad_x = at::empty_like(x);
  const int64_t n = x.numel() / enc.dims;
  MIXER_NERF_DISPATCH_FLOATING(x.scalar_type(), "positional_encoding_bwd_cpu", [&] {
    const scalar_t* gp = grad_out.const_data_ptr<scalar_t>();
    const scalar_t* xp = x.const_data_ptr<scalar_t>();
    scalar_t* gxp = grad_x.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, n, enc.grain(),
                     [&](int64_t begin, int64_t end) { encode_points_backward(gp, xp, gxp, begin, end, enc); });
  });
  return grad_x;
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CPU, m) {
  m.impl("positional_encoding_fwd", &positional_encoding_fwd_cpu);
  m.impl("positional_encoding_bwd", &positional_encoding_bwd_cpu);
}

}  // namespace mixer_nerf
