// The autograd of every op with a backward kernel, in C++: a call that records its backward crosses
// Python once, in the forward, and the backward runs without Python (a torch.autograd.Function per
// op cost a training step more host time than the GPU spent on a composite's two kernels).
//
// Each op's forward `<op>_fwd` gets a boxed Autograd kernel. It makes the tensor arguments
// contiguous, runs the forward below autograd, saves the tensor arguments (and the outputs the
// backward takes) and records a node whose backward calls the op's backward kernel on the upstream
// gradients of the differentiable outputs (absent ones as None: the kernels read no zeros), the
// arguments as called and what the op adds (flags for the gradients wanted, a saved output). The
// backward kernel returns the gradients of the leading arguments. Outputs past `differentiable`
// (positions drawn, findings about the inputs) carry no gradient. Once differentiable: the backward
// kernels have no backward, so a double backward through them raises.
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/autograd.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <iterator>
#include <string>
#include <vector>

#include "common.h"

namespace mixer_nerf {
namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;
using Stack = std::vector<c10::IValue>;

// The backward kernel's arguments: the upstream gradients, then the forward's arguments.
struct UpstreamThenArguments {
  static constexpr std::array<int, 0> saved_outputs{};
  static Stack backward_args(Stack grads, const Stack& args, const variable_list& /*saved_outputs*/,
                             const std::vector<bool>& /*wants*/) {
    grads.insert(grads.end(), args.begin(), args.end());
    return grads;
  }
};

struct PositionalEncoding : UpstreamThenArguments {
  static constexpr const char* forward = "mixer_nerf::positional_encoding_fwd";
  static constexpr const char* backward = "mixer_nerf::positional_encoding_bwd";
  static constexpr int differentiable = 1;
};

struct SamplePdf : UpstreamThenArguments {
  static constexpr const char* forward = "mixer_nerf::sample_pdf_fwd";
  static constexpr const char* backward = "mixer_nerf::sample_pdf_bwd";
  static constexpr int differentiable = 1;
};

struct SamplePdfPacked : UpstreamThenArguments {
  static constexpr const char* forward = "mixer_nerf::sample_pdf_packed_fwd";
  static constexpr const char* backward = "mixer_nerf::sample_pdf_packed_bwd";
  static constexpr int differentiable = 1;
};

struct RayScale : UpstreamThenArguments {
  static constexpr const char* forward = "mixer_nerf::ray_scale_fwd";
  static constexpr const char* backward = "mixer_nerf::ray_scale_bwd";
  static constexpr int differentiable = 1;
};

// mlca_bwd's last argument: whether the encoding wants a gradient (positions' need none in training).
struct Mlca {
  static constexpr const char* forward = "mixer_nerf::mlca_fwd";
  static constexpr const char* backward = "mixer_nerf::mlca_bwd";
  static constexpr int differentiable = 1;
  static constexpr std::array<int, 0> saved_outputs{};
  static Stack backward_args(Stack grads, const Stack& args, const variable_list& saved_outputs,
                             const std::vector<bool>& wants) {
    Stack out = UpstreamThenArguments::backward_args(std::move(grads), args, saved_outputs, wants);
    out.emplace_back(static_cast<bool>(wants[0]));
    return out;
  }
};

// segment_mean_bwd(grad, offsets, num_rows): it spreads each ray's mean over the ray's rows.
struct SegmentMean {
  static constexpr const char* forward = "mixer_nerf::segment_mean_fwd";
  static constexpr const char* backward = "mixer_nerf::segment_mean_bwd";
  static constexpr int differentiable = 1;
  static constexpr std::array<int, 0> saved_outputs{};
  static Stack backward_args(Stack grads, const Stack& args, const variable_list& /*saved_outputs*/,
                             const std::vector<bool>& /*wants*/) {
    grads.push_back(args[1]);
    grads.emplace_back(args[0].toTensor().size(0));
    return grads;
  }
};

// *_stratified_fwd(*pdf, num_samples, generator, weight_padding, keep_positions) -> (samples,
// positions drawn, invalid): the given-positions op's backward on the positions drawn (kept: the
// caller asks for keep_positions where a backward is recorded). `pdf` is (bins, weights[, offsets]).
template <int pdf_arguments>
struct Stratified {
  static constexpr int differentiable = 1;
  static constexpr std::array<int, 1> saved_outputs{1};
  static Stack backward_args(Stack grads, const Stack& args, const variable_list& saved_outputs,
                             const std::vector<bool>& /*wants*/) {
    grads.insert(grads.end(), args.begin(), args.begin() + pdf_arguments);
    grads.emplace_back(saved_outputs[0]);
    grads.push_back(args[pdf_arguments + 2]);  // weight_padding
    return grads;
  }
};

struct SamplePdfStratified : Stratified<2> {
  static constexpr const char* forward = "mixer_nerf::sample_pdf_stratified_fwd";
  static constexpr const char* backward = "mixer_nerf::sample_pdf_bwd";
};

struct SamplePdfPackedStratified : Stratified<3> {
  static constexpr const char* forward = "mixer_nerf::sample_pdf_packed_stratified_fwd";
  static constexpr const char* backward = "mixer_nerf::sample_pdf_packed_bwd";
};

// composite[_packed]_fwd -> (color, depth, opacity, weights, chunk_transmittances, invalid): the
// backward also takes chunk_transmittances and flags for the intervals' and the background's gradients.
struct CompositeBackwardArgs {
  static constexpr int differentiable = 4;
  static constexpr std::array<int, 1> saved_outputs{4};
  static Stack backward_args(Stack grads, const Stack& args, const variable_list& saved_outputs,
                             const std::vector<bool>& wants) {
    grads.insert(grads.end(), args.begin(), args.end());
    grads.emplace_back(saved_outputs[0]);
    grads.emplace_back(static_cast<bool>(wants[2] || wants[3]));
    grads.emplace_back(static_cast<bool>(wants[4]));
    return grads;
  }
};

struct Composite : CompositeBackwardArgs {
  static constexpr const char* forward = "mixer_nerf::composite_fwd";
  static constexpr const char* backward = "mixer_nerf::composite_bwd";
};

struct CompositePacked : CompositeBackwardArgs {
  static constexpr const char* forward = "mixer_nerf::composite_packed_fwd";
  static constexpr const char* backward = "mixer_nerf::composite_packed_bwd";
};

c10::OperatorHandle find_op(const char* name) {
  return c10::Dispatcher::singleton().findSchemaOrThrow(name, "");
}

// The tensor arguments (`tensors`, the inputs autograd sees) sit at `args`' tensor slots.
template <typename Op>
struct KernelFunction : torch::autograd::Function<KernelFunction<Op>> {
  static variable_list forward(AutogradContext* ctx, Stack args, at::TensorList tensors) {
    at::AutoDispatchBelowADInplaceOrView below_autograd;
    static const c10::OperatorHandle op = find_op(Op::forward);
    Stack stack = args;
    op.callBoxed(stack);
    variable_list outputs;
    outputs.reserve(stack.size());
    for (c10::IValue& out : stack) outputs.push_back(std::move(out).toTensor());

    variable_list saved(tensors.begin(), tensors.end());
    for (int i : Op::saved_outputs) saved.push_back(outputs[i]);
    ctx->save_for_backward(saved);
    int64_t slots = 0;  // bit i: argument i is a tensor (schemas have fewer than 64 arguments)
    for (size_t i = 0; i < args.size(); ++i) {
      if (args[i].isTensor()) {
        slots |= int64_t{1} << i;
        args[i] = c10::IValue();  // saved above
      }
    }
    ctx->saved_data["slots"] = slots;
    ctx->saved_data["args"] = c10::ivalue::Tuple::create(std::move(args));
    ctx->mark_non_differentiable(variable_list(outputs.begin() + Op::differentiable, outputs.end()));
    ctx->set_materialize_grads(false);
    return outputs;
  }

  static variable_list backward(AutogradContext* ctx, variable_list grads) {
    Stack args = ctx->saved_data["args"].toTupleRef().elements().vec();
    std::vector<size_t> slots;  // the tensor arguments' indices, in order
    const int64_t mask = ctx->saved_data["slots"].toInt();
    for (size_t i = 0; i < args.size(); ++i) {
      if (mask >> i & 1) slots.push_back(i);
    }
    variable_list input_grads(1 + slots.size());  // none for `args`, one per tensor
    const auto upstream_end = grads.begin() + Op::differentiable;
    if (std::none_of(grads.begin(), upstream_end, [](const at::Tensor& g) { return g.defined(); })) {
      return input_grads;
    }
    MIXER_NERF_CHECK(!at::GradMode::is_enabled() || std::none_of(grads.begin(), upstream_end, [](const at::Tensor& g) {
                       return g.defined() && g.requires_grad();
                     }),
                     Op::forward, ": the backward is differentiable once (no double backward through its kernels)");
    const variable_list saved = ctx->get_saved_variables();
    std::vector<bool> wants(args.size(), false);
    for (size_t k = 0; k < slots.size(); ++k) {
      args[slots[k]] = saved[k];
      wants[slots[k]] = ctx->needs_input_grad(k);
    }
    const variable_list saved_outputs(saved.begin() + slots.size(), saved.end());
    Stack upstream;
    for (auto g = grads.begin(); g != upstream_end; ++g) {
      upstream.emplace_back(g->defined() ? c10::IValue(g->contiguous()) : c10::IValue());
    }
    Stack stack = Op::backward_args(std::move(upstream), args, saved_outputs, wants);
    at::AutoDispatchBelowADInplaceOrView below_autograd;
    static const c10::OperatorHandle op = find_op(Op::backward);
    op.callBoxed(stack);
    // stack[i]: the gradient of argument i (None where not computed)
    for (size_t k = 0; k < slots.size(); ++k) {
      const size_t i = slots[k];
      if (i < stack.size() && stack[i].isTensor()) input_grads[1 + k] = stack[i].toTensor();
    }
    return input_grads;
  }
};

template <typename Op>
void autograd_kernel(const c10::OperatorHandle& op, torch::jit::Stack* stack) {
  const size_t n = op.schema().arguments().size();
  Stack args(stack->end() - static_cast<std::ptrdiff_t>(n), stack->end());
  torch::jit::drop(*stack, n);
  std::vector<at::Tensor> tensors;
  bool records = false;
  for (c10::IValue& arg : args) {
    if (arg.isTensor()) {
      arg = arg.toTensor().contiguous();
      tensors.push_back(arg.toTensor());
      records |= tensors.back().requires_grad();
    }
  }
  if (!records || !at::GradMode::is_enabled()) {  // nothing to record: the kernel alone
    at::AutoDispatchBelowADInplaceOrView below_autograd;
    stack->insert(stack->end(), std::make_move_iterator(args.begin()), std::make_move_iterator(args.end()));
    op.callBoxed(*stack);
    return;
  }
  for (at::Tensor& out : KernelFunction<Op>::apply(std::move(args), at::TensorList(tensors))) {
    stack->emplace_back(std::move(out));
  }
}

template <typename Op>
void register_autograd(torch::Library& m) {
  m.impl(Op::forward + std::char_traits<char>::length("mixer_nerf::"),
         torch::CppFunction::makeFromBoxedFunction<&autograd_kernel<Op>>());
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, Autograd, m) {
  register_autograd<PositionalEncoding>(m);
  register_autograd<SamplePdf>(m);
  register_autograd<SamplePdfPacked>(m);
  register_autograd<SamplePdfStratified>(m);
  register_autograd<SamplePdfPackedStratified>(m);
  register_autograd<Mlca>(m);
  register_autograd<SegmentMean>(m);
  register_autograd<RayScale>(m);
  register_autograd<Composite>(m);
  register_autograd<CompositePacked>(m);
}

}  // namespace mixer_nerf
