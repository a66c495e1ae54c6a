// CPU kernels of mlca, Mixer-NeRF's token + channel mixing, per point with X = encoded row (T, D):
//   L = X lift^T                                 (T, C)  lift
//   Y = L + GELU(W_t L + b_t 1^T)                (T, C)  token mixing (b_t per token)
//   Z = Y + GELU(Y W_c^T + 1 b_c^T)              (T, C)  channel mixing (b_c per channel)
// out = Z flattened token-major (N, T*C). The backward recomputes L, Y and the pre-activations
// from `encoded` (cheaper than storing them) and, with G = dZ:
//   gQ = G * GELU'(Q),  dY = G + gQ W_c,          dW_c = sum gQ^T Y,  db_c = sum gQ
//   gP = dY * GELU'(P), dL = dY + W_t^T gP,       dW_t = sum gP L^T,  db_t = sum_c gP
//   dlift = sum dL^T X, dX = dL lift              (sums over points, and tokens or channels)
// Work is split into fixed chunks of points, each accumulating its weight gradients into its own
// row of a (chunks, P) buffer; the rows are then summed in order, so the result does not depend on
// the number of threads. A chunk runs the stages one after another over all its points (Batch
// below); token mixing as (W_t X) lift^T + b_t, which mixes D < C values per token, and its backward
// likewise through G = gP lift (dW_t = sum G X^T, dlift = sum dY^T X + gP^T W_t X, dX = dY lift + W_t^T G).
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/CPUFunctions.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <type_traits>
#include <vector>

#include "common.h"
#include "mlca.h"

namespace mixer_nerf {
namespace {

namespace mm = mlca;
using mm::Sizes;

// Points per chunk: a parallel task's unit, a row of weight-gradient partials, and one pass of the
// stages (Batch below), whose buffers stay in L2. Chunks start at fixed points: no result depends on
// the thread count.
constexpr int64_t kChunkPoints = 256;
constexpr int64_t kMaxChannels = 32;  // a row of C on the stack (row_times); mlca() refuses C > 32 first
constexpr int64_t kMaxTokenDim = 32;  // mlca() refuses D > 32 first

// The weights in the accumulation type, in the layouts the per-point loops read contiguously.
template <typename acc>
struct Weights {
  std::vector<acc> lift_t;        // (D, C): lift transposed
  std::vector<acc> token;         // (T, T)
  std::vector<acc> token_bias;    // (T)
  std::vector<acc> channel;       // (C, C)
  std::vector<acc> channel_t;     // (C, C): channel transposed
  std::vector<acc> channel_bias;  // (C)
};

template <typename scalar_t, typename acc = acc_t<scalar_t>>
std::vector<acc> to_acc(const at::Tensor& t) {
  const scalar_t* p = t.const_data_ptr<scalar_t>();
  return std::vector<acc>(p, p + t.numel());
}

template <typename acc>
std::vector<acc> transposed(const std::vector<acc>& m, int64_t rows, int64_t cols) {
  std::vector<acc> out(m.size());
  for (int64_t r = 0; r < rows; ++r) {
    for (int64_t c = 0; c < cols; ++c) out[c * rows + r] = m[r * cols + c];
  }
  return out;
}

template <typename scalar_t>
Weights<acc_t<scalar_t>> weights_of(const Sizes& s, const at::Tensor& lift, const at::Tensor& token_weight,
                                    const at::Tensor& token_bias, const at::Tensor& channel_weight,
                                    const at::Tensor& channel_bias) {
  Weights<acc_t<scalar_t>> w;
  w.lift_t = transposed(to_acc<scalar_t>(lift), s.C, s.D);
  w.token = to_acc<scalar_t>(token_weight);
  w.token_bias = to_acc<scalar_t>(token_bias);
  w.channel = to_acc<scalar_t>(channel_weight);
  w.channel_t = transposed(w.channel, s.C, s.C);
  w.channel_bias = to_acc<scalar_t>(channel_bias);
  return w;
}

// A chunk of n points through the three stages in token-major buffers: row m = t n + p holds token t
// of point p (C values; D for x). Token mixing is then, per pair of tokens, one long contiguous
// multiply-add over the chunk's points, and the row-wise stages (lift, channel mixing) run over C
// contiguous values; `omp simd` lets the compiler vectorise both, reductions included (in a fixed
// order). The GELUs of a whole chunk go to ATen's vectorised CPU kernels, the ones F.gelu runs,
// instead of a scalar erf per value. kC > 0: C = kC (the model's 8) as a compile-time constant.
template <typename acc, int kC>
struct Batch {
  int64_t T, C, D, capacity, n = 0;
  // mixed_x = W_t X and (backward) lifted_grad = gP lift: (T, n, D)
  std::vector<acc> x, mixed_x, lifted, pre, mixed, chan, tmp, grad, lifted_grad;
  Batch(const Sizes& s, int64_t points, bool backward)
      : T(s.T), C(kC > 0 ? kC : s.C), D(s.D), capacity(points), x(points * s.T * s.D), mixed_x(x.size()),
        lifted(points * s.T * C), pre(lifted.size()), mixed(lifted.size()), chan(lifted.size()), tmp(lifted.size()),
        grad(backward ? lifted.size() : 0), lifted_grad(backward ? x.size() : 0) {}

  int64_t channels() const { return kC > 0 ? kC : C; }

  // out = v M (+ bias) for a row v of K values and M (K, C) row-major: C-wide multiply-adds.
  void row_times(const acc* v, int64_t K, const acc* M, const acc* bias, acc* out) const {
    const int64_t C = channels();
    acc sum[kC > 0 ? kC : kMaxChannels];
#pragma omp simd
    for (int64_t c = 0; c < C; ++c) sum[c] = bias ? bias[c] : acc(0);
    for (int64_t k = 0; k < K; ++k) {
      const acc vk = v[k];
      const acc* row = M + k * C;
#pragma omp simd
      for (int64_t c = 0; c < C; ++c) sum[c] += vk * row[c];
    }
    std::copy(sum, sum + C, out);
  }

  // The first n T C values of a buffer as a tensor, for ATen's CPU kernels.
  at::Tensor view(std::vector<acc>& v) {
    return at::from_blob(v.data(), {n * T * channels()},
                         at::TensorOptions().dtype(c10::CppTypeToScalarType<acc>::value));
  }

  // Rows of W values between a (points, T, W) array and token-major buffers: token t of point p is
  // row p T + t there and row t n + p here. kToTokens: into the buffer (gather), else out (scatter).
  template <bool kToTokens, typename from_t, typename to_t>
  void reorder(const from_t* src, int64_t W, to_t* dst) const {
    for (int64_t p = 0; p < n; ++p) {
      for (int64_t t = 0; t < T; ++t) {
        const int64_t point_row = p * T + t, token_row = t * n + p;
        const from_t* from = src + (kToTokens ? point_row : token_row) * W;
        to_t* to = dst + (kToTokens ? token_row : point_row) * W;
        for (int64_t k = 0; k < W; ++k) to[k] = static_cast<to_t>(from[k]);
      }
    }
  }
  template <typename src_t>
  void gather(const src_t* src, int64_t W, acc* dst) const { reorder<true>(src, W, dst); }
  template <typename dst_t>
  void scatter(const acc* src, int64_t W, dst_t* dst) const { reorder<false>(src, W, dst); }

  // For points [first, first + points) of encoded: x, lifted = L = X lift^T, pre = P = W_t L + b_t,
  // mixed = Y = L + GELU(P), chan = Q = Y W_c^T + b_c.
  template <typename scalar_t>
  void forward(const scalar_t* encoded, int64_t first, int64_t points, const Weights<acc>& w) {
    n = points;
    const int64_t C = channels(), rows = n * T;
    gather(encoded + first * T * D, D, x.data());
    for (int64_t m = 0; m < rows; ++m) row_times(&x[m * D], D, w.lift_t.data(), nullptr, &lifted[m * C]);
    // P = W_t X lift^T + b_t as (W_t X) lift^T: D < C values per token to mix, not C.
    const int64_t x_width = n * D;
    for (int64_t t = 0; t < T; ++t) {
      acc* v = &mixed_x[t * x_width];
#pragma omp simd
      for (int64_t j = 0; j < x_width; ++j) v[j] = 0;
      for (int64_t u = 0; u < T; ++u) {
        const acc wtu = w.token[t * T + u];
        const acc* xu = &x[u * x_width];
#pragma omp simd
        for (int64_t j = 0; j < x_width; ++j) v[j] += wtu * xu[j];
      }
    }
    for (int64_t m = 0; m < rows; ++m) {
      acc* q = &pre[m * C];
      row_times(&mixed_x[m * D], D, w.lift_t.data(), nullptr, q);
      const acc bias = w.token_bias[m / n];
#pragma omp simd
      for (int64_t c = 0; c < C; ++c) q[c] += bias;
    }
    at::Tensor gelu = view(tmp);
    at::cpu::gelu_out(gelu, view(pre));
#pragma omp simd
    for (int64_t j = 0; j < rows * C; ++j) mixed[j] = lifted[j] + tmp[j];
    for (int64_t m = 0; m < rows; ++m) {
      row_times(&mixed[m * C], C, w.channel_t.data(), w.channel_bias.data(), &chan[m * C]);
    }
  }
};

// f(std::integral_constant<int, kC>): kC = C where C is the model's, else 0 (run-time C).
template <typename F>
void with_channels(int64_t C, F f) {
  if (C == mm::kExactChannels) {
    f(std::integral_constant<int, mm::kExactChannels>{});
  } else {
    f(std::integral_constant<int, 0>{});
  }
}

// The points of chunks [first_chunk, last_chunk) of n, into out.
template <int kC, typename scalar_t>
void forward_chunks(const scalar_t* encoded, scalar_t* out, int64_t n, int64_t first_chunk, int64_t last_chunk,
                    const Sizes& s, const Weights<acc_t<scalar_t>>& w) {
  using acc = acc_t<scalar_t>;
  Batch<acc, kC> b(s, std::min(kChunkPoints, n), false);
  for (int64_t k = first_chunk; k < last_chunk; ++k) {
    const int64_t first = k * kChunkPoints;
    b.forward(encoded, first, std::min(kChunkPoints, n - first), w);
    at::Tensor gelu = b.view(b.tmp);
    at::cpu::gelu_out(gelu, b.view(b.chan));
    const int64_t size = b.n * s.T * b.channels();
#pragma omp simd
    for (int64_t j = 0; j < size; ++j) b.tmp[j] += b.mixed[j];  // Z = Y + GELU(Q)
    b.scatter(b.tmp.data(), b.channels(), out + first * s.T * b.channels());
  }
}

// A chunk's channel-mixing and lift gradients (dW_c, db_c, dlift) while its rows are summed; sized
// at compile time for the model's channels (kC > 0) so that they can live in registers.
template <typename acc, int kC>
struct Sums {
  static constexpr int64_t kMaxC = kC > 0 ? kC : kMaxChannels;
  int64_t C, D;
  acc channel[kMaxC * kMaxC] = {}, channel_bias[kMaxC] = {}, lift[kMaxC * kMaxTokenDim] = {};
  Sums(int64_t channels, int64_t token_dim) : C(channels), D(token_dim) {}
  void add_to(acc* d_channel, acc* d_channel_bias, acc* d_lift) const {
    for (int64_t j = 0; j < C * C; ++j) d_channel[j] += channel[j];
    for (int64_t c = 0; c < C; ++c) d_channel_bias[c] += channel_bias[c];
    for (int64_t j = 0; j < C * D; ++j) d_lift[j] += lift[j];
  }
};

// For chunks [first_chunk, last_chunk) of n points: adds chunk k's weight gradients to row k of
// `partials` (rows of Sizes::params()) and, with grad_encoded, writes its points' input gradients.
template <int kC, typename scalar_t>
void backward_chunks(const scalar_t* grad_out, const scalar_t* encoded, scalar_t* grad_encoded, int64_t n,
                     int64_t first_chunk, int64_t last_chunk, const Sizes& s, const Weights<acc_t<scalar_t>>& w,
                     acc_t<scalar_t>* partials) {
  using acc = acc_t<scalar_t>;
  const int64_t T = s.T, C = kC > 0 ? kC : s.C, D = s.D;
  Batch<acc, kC> b(s, std::min(kChunkPoints, n), true);
  std::vector<acc> dx(grad_encoded != nullptr ? b.capacity * T * D : 0);
  for (int64_t chunk = first_chunk; chunk < last_chunk; ++chunk) {
    acc* d_token = partials + chunk * s.params();
    acc* d_token_bias = d_token + s.token_bias();
    acc* d_channel = d_token + s.channel_weight();
    acc* d_channel_bias = d_token + s.channel_bias();
    acc* d_lift = d_token + s.lift();
    const int64_t first = chunk * kChunkPoints;
    b.forward(encoded, first, std::min(kChunkPoints, n - first), w);
    const int64_t rows = b.n * T, width = b.n * C;  // b.n: this chunk's points
    b.gather(grad_out + first * T * C, C, b.grad.data());  // G = dZ
    // Channel mixing: tmp = gQ = G * GELU'(Q), then grad = dY = G + gQ W_c.
    at::Tensor gq = b.view(b.tmp);
    at::cpu::gelu_backward_out(gq, b.view(b.grad), b.view(b.chan));
    // The chunk's weight gradients summed in locals, then added to its row once: accumulated in the
    // row itself, every update was a store and a reload (the compiler cannot rule out aliasing).
    Sums<acc, kC> sums(C, D);
    for (int64_t m = 0; m < rows; ++m) {
      const acc* q = &b.tmp[m * C];
      const acc* y = &b.mixed[m * C];
      acc* dy = &b.grad[m * C];
#pragma omp simd
      for (int64_t e = 0; e < C; ++e) {
        acc sum = 0;
        for (int64_t c = 0; c < C; ++c) sum += q[c] * w.channel[c * C + e];
        dy[e] += sum;
      }
      for (int64_t c = 0; c < C; ++c) {
        const acc gqc = q[c];
        sums.channel_bias[c] += gqc;
        acc* dwc = &sums.channel[c * C];
#pragma omp simd
        for (int64_t e = 0; e < C; ++e) dwc[e] += gqc * y[e];
      }
    }
    // Token mixing: tmp = gP = dY * GELU'(P). Its gradients pass through the lift first, G = gP lift
    // (D < C values per token, as the forward mixes W_t X): dW_t = sum G X^T, db_t = sum_c gP, and
    // with dL = dY + W_t^T gP never formed, dlift = sum (dY^T X + gP^T W_t X), dX = dY lift + W_t^T G.
    at::Tensor gp = b.view(b.tmp);
    at::cpu::gelu_backward_out(gp, b.view(b.grad), b.view(b.pre));
    for (int64_t m = 0; m < rows; ++m) {
      const acc* gpm = &b.tmp[m * C];
      const acc* dym = &b.grad[m * C];
      const acc* xm = &b.x[m * D];
      const acc* wxm = &b.mixed_x[m * D];
      for (int64_t k = 0; k < D; ++k) {
        const acc* lift_k = &w.lift_t[k * C];
        acc g = 0, dy_lift = 0;
#pragma omp simd reduction(+ : g, dy_lift)
        for (int64_t c = 0; c < C; ++c) {
          g += gpm[c] * lift_k[c];
          dy_lift += dym[c] * lift_k[c];
        }
        b.lifted_grad[m * D + k] = g;
        if (grad_encoded != nullptr) dx[m * D + k] = dy_lift;
      }
      for (int64_t c = 0; c < C; ++c) {
        for (int64_t k = 0; k < D; ++k) sums.lift[c * D + k] += dym[c] * xm[k] + gpm[c] * wxm[k];
      }
    }
    sums.add_to(d_channel, d_channel_bias, d_lift);
    const int64_t x_width = b.n * D;
    for (int64_t t = 0; t < T; ++t) {
      const acc* gpt = &b.tmp[t * width];
      acc bias = 0;
#pragma omp simd reduction(+ : bias)
      for (int64_t j = 0; j < width; ++j) bias += gpt[j];
      d_token_bias[t] += bias;
      const acc* gt = &b.lifted_grad[t * x_width];
      for (int64_t u = 0; u < T; ++u) {
        const acc* xu = &b.x[u * x_width];
        acc dot = 0;
#pragma omp simd reduction(+ : dot)
        for (int64_t j = 0; j < x_width; ++j) dot += gt[j] * xu[j];
        d_token[t * T + u] += dot;
        if (grad_encoded != nullptr) {
          const acc wtu = w.token[t * T + u];
          acc* dxu = &dx[u * x_width];
#pragma omp simd
          for (int64_t j = 0; j < x_width; ++j) dxu[j] += wtu * gt[j];
        }
      }
    }
    if (grad_encoded != nullptr) b.scatter(dx.data(), D, grad_encoded + first * T * D);
  }
}

Sizes check_cpu_args(const at::Tensor& encoded, const at::Tensor& lift, const at::Tensor& token_weight,
                     const at::Tensor& token_bias, const at::Tensor& channel_weight, const at::Tensor& channel_bias) {
  const Sizes s = mm::check_args(encoded, lift, token_weight, token_bias, channel_weight, channel_bias, at::kCPU);
  MIXER_NERF_CHECK(s.C <= kMaxChannels, "mlca: the CPU kernel takes C <= ", kMaxChannels, ", got C=", s.C);
  MIXER_NERF_CHECK(s.D <= kMaxTokenDim, "mlca: the CPU kernel takes D <= ", kMaxTokenDim, ", got D=", s.D);
  return s;
}

at::Tensor mlca_fwd_cpu(const at::Tensor& encoded, const at::Tensor& lift, const at::Tensor& token_weight,
                        const at::Tensor& token_bias, const at::Tensor& channel_weight,
                        const at::Tensor& channel_bias) {
  const Sizes s = check_cpu_args(encoded, lift, token_weight, token_bias, channel_weight, channel_bias);
  const int64_t n = encoded.size(0);
  at::Tensor out = at::empty({n, s.T * s.C}, encoded.options());
  MIXER_NERF_DISPATCH_FLOATING(encoded.scalar_type(), "mlca_fwd_cpu", [&] {
    const auto w = weights_of<scalar_t>(s, lift, token_weight, token_bias, channel_weight, channel_bias);
    const scalar_t* ep = encoded.const_data_ptr<scalar_t>();
    scalar_t* op = out.mutable_data_ptr<scalar_t>();
    with_channels(s.C, [&](auto kC) {
      at::parallel_for(0, (n + kChunkPoints - 1) / kChunkPoints, 1, [&](int64_t first, int64_t last) {
        forward_chunks<decltype(kC)::value>(ep, op, n, first, last, s, w);
      });
    });
  });
  return out;
}

mm::Grads mlca_bwd_cpu(
    const at::Tensor& grad_out, const at::Tensor& encoded, const at::Tensor& lift, const at::Tensor& token_weight,
    const at::Tensor& token_bias, const at::Tensor& channel_weight, const at::Tensor& channel_bias,
    bool input_grad) {
  const Sizes s = check_cpu_args(encoded, lift, token_weight, token_bias, channel_weight, channel_bias);
  mm::check_grad_out(grad_out, encoded, s);
  const int64_t n = encoded.size(0);
  at::Tensor grad_encoded = input_grad ? at::empty_like(encoded) : at::Tensor();
  const int64_t chunks = (n + kChunkPoints - 1) / kChunkPoints;
  const at::ScalarType acc_type = encoded.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  // One row per chunk, and at least one: no points give zero weight gradients.
  at::Tensor partials = at::zeros({std::max<int64_t>(chunks, 1), s.params()}, encoded.options().dtype(acc_type));
  MIXER_NERF_DISPATCH_FLOATING(encoded.scalar_type(), "mlca_bwd_cpu", [&] {
    using acc = acc_t<scalar_t>;
    const auto w = weights_of<scalar_t>(s, lift, token_weight, token_bias, channel_weight, channel_bias);
    const scalar_t* gp = grad_out.const_data_ptr<scalar_t>();
    const scalar_t* ep = encoded.const_data_ptr<scalar_t>();
    scalar_t* gep = input_grad ? grad_encoded.mutable_data_ptr<scalar_t>() : nullptr;
    acc* pp = partials.mutable_data_ptr<acc>();
    with_channels(s.C, [&](auto kC) {
      at::parallel_for(0, chunks, 1, [&](int64_t first, int64_t last) {
        backward_chunks<decltype(kC)::value>(gp, ep, gep, n, first, last, s, w, pp);
      });
    });
    for (int64_t k = 1; k < chunks; ++k) {  // in chunk order: independent of the thread count
      for (int64_t j = 0; j < s.params(); ++j) pp[j] += pp[k * s.params() + j];
    }
  });
  return mm::split_grads(partials[0], input_grad ? std::optional<at::Tensor>(grad_encoded) : std::nullopt, s,
                         encoded.scalar_type());
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CPU, m) {
  m.impl("mlca_fwd", &mlca_fwd_cpu);
  m.impl("mlca_bwd", &mlca_bwd_cpu);
}

}  // namespace mixer_nerf
