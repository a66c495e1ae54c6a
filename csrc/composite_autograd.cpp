// Autograd of composite_fwd and composite_packed_fwd, in C++: a call that records its backward
// crosses Python once, in the forward, and the backward runs without Python (a torch.autograd.Function
// cost a training step more host time than the GPU spent on both kernels).
//
// The forward saves the inputs (made contiguous once) and its chunk_transmittances output; the
// backward hands composite[_packed]_bwd the gradients that reached the four differentiable outputs
// (absent ones as None: the kernels read no zeros) and flags for the gradients wanted. The last two
// outputs (chunk_transmittances, invalid) are not differentiable. Once differentiable: the backward
// kernels have no backward, so a double backward through them raises instead of returning zeros.
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/autograd.h>
#include <torch/library.h>

#include <algorithm>
#include <optional>
#include <type_traits>

#include "common.h"
#include "composite.h"

namespace mixer_nerf {
namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

std::optional<at::Tensor> optional_of(const at::Tensor& t) {
  return t.defined() ? std::optional<at::Tensor>(t) : std::nullopt;
}

// Each layout's ops: names and signatures (packed: offsets after background).
struct Dense {
  using Fwd = CompositeForward(const at::Tensor&, const at::Tensor&, const at::Tensor&, const at::Tensor&,
                               const std::optional<at::Tensor>&);
  using Bwd = CompositeBackward(const std::optional<at::Tensor>&, const std::optional<at::Tensor>&,
                                const std::optional<at::Tensor>&, const std::optional<at::Tensor>&,
                                const at::Tensor&, const at::Tensor&, const at::Tensor&, const at::Tensor&,
                                const std::optional<at::Tensor>&, const at::Tensor&, bool, bool);
  static constexpr const char* fwd_name = "mixer_nerf::composite_fwd";
  static constexpr const char* bwd_name = "mixer_nerf::composite_bwd";
};

struct Packed {
  using Fwd = CompositeForward(const at::Tensor&, const at::Tensor&, const at::Tensor&, const at::Tensor&,
                               const std::optional<at::Tensor>&, const at::Tensor&);
  using Bwd = CompositeBackward(const std::optional<at::Tensor>&, const std::optional<at::Tensor>&,
                                const std::optional<at::Tensor>&, const std::optional<at::Tensor>&,
                                const at::Tensor&, const at::Tensor&, const at::Tensor&, const at::Tensor&,
                                const std::optional<at::Tensor>&, const at::Tensor&, const at::Tensor&, bool, bool);
  static constexpr const char* fwd_name = "mixer_nerf::composite_packed_fwd";
  static constexpr const char* bwd_name = "mixer_nerf::composite_packed_bwd";
};

template <typename Layout>
const c10::TypedOperatorHandle<typename Layout::Fwd>& forward_op() {
  static const auto op = c10::Dispatcher::singleton().findSchemaOrThrow(Layout::fwd_name, "").template typed<typename Layout::Fwd>();
  return op;
}

template <typename Layout>
const c10::TypedOperatorHandle<typename Layout::Bwd>& backward_op() {
  static const auto op = c10::Dispatcher::singleton().findSchemaOrThrow(Layout::bwd_name, "").template typed<typename Layout::Bwd>();
  return op;
}

constexpr int kDifferentiableOutputs = 4;  // color, depth, opacity, weights

// Inputs: sigmas, rgbs, t_starts, t_ends, background, offsets (absent for the dense layout).
template <typename Layout>
struct CompositeFunction : torch::autograd::Function<CompositeFunction<Layout>> {
  static variable_list forward(AutogradContext* ctx, const at::Tensor& sigmas, const at::Tensor& rgbs,
                               const at::Tensor& t_starts, const at::Tensor& t_ends,
                               const std::optional<at::Tensor>& background,
                               const std::optional<at::Tensor>& offsets) {
    at::AutoDispatchBelowADInplaceOrView below_autograd;
    const CompositeTensors in(sigmas, rgbs, t_starts, t_ends, background);
    at::Tensor rows;
    CompositeForward out;
    if constexpr (std::is_same_v<Layout, Packed>) {
      rows = offsets->contiguous();
      out = forward_op<Layout>().call(in.sigmas, in.rgbs, in.t_starts, in.t_ends, in.background, rows);
    } else {
      out = forward_op<Layout>().call(in.sigmas, in.rgbs, in.t_starts, in.t_ends, in.background);
    }
    const auto& [color, depth, opacity, weights, chunk_transmittances, invalid] = out;
    ctx->save_for_backward(
        {in.sigmas, in.rgbs, in.t_starts, in.t_ends, in.background.value_or(at::Tensor()), rows, chunk_transmittances});
    ctx->mark_non_differentiable({chunk_transmittances, invalid});
    ctx->set_materialize_grads(false);
    return {color, depth, opacity, weights, chunk_transmittances, invalid};
  }

  static variable_list backward(AutogradContext* ctx, variable_list grads) {
    variable_list input_grads(6);
    const auto upstream = grads.begin(), upstream_end = grads.begin() + kDifferentiableOutputs;
    if (std::none_of(upstream, upstream_end, [](const at::Tensor& g) { return g.defined(); })) return input_grads;
    MIXER_NERF_CHECK(!at::GradMode::is_enabled() || std::none_of(upstream, upstream_end, [](const at::Tensor& g) {
                       return g.defined() && g.requires_grad();
                     }),
                     "composite: the backward is differentiable once (no double backward through its kernels)");
    const variable_list saved = ctx->get_saved_variables();
    const bool interval_grads = ctx->needs_input_grad(2) || ctx->needs_input_grad(3);
    // needs_input_grad counts the inputs given: background is the fifth when present
    const bool background_grad = saved[4].defined() && ctx->needs_input_grad(4);
    at::AutoDispatchBelowADInplaceOrView below_autograd;
    const auto g = [&](int i) { return optional_of(grads[i]); };
    CompositeBackward result;
    if constexpr (std::is_same_v<Layout, Packed>) {
      result = backward_op<Layout>().call(g(0), g(1), g(2), g(3), saved[0], saved[1], saved[2], saved[3],
                                          optional_of(saved[4]), saved[5], saved[6], interval_grads, background_grad);
    } else {
      result = backward_op<Layout>().call(g(0), g(1), g(2), g(3), saved[0], saved[1], saved[2], saved[3],
                                          optional_of(saved[4]), saved[6], interval_grads, background_grad);
    }
    const auto& [grad_sigmas, grad_rgbs, grad_t_starts, grad_t_ends, grad_background] = result;
    input_grads[0] = grad_sigmas;
    input_grads[1] = grad_rgbs;
    input_grads[2] = grad_t_starts.value_or(at::Tensor());
    input_grads[3] = grad_t_ends.value_or(at::Tensor());
    input_grads[4] = grad_background.value_or(at::Tensor());
    return input_grads;
  }
};

CompositeForward as_tuple(const variable_list& out) { return {out[0], out[1], out[2], out[3], out[4], out[5]}; }

CompositeForward dense_autograd(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                                const at::Tensor& t_ends, const std::optional<at::Tensor>& background) {
  return as_tuple(CompositeFunction<Dense>::apply(sigmas, rgbs, t_starts, t_ends, background, std::nullopt));
}

CompositeForward packed_autograd(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                                 const at::Tensor& t_ends, const std::optional<at::Tensor>& background,
                                 const at::Tensor& offsets) {
  return as_tuple(CompositeFunction<Packed>::apply(sigmas, rgbs, t_starts, t_ends, background, offsets));
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, Autograd, m) {
  m.impl("composite_fwd", &dense_autograd);
  m.impl("composite_packed_fwd", &packed_autograd);
}

}  // namespace mixer_nerf
