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
// the number of threads. Rows of L/Y are C contiguous values: the inner loops run over channels.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <vector>

#include "common.h"
#include "mlca.h"

namespace mixer_nerf {
namespace {

namespace mm = mlca;
using mm::Sizes;

constexpr int64_t kChunkPoints = 256;  // points per weight-gradient partial (and per parallel task)

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

// Per-point buffers of one task, (T, C) each.
template <typename acc>
struct Workspace {
  std::vector<acc> x, lifted, pre, mixed, grad;
  explicit Workspace(const Sizes& s)
      : x(s.T * s.D), lifted(s.T * s.C), pre(s.T * s.C), mixed(s.T * s.C), grad(s.T * s.C) {}
};

// lifted = X lift^T; mixed = Y = lifted + GELU(P), with pre = P (the token-mixing pre-activation).
template <typename scalar_t, typename acc>
void lift_and_mix_tokens(const scalar_t* row, const Sizes& s, const Weights<acc>& w, Workspace<acc>& ws) {
  const int64_t T = s.T, C = s.C, D = s.D;
  for (int64_t j = 0; j < T * D; ++j) ws.x[j] = static_cast<acc>(row[j]);
  std::fill(ws.lifted.begin(), ws.lifted.end(), acc(0));
  for (int64_t t = 0; t < T; ++t) {
    for (int64_t k = 0; k < D; ++k) {
      const acc xk = ws.x[t * D + k];
      for (int64_t c = 0; c < C; ++c) ws.lifted[t * C + c] += xk * w.lift_t[k * C + c];
    }
  }
  for (int64_t t = 0; t < T; ++t) {
    acc* pre = &ws.pre[t * C];
    std::fill(pre, pre + C, w.token_bias[t]);
    for (int64_t u = 0; u < T; ++u) {
      const acc wtu = w.token[t * T + u];
      for (int64_t c = 0; c < C; ++c) pre[c] += wtu * ws.lifted[u * C + c];
    }
    for (int64_t c = 0; c < C; ++c) ws.mixed[t * C + c] = ws.lifted[t * C + c] + mm::gelu(pre[c]);
  }
}

// q = Q[t] = Y[t] W_c^T + b_c, the channel-mixing pre-activation of token t.
template <typename acc>
void channel_pre(const acc* y, const Sizes& s, const Weights<acc>& w, acc* q) {
  const int64_t C = s.C;
  std::copy(w.channel_bias.begin(), w.channel_bias.end(), q);
  for (int64_t e = 0; e < C; ++e) {
    const acc ye = y[e];
    for (int64_t c = 0; c < C; ++c) q[c] += ye * w.channel_t[e * C + c];
  }
}

template <typename scalar_t>
void forward_points(const scalar_t* encoded, scalar_t* out, int64_t begin, int64_t end, const Sizes& s,
                    const Weights<acc_t<scalar_t>>& w) {
  using acc = acc_t<scalar_t>;
  const int64_t T = s.T, C = s.C, D = s.D;
  Workspace<acc> ws(s);
  std::vector<acc> q(C);
  for (int64_t n = begin; n < end; ++n) {
    lift_and_mix_tokens(encoded + n * T * D, s, w, ws);
    scalar_t* row = out + n * T * C;
    for (int64_t t = 0; t < T; ++t) {
      const acc* y = &ws.mixed[t * C];
      channel_pre(y, s, w, q.data());
      for (int64_t c = 0; c < C; ++c) row[t * C + c] = static_cast<scalar_t>(y[c] + mm::gelu(q[c]));
    }
  }
}

// Adds the weight gradients of points [begin, end) to `partial` (a row of Sizes::params()) and,
// with grad_encoded, writes their input gradients.
template <typename scalar_t>
void backward_points(const scalar_t* grad_out, const scalar_t* encoded, scalar_t* grad_encoded, int64_t begin,
                     int64_t end, const Sizes& s, const Weights<acc_t<scalar_t>>& w, acc_t<scalar_t>* partial) {
  using acc = acc_t<scalar_t>;
  const int64_t T = s.T, C = s.C, D = s.D;
  acc* d_token = partial;
  acc* d_token_bias = partial + s.token_bias();
  acc* d_channel = partial + s.channel_weight();
  acc* d_channel_bias = partial + s.channel_bias();
  acc* d_lift = partial + s.lift();
  Workspace<acc> ws(s);
  std::vector<acc> q(C), gq(C);
  for (int64_t n = begin; n < end; ++n) {
    lift_and_mix_tokens(encoded + n * T * D, s, w, ws);
    const scalar_t* g = grad_out + n * T * C;
    // Channel mixing: ws.grad = dY, and ws.pre becomes gP = dY * GELU'(P).
    for (int64_t t = 0; t < T; ++t) {
      const acc* y = &ws.mixed[t * C];
      acc* dy = &ws.grad[t * C];
      channel_pre(y, s, w, q.data());
      for (int64_t c = 0; c < C; ++c) {
        dy[c] = static_cast<acc>(g[t * C + c]);
        gq[c] = dy[c] * mm::gelu_grad(q[c]);
      }
      for (int64_t c = 0; c < C; ++c) {
        const acc gqc = gq[c];
        d_channel_bias[c] += gqc;
        for (int64_t e = 0; e < C; ++e) {
          dy[e] += gqc * w.channel[c * C + e];
          d_channel[c * C + e] += gqc * y[e];
        }
      }
      for (int64_t c = 0; c < C; ++c) ws.pre[t * C + c] = dy[c] * mm::gelu_grad(ws.pre[t * C + c]);
    }
    // Token mixing: ws.grad becomes dL = dY + W_t^T gP.
    for (int64_t t = 0; t < T; ++t) {
      const acc* gp = &ws.pre[t * C];
      acc bias = 0;
      for (int64_t c = 0; c < C; ++c) bias += gp[c];
      d_token_bias[t] += bias;
      for (int64_t u = 0; u < T; ++u) {
        const acc* l = &ws.lifted[u * C];
        acc dot = 0;
        for (int64_t c = 0; c < C; ++c) dot += gp[c] * l[c];
        d_token[t * T + u] += dot;
        const acc wtu = w.token[t * T + u];
        acc* dl = &ws.grad[u * C];
        for (int64_t c = 0; c < C; ++c) dl[c] += wtu * gp[c];
      }
    }
    // Lift.
    for (int64_t t = 0; t < T; ++t) {
      const acc* dl = &ws.grad[t * C];
      for (int64_t c = 0; c < C; ++c) {
        for (int64_t k = 0; k < D; ++k) d_lift[c * D + k] += dl[c] * ws.x[t * D + k];
      }
      if (grad_encoded != nullptr) {
        for (int64_t k = 0; k < D; ++k) {
          acc dx = 0;
          for (int64_t c = 0; c < C; ++c) dx += dl[c] * w.lift_t[k * C + c];
          grad_encoded[n * T * D + t * D + k] = static_cast<scalar_t>(dx);
        }
      }
    }
  }
}

at::Tensor mlca_fwd_cpu(const at::Tensor& encoded, const at::Tensor& lift, const at::Tensor& token_weight,
                        const at::Tensor& token_bias, const at::Tensor& channel_weight,
                        const at::Tensor& channel_bias) {
  const Sizes s = mm::check_args(encoded, lift, token_weight, token_bias, channel_weight, channel_bias, at::kCPU);
  const int64_t n = encoded.size(0);
  at::Tensor out = at::empty({n, s.T * s.C}, encoded.options());
  MIXER_NERF_DISPATCH_FLOATING(encoded.scalar_type(), "mlca_fwd_cpu", [&] {
    const auto w = weights_of<scalar_t>(s, lift, token_weight, token_bias, channel_weight, channel_bias);
    const scalar_t* ep = encoded.const_data_ptr<scalar_t>();
    scalar_t* op = out.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, n, kChunkPoints, [&](int64_t begin, int64_t end) { forward_points(ep, op, begin, end, s, w); });
  });
  return out;
}

mm::Grads mlca_bwd_cpu(
    const at::Tensor& grad_out, const at::Tensor& encoded, const at::Tensor& lift, const at::Tensor& token_weight,
    const at::Tensor& token_bias, const at::Tensor& channel_weight, const at::Tensor& channel_bias,
    bool input_grad) {
  const Sizes s = mm::check_args(encoded, lift, token_weight, token_bias, channel_weight, channel_bias, at::kCPU);
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
    at::parallel_for(0, chunks, 1, [&](int64_t first, int64_t last) {
      for (int64_t k = first; k < last; ++k) {
        backward_points(gp, ep, gep, k * kChunkPoints, std::min(n, (k + 1) * kChunkPoints), s, w,
                        pp + k * s.params());
      }
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
