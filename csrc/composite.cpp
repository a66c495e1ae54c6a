// composite (volume rendering) on the CPU: one sequential scan per ray, rays in parallel.
//
// Per sample: tau = sigma * (t_end - t_start), E_i = sum_{j<i} tau_j, T_i = exp(-E_i),
// alpha_i = -expm1(-tau_i), w_i = T_i * alpha_i. T is exp of an exclusive sum (never a product
// of 1 - alpha, never a difference of sums), and w uses expm1, so w keeps full relative accuracy
// for tiny tau and is exactly T_i for huge tau. Per ray: opacity = sum w_i = -expm1(-E_S) and
// 1 - opacity = exp(-E_S) (telescoping), both computed in the stable closed form.
//
// Backward (O(S) per ray): with g_i the upstream gradient reaching w_i (grad_weights_i +
// grad_color . rgb_i + grad_depth * midpoint_i) and the background treated as a sample S of
// weight T_S and g_S = grad_color . background - grad_opacity,
//   dL/dtau_j = T_{j+1} * (g_j - G_{j+1}),  G_j = sum_{i>=j} g_i w_i / T_j
//             = alpha_j g_j + exp(-tau_j) G_{j+1},  G_S = g_S.
// G is a convex combination of upstream gradients (bounded, no cancellation, no division by an
// underflowed T), so the gradient stays exact when T underflows or tau is 1e18 (delta = 1e10).
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <optional>
#include <tuple>
#include <vector>

#include "common.h"

namespace mixer_nerf {
namespace {

// Inputs of a batch of rays. A ray's samples are `count` consecutive rows from `offset`, so the
// same per-ray scans serve the padded (R, S) layout and a packed (ragged) one.
template <typename scalar_t>
struct CompositeInputs {
  const scalar_t* sigmas;      // (N)
  const scalar_t* rgbs;        // (N, C)
  const scalar_t* t_starts;    // (N)
  const scalar_t* t_ends;      // (N)
  const scalar_t* background;  // nullptr, or row r at background + r * background_stride
  int64_t background_stride;   // 0 for one background (C), C for one per ray (R, C)
  int64_t channels;
};

// Upstream gradients; a nullptr stands for zeros. grad_t_* are nullptr when not wanted.
template <typename scalar_t>
struct CompositeGrads {
  const scalar_t* color;    // (R, C)
  const scalar_t* depth;    // (R)
  const scalar_t* opacity;  // (R)
  const scalar_t* weights;  // (N)
  scalar_t* sigmas;         // (N)
  scalar_t* rgbs;           // (N, C)
  scalar_t* t_starts;       // (N) or nullptr
  scalar_t* t_ends;         // (N) or nullptr
  acc_t<scalar_t>* background_rows;  // (R, C) per-ray background gradient, or nullptr
};

template <typename scalar_t>
struct Sample {
  using acc = acc_t<scalar_t>;
  acc sigma, t_start, t_end, tau;
  Sample(const CompositeInputs<scalar_t>& in, int64_t i)
      : sigma(in.sigmas[i]), t_start(in.t_starts[i]), t_end(in.t_ends[i]), tau(sigma * (t_end - t_start)) {}
  acc midpoint() const { return acc(0.5) * (t_start + t_end); }
};

// Forward scan of one ray; color_acc is caller scratch of C accumulators.
template <typename scalar_t>
void composite_forward_ray(const CompositeInputs<scalar_t>& in, int64_t ray, int64_t offset, int64_t count,
                           acc_t<scalar_t>* color_acc, scalar_t* color, scalar_t* depth, scalar_t* opacity,
                           scalar_t* weights) {
  using acc = acc_t<scalar_t>;
  const int64_t C = in.channels;
  std::fill(color_acc, color_acc + C, acc(0));
  acc optical_depth = 0, depth_acc = 0;
  for (int64_t i = offset; i < offset + count; ++i) {
    const Sample<scalar_t> s(in, i);
    const acc w = std::exp(-optical_depth) * -std::expm1(-s.tau);
    optical_depth += s.tau;
    weights[i] = static_cast<scalar_t>(w);
    depth_acc += w * s.midpoint();
    const scalar_t* rgb = in.rgbs + i * C;
    for (int64_t c = 0; c < C; ++c) color_acc[c] += w * acc(rgb[c]);
  }
  const acc transmittance = std::exp(-optical_depth);
  const scalar_t* bg = in.background ? in.background + ray * in.background_stride : nullptr;
  for (int64_t c = 0; c < C; ++c) {
    color[ray * C + c] = static_cast<scalar_t>(color_acc[c] + (bg ? transmittance * acc(bg[c]) : acc(0)));
  }
  depth[ray] = static_cast<scalar_t>(depth_acc);
  opacity[ray] = static_cast<scalar_t>(-std::expm1(-optical_depth));
}

// Backward of one ray: a forward pass records T_{i+1} in `transmittance_after` (caller scratch
// of `count` entries; a reverse pass cannot rebuild it without subtracting sums), then one
// reverse pass carries G (see the file comment).
template <typename scalar_t>
void composite_backward_ray(const CompositeInputs<scalar_t>& in, const CompositeGrads<scalar_t>& g, int64_t ray,
                            int64_t offset, int64_t count, acc_t<scalar_t>* transmittance_after) {
  using acc = acc_t<scalar_t>;
  const int64_t C = in.channels;
  acc optical_depth = 0;
  for (int64_t k = 0; k < count; ++k) {
    optical_depth += Sample<scalar_t>(in, offset + k).tau;
    transmittance_after[k] = std::exp(-optical_depth);
  }
  const acc transmittance_end = count > 0 ? transmittance_after[count - 1] : acc(1);
  const scalar_t* grad_color = g.color ? g.color + ray * C : nullptr;
  const acc grad_depth = g.depth ? acc(g.depth[ray]) : acc(0);

  acc G = g.opacity ? -acc(g.opacity[ray]) : acc(0);
  if (in.background && grad_color) {
    const scalar_t* bg = in.background + ray * in.background_stride;
    for (int64_t c = 0; c < C; ++c) G += acc(grad_color[c]) * acc(bg[c]);
  }
  if (g.background_rows) {
    for (int64_t c = 0; c < C; ++c) {
      g.background_rows[ray * C + c] = grad_color ? acc(grad_color[c]) * transmittance_end : acc(0);
    }
  }
  for (int64_t k = count - 1; k >= 0; --k) {
    const int64_t i = offset + k;
    const Sample<scalar_t> s(in, i);
    const acc alpha = -std::expm1(-s.tau);
    const acc w = (k > 0 ? transmittance_after[k - 1] : acc(1)) * alpha;
    const scalar_t* rgb = in.rgbs + i * C;
    acc g_i = grad_depth * s.midpoint() + (g.weights ? acc(g.weights[i]) : acc(0));
    for (int64_t c = 0; c < C; ++c) {
      const acc gc = grad_color ? acc(grad_color[c]) : acc(0);
      g_i += gc * acc(rgb[c]);
      g.rgbs[i * C + c] = static_cast<scalar_t>(gc * w);
    }
    const acc grad_tau = transmittance_after[k] * (g_i - G);
    G = alpha * g_i + std::exp(-s.tau) * G;
    g.sigmas[i] = static_cast<scalar_t>(grad_tau * (s.t_end - s.t_start));
    if (g.t_starts) {
      const acc from_depth = acc(0.5) * grad_depth * w;
      g.t_starts[i] = static_cast<scalar_t>(from_depth - grad_tau * s.sigma);
      g.t_ends[i] = static_cast<scalar_t>(from_depth + grad_tau * s.sigma);
    }
  }
}

void check_inputs(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                  const at::Tensor& t_ends, const std::optional<at::Tensor>& background) {
  MIXER_NERF_CHECK_INPUT(sigmas, at::kCPU);
  MIXER_NERF_CHECK_INPUT(rgbs, at::kCPU);
  MIXER_NERF_CHECK_INPUT(t_starts, at::kCPU);
  MIXER_NERF_CHECK_INPUT(t_ends, at::kCPU);
  TORCH_CHECK(sigmas.dim() == 2 && rgbs.dim() == 3, "composite: sigmas (R, S) and rgbs (R, S, C) expected");
  TORCH_CHECK(rgbs.size(0) == sigmas.size(0) && rgbs.size(1) == sigmas.size(1), "composite: rgbs/sigmas mismatch");
  TORCH_CHECK(t_starts.sizes() == sigmas.sizes() && t_ends.sizes() == sigmas.sizes(),
              "composite: t_starts/t_ends must match sigmas");
  if (background) {
    MIXER_NERF_CHECK_INPUT(*background, at::kCPU);
    const bool shared = background->dim() == 1 && background->size(0) == rgbs.size(2);
    const bool per_ray = background->dim() == 2 && background->size(0) == rgbs.size(0) &&
                         background->size(1) == rgbs.size(2);
    TORCH_CHECK(shared || per_ray, "composite: background must be (C) or (R, C)");
  }
}

template <typename scalar_t>
CompositeInputs<scalar_t> inputs_of(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                                    const at::Tensor& t_ends, const std::optional<at::Tensor>& background) {
  const bool per_ray = background && background->dim() == 2;
  return {sigmas.const_data_ptr<scalar_t>(),
          rgbs.const_data_ptr<scalar_t>(),
          t_starts.const_data_ptr<scalar_t>(),
          t_ends.const_data_ptr<scalar_t>(),
          background ? background->const_data_ptr<scalar_t>() : nullptr,
          per_ray ? rgbs.size(2) : 0,
          rgbs.size(2)};
}

int64_t ray_grain(int64_t samples_per_ray) { return std::max<int64_t>(1, 4096 / std::max<int64_t>(1, samples_per_ray)); }

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> composite_fwd_cpu(
    const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts, const at::Tensor& t_ends,
    const std::optional<at::Tensor>& background) {
  check_inputs(sigmas, rgbs, t_starts, t_ends, background);
  const int64_t R = sigmas.size(0), S = sigmas.size(1), C = rgbs.size(2);
  at::Tensor color = at::empty({R, C}, sigmas.options());
  at::Tensor depth = at::empty({R}, sigmas.options());
  at::Tensor opacity = at::empty({R}, sigmas.options());
  at::Tensor weights = at::empty({R, S}, sigmas.options());
  MIXER_NERF_DISPATCH_FLOATING(sigmas.scalar_type(), "composite_fwd_cpu", [&] {
    const auto in = inputs_of<scalar_t>(sigmas, rgbs, t_starts, t_ends, background);
    at::parallel_for(0, R, ray_grain(S), [&](int64_t begin, int64_t end) {
      std::vector<acc_t<scalar_t>> color_acc(C);
      for (int64_t r = begin; r < end; ++r) {
        composite_forward_ray(in, r, r * S, S, color_acc.data(), color.data_ptr<scalar_t>(),
                              depth.data_ptr<scalar_t>(), opacity.data_ptr<scalar_t>(), weights.data_ptr<scalar_t>());
      }
    });
  });
  return {color, depth, opacity, weights};
}

const void* data_or_null(const std::optional<at::Tensor>& t) { return t ? t->const_data_ptr() : nullptr; }

std::tuple<at::Tensor, at::Tensor, std::optional<at::Tensor>, std::optional<at::Tensor>, std::optional<at::Tensor>>
composite_bwd_cpu(const std::optional<at::Tensor>& grad_color, const std::optional<at::Tensor>& grad_depth,
                  const std::optional<at::Tensor>& grad_opacity, const std::optional<at::Tensor>& grad_weights,
                  const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                  const at::Tensor& t_ends, const std::optional<at::Tensor>& background, bool interval_grads) {
  check_inputs(sigmas, rgbs, t_starts, t_ends, background);
  const int64_t R = sigmas.size(0), S = sigmas.size(1), C = rgbs.size(2);
  for (const auto* grad : {&grad_color, &grad_depth, &grad_opacity, &grad_weights}) {
    if (*grad) {
      const at::Tensor& upstream = **grad;
      MIXER_NERF_CHECK_INPUT(upstream, at::kCPU);
      TORCH_CHECK(upstream.scalar_type() == sigmas.scalar_type(), "composite_bwd: gradient dtype mismatch");
    }
  }
  TORCH_CHECK(!grad_color || grad_color->sizes() == at::IntArrayRef({R, C}), "grad_color must be (R, C)");
  TORCH_CHECK(!grad_depth || grad_depth->sizes() == at::IntArrayRef({R}), "grad_depth must be (R)");
  TORCH_CHECK(!grad_opacity || grad_opacity->sizes() == at::IntArrayRef({R}), "grad_opacity must be (R)");
  TORCH_CHECK(!grad_weights || grad_weights->sizes() == sigmas.sizes(), "grad_weights must be (R, S)");

  at::Tensor grad_sigmas = at::empty_like(sigmas);
  at::Tensor grad_rgbs = at::empty_like(rgbs);
  std::optional<at::Tensor> grad_t_starts, grad_t_ends, grad_background;
  if (interval_grads) {
    grad_t_starts = at::empty_like(t_starts);
    grad_t_ends = at::empty_like(t_ends);
  }
  const at::ScalarType acc_type = at::toOpMathType(sigmas.scalar_type());
  at::Tensor background_rows;
  if (background) background_rows = at::empty({R, C}, sigmas.options().dtype(acc_type));

  MIXER_NERF_DISPATCH_FLOATING(sigmas.scalar_type(), "composite_bwd_cpu", [&] {
    using acc = acc_t<scalar_t>;
    const auto in = inputs_of<scalar_t>(sigmas, rgbs, t_starts, t_ends, background);
    const CompositeGrads<scalar_t> g{
        static_cast<const scalar_t*>(data_or_null(grad_color)),
        static_cast<const scalar_t*>(data_or_null(grad_depth)),
        static_cast<const scalar_t*>(data_or_null(grad_opacity)),
        static_cast<const scalar_t*>(data_or_null(grad_weights)),
        grad_sigmas.data_ptr<scalar_t>(),
        grad_rgbs.data_ptr<scalar_t>(),
        interval_grads ? grad_t_starts->data_ptr<scalar_t>() : nullptr,
        interval_grads ? grad_t_ends->data_ptr<scalar_t>() : nullptr,
        background ? background_rows.data_ptr<acc>() : nullptr};
    at::parallel_for(0, R, ray_grain(S), [&](int64_t begin, int64_t end) {
      std::vector<acc> transmittance_after(S);
      for (int64_t r = begin; r < end; ++r) composite_backward_ray(in, g, r, r * S, S, transmittance_after.data());
    });
  });
  if (background) {
    grad_background = (background->dim() == 1 ? background_rows.sum(0) : background_rows).to(sigmas.scalar_type());
  }
  return {grad_sigmas, grad_rgbs, grad_t_starts, grad_t_ends, grad_background};
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CPU, m) {
  m.impl("composite_fwd", &composite_fwd_cpu);
  m.impl("composite_bwd", &composite_bwd_cpu);
}

}  // namespace mixer_nerf
