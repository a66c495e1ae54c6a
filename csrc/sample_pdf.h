// What the CPU and CUDA ops of sample_pdf, sample_pdf_packed and hierarchical_samples share: the
// host-side checks (Python validates first, with clear messages; these only keep a direct call
// of an op from reading out of bounds) and the entry points, which pick the layout of the bins.
#pragma once

#include <ATen/ATen.h>
#include <torch/library.h>

#include <cstdint>
#include <optional>
#include <tuple>

#include "common.h"
#include "sample_pdf_math.h"

namespace mixer_nerf {
namespace sample_pdf {

using sample_pdf_math::DenseBins;
using sample_pdf_math::PackedBins;

// Shapes of a call, after the defensive checks every op shares: rows of `edges_or_z` and
// `weights` are rays; u is (N) shared by every ray or (R, N), in the accumulation dtype.
struct RayBatch {
  int64_t rays;
  int64_t samples;
  int64_t u_row_stride;
};

constexpr int64_t kMaxCount = int64_t{1} << 30;  // bins per ray, packed bins, samples: int-sized

// Dense bins/z (R, *) and weights (R, *) of one dtype.
inline void check_dense_pdf(const at::Tensor& edges_or_z, const at::Tensor& weights, at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(edges_or_z, device);
  MIXER_NERF_CHECK_INPUT(weights, device);
  MIXER_NERF_CHECK(edges_or_z.dim() == 2 && weights.dim() == 2, "expected 2-D bins/z and weights");
  MIXER_NERF_CHECK(weights.scalar_type() == edges_or_z.scalar_type(), "weights must have the dtype of bins/z");
  MIXER_NERF_CHECK(weights.size(0) == edges_or_z.size(0), "weights and bins/z must have the same number of rays");
  MIXER_NERF_CHECK(edges_or_z.size(1) < kMaxCount, "too many bins");
}

// Packed: bins (N + R), weights (N), offsets (R + 1) int64. Returns R.
inline int64_t check_packed_pdf(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& offsets,
                                at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(bins, device);
  MIXER_NERF_CHECK_INPUT(weights, device);
  MIXER_NERF_CHECK_INPUT(offsets, device);
  MIXER_NERF_CHECK(offsets.scalar_type() == at::kLong && offsets.dim() == 1 && offsets.size(0) >= 1,
              "offsets must be (R+1) int64");
  const int64_t rays = offsets.size(0) - 1;
  MIXER_NERF_CHECK(bins.dim() == 1 && weights.dim() == 1 && bins.size(0) == weights.size(0) + rays,
              "packed bins must be (N + R) for weights (N)");
  MIXER_NERF_CHECK(weights.scalar_type() == bins.scalar_type(), "weights must have the dtype of bins");
  MIXER_NERF_CHECK(weights.size(0) < kMaxCount, "too many bins");
  return rays;
}

// Given positions u: (N) shared by every ray or (R, N), in the accumulation dtype of `like`.
inline RayBatch check_positions(const at::Tensor& u, const at::Tensor& like, int64_t rays, at::DeviceType device) {
  MIXER_NERF_CHECK_INPUT(u, device);
  MIXER_NERF_CHECK(u.scalar_type() == at::toOpMathType(like.scalar_type()),
              "u must be in the accumulation dtype of bins/z (float32, or float64 for float64)");
  MIXER_NERF_CHECK(u.dim() == 1 || (u.dim() == 2 && u.size(0) == rays), "u must be (N) or (R, N)");
  MIXER_NERF_CHECK(u.size(-1) < kMaxCount, "too many samples");
  const int64_t samples = u.size(-1);
  return {rays, samples, u.dim() == 2 ? samples : 0};
}

// Positions the op draws itself: (R, N).
inline RayBatch drawn_positions(int64_t rays, int64_t num_samples) {
  MIXER_NERF_CHECK(0 <= num_samples && num_samples < kMaxCount, "too many samples");
  return {rays, num_samples, num_samples};
}

inline RayBatch check_batch(const at::Tensor& edges_or_z, const at::Tensor& weights, const at::Tensor& u,
                            at::DeviceType device) {
  check_dense_pdf(edges_or_z, weights, device);
  return check_positions(u, edges_or_z, edges_or_z.size(0), device);
}

inline RayBatch check_packed_batch(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& offsets,
                                   const at::Tensor& u, at::DeviceType device) {
  return check_positions(u, bins, check_packed_pdf(bins, weights, offsets, device), device);
}

inline void check_bins(const at::Tensor& bins, const at::Tensor& weights) {
  MIXER_NERF_CHECK(weights.size(1) >= 1 && bins.size(1) == weights.size(1) + 1,
              "bins must be (R, B+1) for weights (R, B), B >= 1");
}

inline void check_coarse(const at::Tensor& z_coarse, const at::Tensor& weights) {
  MIXER_NERF_CHECK(z_coarse.size(1) >= 3 && weights.size(1) == z_coarse.size(1), "z_coarse and weights must be (R, S), S >= 3");
}

// What the ops that check values find wrong in the values they read, OR-ed into their `invalid`
// output (read later by mixer_nerf/ops/deferred_checks.py; mirrored in
// mixer_nerf/ops/hierarchical_samples.py and mixer_nerf/ops/sample_pdf.py).
enum InvalidInput : int32_t {
  kNegativeWeight = 1,  // a weight below 0
  kUnsortedEdges = 2,   // bins (or z_coarse) decreasing along a ray
  kPositionOutside = 4, // u outside [0, 1] (or NaN)
  kUnsortedPositions = 8,
  kBadOffsets = 16,     // packed offsets not from 0 to N, or decreasing
};

// The bits of one ray's edges (num_edges) and weights (num_weights), the entries first,
// first + stride, ... (one thread: 0, 1; a warp's lane: lane, 32).
template <typename E, typename W>
C10_HOST_DEVICE inline int32_t invalid_pdf_bits(const E* edges, int64_t num_edges, const W* weights,
                                                int64_t num_weights, int64_t first, int64_t stride) {
  int32_t bits = 0;
  for (int64_t i = first; i < num_weights; i += stride) {
    if (weights[i] < W(0)) bits |= kNegativeWeight;
  }
  for (int64_t i = first; i + 1 < num_edges; i += stride) {
    if (edges[i + 1] < edges[i]) bits |= kUnsortedEdges;
  }
  return bits;
}

// The bits of one ray's given positions u (N), strided as above.
template <typename U>
C10_HOST_DEVICE inline int32_t invalid_position_bits(const U* u, int64_t N, int64_t first, int64_t stride) {
  int32_t bits = 0;
  for (int64_t n = first; n < N; n += stride) {
    if (!(u[n] >= U(0) && u[n] <= U(1))) bits |= kPositionOutside;
    if (n + 1 < N && u[n + 1] < u[n]) bits |= kUnsortedPositions;
  }
  return bits;
}

inline void check_grad(const at::Tensor& grad_samples, const at::Tensor& bins, const RayBatch& batch) {
  MIXER_NERF_CHECK_INPUT(grad_samples, bins.device().type());
  MIXER_NERF_CHECK(grad_samples.scalar_type() == bins.scalar_type(), "grad_samples must have the dtype of bins");
  MIXER_NERF_CHECK(grad_samples.dim() == 2 && grad_samples.size(0) == batch.rays && grad_samples.size(1) == batch.samples,
              "grad_samples must be (R, N)");
}

// The ops of one device: the checks both devices share and the layout of the bins, then
// Device::forward / Device::backward (templates over DenseBins and PackedBins; `offsets` is the
// packed layout's, absent for dense bins), Device::forward_stratified and Device::hierarchical,
// which the device's source registers with register_ops.
//
// The *_stratified ops draw their own positions u_n = (n + xi_n) / N, xi ~ U[0, 1), from
// `generator`: on the CPU the stream torch.rand draws (the Python path's, bit for bit), on CUDA
// Philox in the kernel (one launch, graph-safe). Besides their samples they return the positions
// drawn, (R, N) in the accumulation dtype (sample_pdf's backward ops take them; with
// keep_positions false, (R, 0): a caller without gradients has no use for them, and not writing
// them spares the kernel as many bytes as the samples), and, like hierarchical_samples_fwd,
// invalid (1) int32: the InvalidInput bits of the values read.
template <typename Device>
struct SamplePdfOps {
  static DenseBins dense_rows(const at::Tensor& weights) { return {static_cast<int>(weights.size(1))}; }
  static PackedBins packed_rows(const at::Tensor& weights, const at::Tensor& offsets) {
    return {offsets.const_data_ptr<int64_t>(), weights.size(0), offsets.size(0) - 1};
  }

  static at::Tensor dense_fwd(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& u,
                              double weight_padding) {
    const RayBatch batch = check_batch(bins, weights, u, Device::kind);
    check_bins(bins, weights);
    return Device::forward(bins, weights, u, weight_padding, batch, dense_rows(weights), std::nullopt);
  }

  static std::tuple<at::Tensor, at::Tensor, at::Tensor> dense_stratified_fwd(
      const at::Tensor& bins, const at::Tensor& weights, int64_t num_samples, std::optional<at::Generator> generator,
      double weight_padding, bool keep_positions) {
    check_dense_pdf(bins, weights, Device::kind);
    check_bins(bins, weights);
    return Device::forward_stratified(bins, weights, generator, weight_padding, keep_positions,
                                      drawn_positions(bins.size(0), num_samples), dense_rows(weights), std::nullopt);
  }

  static std::tuple<at::Tensor, at::Tensor> dense_bwd(const at::Tensor& grad_samples, const at::Tensor& bins,
                                                      const at::Tensor& weights, const at::Tensor& u,
                                                      double weight_padding) {
    const RayBatch batch = check_batch(bins, weights, u, Device::kind);
    check_bins(bins, weights);
    return Device::backward(grad_samples, bins, weights, u, weight_padding, batch, dense_rows(weights), std::nullopt);
  }

  static at::Tensor packed_fwd(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& offsets,
                               const at::Tensor& u, double weight_padding) {
    const RayBatch batch = check_packed_batch(bins, weights, offsets, u, Device::kind);
    return Device::forward(bins, weights, u, weight_padding, batch, packed_rows(weights, offsets), offsets);
  }

  static std::tuple<at::Tensor, at::Tensor, at::Tensor> packed_stratified_fwd(
      const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& offsets, int64_t num_samples,
      std::optional<at::Generator> generator, double weight_padding, bool keep_positions) {
    const int64_t rays = check_packed_pdf(bins, weights, offsets, Device::kind);
    return Device::forward_stratified(bins, weights, generator, weight_padding, keep_positions,
                                      drawn_positions(rays, num_samples), packed_rows(weights, offsets), offsets);
  }

  static std::tuple<at::Tensor, at::Tensor> packed_bwd(const at::Tensor& grad_samples, const at::Tensor& bins,
                                                       const at::Tensor& weights, const at::Tensor& offsets,
                                                       const at::Tensor& u, double weight_padding) {
    const RayBatch batch = check_packed_batch(bins, weights, offsets, u, Device::kind);
    return Device::backward(grad_samples, bins, weights, u, weight_padding, batch, packed_rows(weights, offsets),
                            offsets);
  }

  // -> merged depths (R, S + N) and invalid (1) int32 (InvalidInput bits).
  static std::tuple<at::Tensor, at::Tensor> hierarchical_fwd(const at::Tensor& z_coarse, const at::Tensor& weights,
                                                             const at::Tensor& u, double weight_padding) {
    const RayBatch batch = check_batch(z_coarse, weights, u, Device::kind);
    check_coarse(z_coarse, weights);
    return Device::hierarchical(z_coarse, weights, u, weight_padding, batch);
  }

  static std::tuple<at::Tensor, at::Tensor> hierarchical_stratified_fwd(const at::Tensor& z_coarse,
                                                                        const at::Tensor& weights, int64_t num_samples,
                                                                        std::optional<at::Generator> generator,
                                                                        double weight_padding) {
    check_dense_pdf(z_coarse, weights, Device::kind);
    check_coarse(z_coarse, weights);
    return Device::hierarchical_stratified(z_coarse, weights, generator, weight_padding,
                                           drawn_positions(z_coarse.size(0), num_samples));
  }

  static void register_ops(torch::Library& m) {
    m.impl("hierarchical_samples_stratified_fwd", &hierarchical_stratified_fwd);
    m.impl("sample_pdf_fwd", &dense_fwd);
    m.impl("sample_pdf_stratified_fwd", &dense_stratified_fwd);
    m.impl("sample_pdf_bwd", &dense_bwd);
    m.impl("hierarchical_samples_fwd", &hierarchical_fwd);
    m.impl("sample_pdf_packed_fwd", &packed_fwd);
    m.impl("sample_pdf_packed_stratified_fwd", &packed_stratified_fwd);
    m.impl("sample_pdf_packed_bwd", &packed_bwd);
  }
};

}  // namespace sample_pdf
}  // namespace mixer_nerf
