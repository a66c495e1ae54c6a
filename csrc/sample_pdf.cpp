// sample_pdf (dense or packed bins) and hierarchical_samples on the CPU: one sequential pass per
// ray, rays in parallel.
//
// Per ray the unnormalised CDF is built once (sample_pdf_math.h); the samples are sorted, so
// their bins are found by walking forward through it (O(B + N), no binary search), and the fine
// samples of hierarchical_samples come out sorted and are merged with the coarse depths on the
// fly (no sort). The backward is one reverse pass per ray (sample_pdf_ray_backward), in double
// for every input dtype.
#include <torch/library.h>

#include <atomic>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <optional>
#include <tuple>
#include <vector>

#include "common.h"
#include "sample_pdf.h"
#include "sample_pdf_math.h"

namespace mixer_nerf {
namespace {

using namespace sample_pdf;
using namespace sample_pdf_math;

int64_t grain_for(int64_t work_per_ray) {
  return std::max<int64_t>(1, at::internal::GRAIN_SIZE / std::max<int64_t>(1, work_per_ray));
}

// Calls emit(n, s) for the sorted samples s of one ray, in order.
template <typename acc_t, typename Weights, typename Edges, typename Emit>
void sample_ray(Weights weights, Edges edges, int num_bins, const acc_t* u, int64_t num_samples, cdf_t* cdf,
                Emit emit) {
  const cdf_t total = build_cdf(weights, num_bins, cdf);
  if (nan_pdf(total)) {
    for (int64_t n = 0; n < num_samples; ++n) emit(n, not_a_number<acc_t>());
    return;
  }
  if (no_pdf<acc_t>(total)) {
    for (int64_t n = 0; n < num_samples; ++n) emit(n, sample_uniform(u[n], num_bins, edges));
    return;
  }
  int k = 0;
  for (int64_t n = 0; n < num_samples; ++n) {
    const cdf_t v = cdf_t(u[n]) * total;
    k = walk_to_bin(cdf, num_bins, v, k);
    emit(n, sample_in_bin<acc_t>(v, k, cdf, weights, edges));
  }
}

// The sample_pdf ops' CPU kernels, for SamplePdfOps (sample_pdf.h). Each checks the values it
// reads only where it returns `invalid`: the given-positions sample_pdf ops' callers check first.
struct Cpu {
  static constexpr at::DeviceType kind = at::kCPU;

  template <typename Rows>
  static at::Tensor forward(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& u,
                            double weight_padding, const RayBatch& batch, Rows rows,
                            const std::optional<at::Tensor>& /*offsets*/) {
    return sample(bins, weights, u, weight_padding, batch, rows, nullptr);
  }

  template <typename Rows>
  static std::tuple<at::Tensor, at::Tensor, at::Tensor> forward_stratified(
      const at::Tensor& bins, const at::Tensor& weights, std::optional<at::Generator> generator,
      double weight_padding, bool keep_positions, const RayBatch& batch, Rows rows,
      const std::optional<at::Tensor>& /*offsets*/) {
    const at::Tensor u = stratified_positions(batch, generator, bins);
    std::atomic<int32_t> invalid{0};
    at::Tensor samples = sample(bins, weights, u, weight_padding, batch, rows, &invalid);
    return {samples, keep_positions ? u : at::empty({batch.rays, 0}, u.options()), invalid_flag(invalid.load(), bins)};
  }

  // sample_pdf of R rays whose bins `rows` places (DenseBins or PackedBins): samples (R, S); with
  // `invalid`, the InvalidInput bits of the bins, weights and offsets read are OR-ed into it.
  template <typename Rows>
  static at::Tensor sample(const at::Tensor& bins, const at::Tensor& weights, const at::Tensor& u,
                           double weight_padding, const RayBatch& batch, Rows rows, std::atomic<int32_t>* invalid) {
    at::Tensor samples = at::empty({batch.rays, batch.samples}, bins.options());
    const int64_t bins_per_ray = weights.numel() / std::max<int64_t>(1, batch.rays);
    MIXER_NERF_DISPATCH_FLOATING(bins.scalar_type(), "sample_pdf_fwd_cpu", [&] {
      using acc = acc_t<scalar_t>;
      const scalar_t* bins_p = bins.data_ptr<scalar_t>();
      const scalar_t* weights_p = weights.data_ptr<scalar_t>();
      const acc* u_p = u.data_ptr<acc>();
      scalar_t* out_p = samples.data_ptr<scalar_t>();
      at::parallel_for(0, batch.rays, grain_for(bins_per_ray + batch.samples), [&](int64_t begin, int64_t end) {
        std::vector<cdf_t> cdf;
        int32_t bits = 0;
        for (int64_t r = begin; r < end; ++r) {
          const RayBins ray = rows(r);
          if (invalid) {
            bits |= invalid_pdf_bits(bins_p + ray.edges, ray.num_bins + 1, weights_p + ray.weights, ray.num_bins, 0, 1);
            if (!rows.well_formed(r)) bits |= kBadOffsets;
          }
          if (cdf.size() < size_t(ray.num_bins) + 1) cdf.resize(size_t(ray.num_bins) + 1);
          scalar_t* out = out_p + r * batch.samples;
          sample_ray(PaddedWeights<acc, scalar_t>{weights_p + ray.weights, static_cast<acc>(weight_padding)},
                     GivenEdges<acc, scalar_t>{bins_p + ray.edges}, ray.num_bins, u_p + r * batch.u_row_stride,
                     batch.samples, cdf.data(), [&](int64_t n, acc s) { out[n] = static_cast<scalar_t>(s); });
        }
        if (bits) invalid->fetch_or(bits, std::memory_order_relaxed);
      });
    });
    return samples;
  }

  template <typename Rows>
  static std::tuple<at::Tensor, at::Tensor> backward(const at::Tensor& grad_samples, const at::Tensor& bins,
                                                     const at::Tensor& weights, const at::Tensor& u,
                                                     double weight_padding, const RayBatch& batch, Rows rows,
                                                     const std::optional<at::Tensor>& /*offsets*/) {
    check_grad(grad_samples, bins, batch);
    at::Tensor grad_bins = at::empty_like(bins);
    at::Tensor grad_weights = at::empty_like(weights);
    const int64_t bins_per_ray = weights.numel() / std::max<int64_t>(1, batch.rays);
    MIXER_NERF_DISPATCH_FLOATING(bins.scalar_type(), "sample_pdf_bwd_cpu", [&] {
      using acc = acc_t<scalar_t>;
      const scalar_t* grad_p = grad_samples.data_ptr<scalar_t>();
      const scalar_t* bins_p = bins.data_ptr<scalar_t>();
      const scalar_t* weights_p = weights.data_ptr<scalar_t>();
      const acc* u_p = u.data_ptr<acc>();
      scalar_t* grad_bins_p = grad_bins.data_ptr<scalar_t>();
      scalar_t* grad_weights_p = grad_weights.data_ptr<scalar_t>();
      at::parallel_for(0, batch.rays, grain_for(bins_per_ray + batch.samples), [&](int64_t begin, int64_t end) {
        std::vector<cdf_t> scratch;
        for (int64_t r = begin; r < end; ++r) {
          const RayBins ray = rows(r);
          if (scratch.size() < size_t(ray.num_bins) + 1) scratch.resize(size_t(ray.num_bins) + 1);
          sample_pdf_ray_backward(grad_p + r * batch.samples, bins_p + ray.edges, weights_p + ray.weights,
                                  u_p + r * batch.u_row_stride, ray.num_bins, static_cast<int>(batch.samples),
                                  static_cast<acc>(weight_padding), scratch.data(), grad_bins_p + ray.edges,
                                  grad_weights_p + ray.weights);
        }
      });
    });
    return {grad_bins, grad_weights};
  }

  // hierarchical_samples: the coarse depths merged with the fine samples, (R, S + N).
  static std::tuple<at::Tensor, at::Tensor> hierarchical(const at::Tensor& z_coarse, const at::Tensor& weights,
                                                         const at::Tensor& u, double weight_padding,
                                                         const RayBatch& batch) {
    const int64_t coarse = z_coarse.size(1);
    const int64_t num_bins = coarse - 2;  // edges: the S-1 midpoints; weights: weights[:, 1:-1]
    const int64_t merged = coarse + batch.samples;
    at::Tensor out = at::empty({batch.rays, merged}, z_coarse.options());
    std::atomic<int32_t> invalid{0};
    MIXER_NERF_DISPATCH_FLOATING(z_coarse.scalar_type(), "hierarchical_samples_fwd_cpu", [&] {
      using acc = acc_t<scalar_t>;
      const scalar_t* z_p = z_coarse.data_ptr<scalar_t>();
      const scalar_t* weights_p = weights.data_ptr<scalar_t>();
      const acc* u_p = u.data_ptr<acc>();
      scalar_t* out_p = out.data_ptr<scalar_t>();
      at::parallel_for(0, batch.rays, grain_for(merged), [&](int64_t begin, int64_t end) {
        std::vector<cdf_t> cdf(num_bins + 1);
        int32_t bits = 0;
        for (int64_t r = begin; r < end; ++r) {
          const scalar_t* z = z_p + r * coarse;
          bits |= invalid_pdf_bits(z, coarse, weights_p + r * coarse, coarse, 0, 1) |
                  invalid_position_bits(u_p + r * batch.u_row_stride, batch.samples, 0, 1);
          scalar_t* row = out_p + r * merged;
          // Coarse depths emitted so far; ties put the coarse depth first, and NaN samples (a ray
          // with a NaN weight) go after every coarse depth, as torch.sort puts NaN last.
          int64_t j = 0;
          sample_ray(PaddedWeights<acc, scalar_t>{weights_p + r * coarse + 1, static_cast<acc>(weight_padding)},
                     MidpointEdges<acc, scalar_t>{z}, static_cast<int>(num_bins), u_p + r * batch.u_row_stride,
                     batch.samples, cdf.data(), [&](int64_t n, acc s) {
                       while (j < coarse && (static_cast<acc>(z[j]) <= s || s != s)) row[n + j] = z[j], ++j;
                       row[n + j] = static_cast<scalar_t>(s);
                     });
          for (; j < coarse; ++j) row[batch.samples + j] = z[j];
        }
        invalid.fetch_or(bits, std::memory_order_relaxed);
      });
    });
    return {out, invalid_flag(invalid.load(), z_coarse)};
  }

  static std::tuple<at::Tensor, at::Tensor> hierarchical_stratified(const at::Tensor& z_coarse,
                                                                    const at::Tensor& weights,
                                                                    std::optional<at::Generator> generator,
                                                                    double weight_padding, const RayBatch& batch) {
    return hierarchical(z_coarse, weights, stratified_positions(batch, generator, z_coarse), weight_padding, batch);
  }

  // (n + U[0, 1)) / N, (R, N) in the accumulation dtype of `like`: the Python path's expression,
  // on the stream torch.rand draws from `generator`.
  static at::Tensor stratified_positions(const RayBatch& batch, std::optional<at::Generator> generator,
                                         const at::Tensor& like) {
    const auto acc_options = like.options().dtype(at::toOpMathType(like.scalar_type()));
    const at::Tensor jitter = at::rand({batch.rays, batch.samples}, generator, acc_options);
    return (at::arange(batch.samples, acc_options) + jitter) / static_cast<double>(batch.samples);
  }

  static at::Tensor invalid_flag(int32_t bits, const at::Tensor& like) {
    return at::full({1}, bits, like.options().dtype(at::kInt));
  }
};

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CPU, m) { SamplePdfOps<Cpu>::register_ops(m); }

}  // namespace mixer_nerf
