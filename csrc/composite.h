// What the CPU and CUDA kernels of composite and composite_packed share: the kernels' arguments
// and host-side checks. The per-ray scans take a ray's (offset, count) from ray_layout.h, so one
// scan serves the padded (R, S) layout and the packed (ragged, CSR) one.
#pragma once

#include <ATen/ATen.h>
#include <torch/library.h>

#include <cstdint>
#include <optional>
#include <tuple>
#include <utility>
#include <vector>

#include "common.h"
#include "ray_layout.h"

namespace mixer_nerf {

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

template <typename scalar_t>
struct CompositeOutputs {
  scalar_t* color;    // (R, C)
  scalar_t* depth;    // (R)
  scalar_t* opacity;  // (R)
  scalar_t* weights;  // (N)
  double* chunk_transmittances;  // the device's entries (see CompositeForward), nullptr where it has none
  int32_t* invalid;   // (1): the InvalidInput bits of the values the forward read
};

// What a forward finds wrong in the values it reads anyway, OR-ed into its `invalid` output: a GPU
// caller learns of bad values without a host synchronisation (mixer_nerf/ops/deferred_checks.py
// reads it later; the bits are mirrored in mixer_nerf/ops/composite.py).
enum InvalidInput : int32_t {
  kNegativeSigma = 1,     // a density below 0
  kReversedInterval = 2,  // t_end < t_start
  kBadOffsets = 4,        // packed offsets not from 0 to N, or decreasing
};

// The bits of one sample's values.
template <typename T>
C10_HOST_DEVICE inline int32_t invalid_sample_bits(T sigma, T t_start, T t_end) {
  return (sigma < T(0) ? kNegativeSigma : 0) | (t_end < t_start ? kReversedInterval : 0);
}

// Upstream gradients (nullptr: zeros) and the gradients to write (grad_t_*: nullptr to skip).
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

// Host-side checks of both layouts (Python validates first, with clear messages; these only keep a
// direct call of the op from reading out of bounds): sigmas (N) packed or (R, S) dense, rgbs
// (*sigmas.shape, C), bounds like sigmas, background (C) or (R, C).
inline void check_composite_inputs(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                                   const at::Tensor& t_ends, const std::optional<at::Tensor>& background,
                                   int64_t rays, at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(sigmas, device);
  MIXER_NERF_CHECK_INPUT(rgbs, device);
  MIXER_NERF_CHECK_INPUT(t_starts, device);
  MIXER_NERF_CHECK_INPUT(t_ends, device);
  MIXER_NERF_CHECK(rgbs.dim() == sigmas.dim() + 1 && rgbs.sizes().slice(0, sigmas.dim()) == sigmas.sizes(),
              "composite: rgbs must be (*sigmas.shape, C)");
  MIXER_NERF_CHECK(t_starts.sizes() == sigmas.sizes() && t_ends.sizes() == sigmas.sizes(),
              "composite: t_starts/t_ends must match sigmas");
  for (const at::Tensor* t : {&rgbs, &t_starts, &t_ends}) {
    MIXER_NERF_CHECK(t->scalar_type() == sigmas.scalar_type(), "composite: inputs must share one dtype");
  }
  if (background) {
    MIXER_NERF_CHECK_INPUT(*background, device);
    MIXER_NERF_CHECK(background->scalar_type() == sigmas.scalar_type(), "composite: inputs must share one dtype");
    const int64_t C = rgbs.size(-1);
    const bool shared = background->dim() == 1 && background->size(0) == C;
    const bool per_ray = background->dim() == 2 && background->size(0) == rays && background->size(1) == C;
    MIXER_NERF_CHECK(shared || per_ray, "composite: background must be (C) or (R, C)");
  }
}

inline void check_dense(const at::Tensor& sigmas) {
  MIXER_NERF_CHECK(sigmas.dim() == 2, "composite: sigmas must be (R, S)");
}

// Packed samples: sigmas (N), offsets (R+1) int64. Returns R.
inline int64_t check_packed(const at::Tensor& sigmas, const at::Tensor& offsets, at::DeviceType device) {
  MIXER_NERF_CHECK(sigmas.dim() == 1, "composite_packed: sigmas must be (N)");
  MIXER_NERF_CHECK_INPUT(offsets, device);
  MIXER_NERF_CHECK(offsets.scalar_type() == at::kLong && offsets.dim() == 1 && offsets.size(0) >= 1,
              "composite_packed: offsets must be (R+1) int64");
  return offsets.size(0) - 1;
}

inline std::optional<at::Tensor> contiguous(const std::optional<at::Tensor>& t) {
  return t ? std::optional<at::Tensor>(t->contiguous()) : std::nullopt;
}

// One call's input tensors, contiguous (the ops take any strides; a contiguous one is not copied).
struct CompositeTensors {
  at::Tensor sigmas, rgbs, t_starts, t_ends;
  std::optional<at::Tensor> background;

  CompositeTensors(const at::Tensor& sigmas_, const at::Tensor& rgbs_, const at::Tensor& t_starts_,
                   const at::Tensor& t_ends_, const std::optional<at::Tensor>& background_)
      : sigmas(sigmas_.contiguous()),
        rgbs(rgbs_.contiguous()),
        t_starts(t_starts_.contiguous()),
        t_ends(t_ends_.contiguous()),
        background(contiguous(background_)) {}

  template <typename scalar_t>
  CompositeInputs<scalar_t> pointers() const {
    const int64_t C = rgbs.size(-1);
    const bool per_ray = background && background->dim() == 2;
    return {sigmas.const_data_ptr<scalar_t>(),
            rgbs.const_data_ptr<scalar_t>(),
            t_starts.const_data_ptr<scalar_t>(),
            t_ends.const_data_ptr<scalar_t>(),
            background ? background->const_data_ptr<scalar_t>() : nullptr,
            per_ray ? C : 0,
            C};
  }
};

// The upstream gradients of a backward, each absent (zeros) or shaped like its output; contiguous.
struct Upstream {
  std::optional<at::Tensor> color, depth, opacity, weights;

  Upstream(const std::optional<at::Tensor>& color_, const std::optional<at::Tensor>& depth_,
           const std::optional<at::Tensor>& opacity_, const std::optional<at::Tensor>& weights_)
      : color(contiguous(color_)), depth(contiguous(depth_)), opacity(contiguous(opacity_)),
        weights(contiguous(weights_)) {}
};

// Upstream gradients: each absent (zeros) or of its output's shape and dtype.
inline void check_upstream(const Upstream& up, const at::Tensor& sigmas, const at::Tensor& rgbs, int64_t rays,
                           at::DeviceType device) {
  const std::vector<int64_t> color_shape{rays, rgbs.size(-1)}, ray_shape{rays};
  const std::pair<const std::optional<at::Tensor>*, at::IntArrayRef> expected[] = {
      {&up.color, color_shape}, {&up.depth, ray_shape}, {&up.opacity, ray_shape}, {&up.weights, sigmas.sizes()}};
  for (const auto& [grad, shape] : expected) {
    if (!*grad) continue;
    const at::Tensor& upstream = **grad;
    MIXER_NERF_CHECK_INPUT(upstream, device);
    MIXER_NERF_CHECK(upstream.scalar_type() == sigmas.scalar_type(), "composite_bwd: gradient dtype mismatch");
    MIXER_NERF_CHECK(upstream.sizes() == shape, "composite_bwd: gradient of shape ", upstream.sizes(), ", expected ", shape);
  }
}

template <typename scalar_t>
const scalar_t* data_or_null(const std::optional<at::Tensor>& t) {
  return t ? t->const_data_ptr<scalar_t>() : nullptr;
}

// What a forward returns: color (R, C), depth (R), opacity (R), weights like sigmas, the
// transmittances its backward starts from (float64, Device::chunk_transmittance_entries(N, R) of them: the
// CUDA kernels keep one per chunk of a ray, the CPU none), invalid (1) int32 (InvalidInput bits); and a
// backward: the gradients of sigmas, rgbs, t_starts, t_ends (absent without interval_grads) and
// background (absent without one).
using CompositeForward = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;
using CompositeBackward =
    std::tuple<at::Tensor, at::Tensor, std::optional<at::Tensor>, std::optional<at::Tensor>, std::optional<at::Tensor>>;

inline CompositeForward empty_outputs(const at::Tensor& sigmas, const at::Tensor& rgbs, int64_t rays,
                                      int64_t chunk_transmittance_entries) {
  return {at::empty({rays, rgbs.size(-1)}, sigmas.options()), at::empty({rays}, sigmas.options()),
          at::empty({rays}, sigmas.options()), at::empty_like(sigmas),
          at::empty({chunk_transmittance_entries}, sigmas.options().dtype(at::kDouble)),
          at::zeros({1}, sigmas.options().dtype(at::kInt))};
}

template <typename scalar_t>
CompositeOutputs<scalar_t> outputs_of(CompositeForward& outputs) {
  auto& [color, depth, opacity, weights, chunk_transmittances, invalid] = outputs;
  return {color.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(), opacity.data_ptr<scalar_t>(),
          weights.data_ptr<scalar_t>(), chunk_transmittances.numel() ? chunk_transmittances.data_ptr<double>() : nullptr,
          invalid.data_ptr<int32_t>()};
}

// The gradients a backward writes, and the per-ray background gradient in the accumulation type
// (summed over rays afterwards for a shared background; undefined without a background or where
// its gradient is not wanted, e.g. a constant colour: no (R, C) writes and no sum then).
struct CompositeGradTensors {
  at::Tensor sigmas, rgbs;
  std::optional<at::Tensor> t_starts, t_ends;
  at::Tensor background_rows;

  CompositeGradTensors(const at::Tensor& sigmas_, const at::Tensor& rgbs_, const std::optional<at::Tensor>& background,
                       int64_t rays, bool interval_grads, bool background_grad)
      : sigmas(at::empty_like(sigmas_)), rgbs(at::empty_like(rgbs_)) {
    if (interval_grads) {
      t_starts = at::empty_like(sigmas_);
      t_ends = at::empty_like(sigmas_);
    }
    if (background && background_grad) {
      background_rows = at::empty({rays, rgbs_.size(-1)}, sigmas_.options().dtype(at::toOpMathType(sigmas_.scalar_type())));
    }
  }

  template <typename scalar_t>
  CompositeGrads<scalar_t> pointers(const Upstream& up) {
    return {data_or_null<scalar_t>(up.color),
            data_or_null<scalar_t>(up.depth),
            data_or_null<scalar_t>(up.opacity),
            data_or_null<scalar_t>(up.weights),
            sigmas.data_ptr<scalar_t>(),
            rgbs.data_ptr<scalar_t>(),
            t_starts ? t_starts->data_ptr<scalar_t>() : nullptr,
            t_ends ? t_ends->data_ptr<scalar_t>() : nullptr,
            background_rows.defined() ? background_rows.data_ptr<acc_t<scalar_t>>() : nullptr};
  }

  CompositeBackward finish(const std::optional<at::Tensor>& background) const {
    std::optional<at::Tensor> grad_background;
    if (background_rows.defined()) {
      grad_background = (background->dim() == 1 ? background_rows.sum(0) : background_rows).to(sigmas.scalar_type());
    }
    return {sigmas, rgbs, t_starts, t_ends, grad_background};
  }
};

// The four composite ops of one device: the checks both devices share and the choice of layout,
// then Device::forward (returns the outputs) and Device::backward (fills `grads`), templates over
// the layout given R rays, which the device's source registers with register_ops.
template <typename Device>
struct CompositeOps {
  template <typename Rays>
  static CompositeForward forward(const CompositeTensors& in, int64_t R, Rays rays) {
    check_composite_inputs(in.sigmas, in.rgbs, in.t_starts, in.t_ends, in.background, R, Device::kind);
    return Device::forward(in, R, rays);
  }

  template <typename Rays>
  static CompositeBackward backward(const Upstream& up, const CompositeTensors& in,
                                    const at::Tensor& chunk_transmittances, bool interval_grads,
                                    bool background_grad, int64_t R, Rays rays) {
    check_composite_inputs(in.sigmas, in.rgbs, in.t_starts, in.t_ends, in.background, R, Device::kind);
    check_upstream(up, in.sigmas, in.rgbs, R, Device::kind);
    MIXER_NERF_CHECK_INPUT(chunk_transmittances, Device::kind);
    MIXER_NERF_CHECK(chunk_transmittances.scalar_type() == at::kDouble && chunk_transmittances.dim() == 1 &&
                         chunk_transmittances.size(0) == Device::chunk_transmittance_entries(in.sigmas.numel(), R),
                     "composite_bwd: chunk_transmittances must be the forward's output for these inputs");
    CompositeGradTensors grads(in.sigmas, in.rgbs, in.background, R, interval_grads, background_grad);
    Device::backward(up, in, chunk_transmittances, grads, R, rays);
    return grads.finish(in.background);
  }

  static CompositeForward dense_fwd(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                                    const at::Tensor& t_ends, const std::optional<at::Tensor>& background) {
    check_dense(sigmas);
    return forward({sigmas, rgbs, t_starts, t_ends, background}, sigmas.size(0),
                   composite_layout::DenseRays{sigmas.size(1)});
  }

  static CompositeBackward dense_bwd(const std::optional<at::Tensor>& grad_color,
                                     const std::optional<at::Tensor>& grad_depth,
                                     const std::optional<at::Tensor>& grad_opacity,
                                     const std::optional<at::Tensor>& grad_weights, const at::Tensor& sigmas,
                                     const at::Tensor& rgbs, const at::Tensor& t_starts, const at::Tensor& t_ends,
                                     const std::optional<at::Tensor>& background,
                                     const at::Tensor& chunk_transmittances, bool interval_grads,
                                     bool background_grad) {
    check_dense(sigmas);
    return backward({grad_color, grad_depth, grad_opacity, grad_weights}, {sigmas, rgbs, t_starts, t_ends, background},
                    chunk_transmittances, interval_grads, background_grad, sigmas.size(0),
                    composite_layout::DenseRays{sigmas.size(1)});
  }

  static CompositeForward packed_fwd(const at::Tensor& sigmas, const at::Tensor& rgbs, const at::Tensor& t_starts,
                                     const at::Tensor& t_ends, const std::optional<at::Tensor>& background,
                                     const at::Tensor& offsets) {
    const at::Tensor rows = offsets.contiguous();
    const int64_t R = check_packed(sigmas, rows, Device::kind);
    return forward({sigmas, rgbs, t_starts, t_ends, background}, R,
                   composite_layout::PackedRays{rows.const_data_ptr<int64_t>(), sigmas.size(0), R});
  }

  static CompositeBackward packed_bwd(const std::optional<at::Tensor>& grad_color,
                                      const std::optional<at::Tensor>& grad_depth,
                                      const std::optional<at::Tensor>& grad_opacity,
                                      const std::optional<at::Tensor>& grad_weights, const at::Tensor& sigmas,
                                      const at::Tensor& rgbs, const at::Tensor& t_starts, const at::Tensor& t_ends,
                                      const std::optional<at::Tensor>& background, const at::Tensor& offsets,
                                      const at::Tensor& chunk_transmittances, bool interval_grads,
                                      bool background_grad) {
    const at::Tensor rows = offsets.contiguous();
    const int64_t R = check_packed(sigmas, rows, Device::kind);
    return backward({grad_color, grad_depth, grad_opacity, grad_weights}, {sigmas, rgbs, t_starts, t_ends, background},
                    chunk_transmittances, interval_grads, background_grad, R,
                    composite_layout::PackedRays{rows.const_data_ptr<int64_t>(), sigmas.size(0), R});
  }

  static void register_ops(torch::Library& m) {
    m.impl("composite_fwd", &dense_fwd);
    m.impl("composite_bwd", &dense_bwd);
    m.impl("composite_packed_fwd", &packed_fwd);
    m.impl("composite_packed_bwd", &packed_bwd);
  }
};

}  // namespace mixer_nerf
