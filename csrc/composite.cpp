// composite and composite_packed (volume rendering) on the CPU: one sequential scan per ray, rays
// in parallel. A ray is a span of samples (ray_layout.h), so both layouts run the same scans.
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
//
// Both scans compute in double for every input dtype (ray_acc); only the outputs and gradients
// they write are rounded, once. Float64 inputs are unchanged by this (their accumulation type
// was double already).
//
// Forward: tau, E, T, alpha, w and the color and depth sums are doubles. A float32 sequential
// E drifted by up to ~i float32 ulps after i samples, and T = exp(-E) turned that into a relative
// error of ~E times it; with tau, alpha and the weighted sums also rounded to float32 at every
// step, float32 weights were off by up to ~1e2 ulps (5.7e-6 relative, typical rays) and colors,
// depths and opacities by a few ulps, 2-4 times the reference path's error (whose torch.cumsum
// accumulates float32 in double). In double, float32/half/bfloat16 outputs are the float64 ones
// rounded once (benchmarks/error_budget.py: within half an ulp on every distribution). The double
// exp and expm1 are ATen's vectorised ones, over groups of samples (below).
//
// Backward: G starts at g_S = O(1) and is multiplied S times by exp(-tau_j); in thin media
// (tau ~ 1e-9..1e-4) that rounds to ~1 in float32, so a float32 G held ~S float32 ulps of g_S,
// and g_j - G_{j+1} kept that absolute error where it is small (float32 gradients off by ~1e-2
// relative, ten times the reference path's error). In double the error is ~S * 2^-53 of max |g|,
// far below float32's resolution: float32/half/bfloat16 gradients are the float64 ones rounded
// once (within half an ulp on every distribution of the error budget). Float64 inputs keep ~S
// float64 ulps of G. exp(-tau_j) comes from the expm1 that alpha needs, as 1 + expm1(-tau_j)
// where that is >= 1/2 (within an ulp; no second transcendental on thin samples), else from exp
// (the sum would keep only an absolute ulp of a tiny exp(-tau); tau = 1e18 still gives exactly
// 0). The CUDA kernel (csrc/cuda/composite.cu) computes both passes in double too, with its own
// exp/expm1 polynomial for non-double inputs (csrc/cuda/neg_exp.cuh).
#include <torch/library.h>

#include <ATen/ATen.h>
#include <ATen/CPUFunctions.h>
#include <ATen/Parallel.h>

#include <atomic>
#include <cmath>
#include <optional>
#include <tuple>
#include <vector>

#include "common.h"
#include "composite.h"

namespace mixer_nerf {
namespace {

// Both scans compute in double for every input dtype (see the file comment).
using ray_acc = double;

template <typename scalar_t, typename acc = ray_acc>
struct Sample {
  acc sigma, t_start, t_end, tau;
  Sample(const CompositeInputs<scalar_t>& in, int64_t i)
      : sigma(in.sigmas[i]), t_start(in.t_starts[i]), t_end(in.t_ends[i]), tau(sigma * (t_end - t_start)) {}
  acc midpoint() const { return acc(0.5) * (t_start + t_end); }
};

// Rays are scanned in groups of about kGroupSamples samples through per-thread buffers of doubles:
// a first pass writes each sample's -tau and -E, ATen's vectorised CPU exp and expm1 (those of
// torch.exp and torch.expm1) turn a whole group into T and alpha in one call each, and a last pass
// per ray uses them. Scalar libm exp/expm1, one sample at a time, were most of a scan's time.
constexpr int64_t kGroupSamples = 8192;

struct GroupBuffers {
  std::vector<ray_acc> a, b, c;
  void fit(int64_t n) {
    if (static_cast<int64_t>(a.size()) < n) a.resize(n), b.resize(n), c.resize(n);
  }
};

// The first n entries of a buffer as a tensor, for ATen's CPU kernels (in place: out is self).
void exp_in_place(std::vector<ray_acc>& v, int64_t n) {
  if (n == 0) return;
  at::Tensor t = at::from_blob(v.data(), {n}, at::TensorOptions().dtype(at::kDouble));
  at::cpu::exp_out(t, t);
}
void expm1_in_place(std::vector<ray_acc>& v, int64_t n) {
  if (n == 0) return;
  at::Tensor t = at::from_blob(v.data(), {n}, at::TensorOptions().dtype(at::kDouble));
  at::cpu::expm1_out(t, t);
}

// Calls scan(first, last, rows) on consecutive groups of rays [first, last) of [begin, end) that
// need at most kGroupSamples buffer rows, `extra` per ray beyond its samples (a longer ray alone).
template <typename Rays, typename Scan>
void for_each_group(Rays rays, int64_t begin, int64_t end, int64_t extra, Scan scan) {
  for (int64_t first = begin; first < end;) {
    int64_t last = first, rows = 0;
    for (; last < end; ++last) {
      const int64_t n = rays(last).count + extra;
      if (last > first && rows + n > kGroupSamples) break;
      rows += n;
    }
    scan(first, last, rows);
    first = last;
  }
}

// Forward of rays [first, last): buffer a holds -E_i then T_i, buffer b -tau_i then expm1(-tau_i),
// each ray's samples followed by one row of its total -E_S (giving 1 - opacity and -opacity).
// Returns the InvalidInput bits of the values read.
template <typename scalar_t, typename Rays>
int32_t composite_forward_group(const CompositeInputs<scalar_t>& in, Rays rays, int64_t R, int64_t first,
                                int64_t last, int64_t rows, GroupBuffers& buf, ray_acc* color_acc,
                                const CompositeOutputs<scalar_t>& out) {
  using acc = ray_acc;
  const int64_t C = in.channels;
  buf.fit(rows);
  int32_t invalid = 0;
  int64_t p = 0;
  for (int64_t r = first; r < last; ++r) {
    const composite_layout::RaySpan span = rays(r);
    if (!rays.well_formed(r, R)) invalid |= kBadOffsets;
    acc optical_depth = 0;
    for (int64_t i = span.offset; i < span.offset + span.count; ++i, ++p) {
      const Sample<scalar_t> s(in, i);
      invalid |= invalid_sample_bits(s.sigma, s.t_start, s.t_end);
      buf.a[p] = -optical_depth;
      buf.b[p] = -s.tau;
      optical_depth += s.tau;
    }
    buf.a[p] = buf.b[p] = -optical_depth;
    ++p;
  }
  exp_in_place(buf.a, rows);
  expm1_in_place(buf.b, rows);
  p = 0;
  for (int64_t r = first; r < last; ++r) {
    const composite_layout::RaySpan span = rays(r);
    std::fill(color_acc, color_acc + C, acc(0));
    acc depth_acc = 0;
    for (int64_t i = span.offset; i < span.offset + span.count; ++i, ++p) {
      const acc w = buf.a[p] * -buf.b[p];
      out.weights[i] = static_cast<scalar_t>(w);
      depth_acc += w * Sample<scalar_t>(in, i).midpoint();
      const scalar_t* rgb = in.rgbs + i * C;
      for (int64_t c = 0; c < C; ++c) color_acc[c] += w * acc(rgb[c]);
    }
    const acc transmittance = buf.a[p], opacity = -buf.b[p];
    ++p;
    const scalar_t* bg = in.background ? in.background + r * in.background_stride : nullptr;
    for (int64_t c = 0; c < C; ++c) {
      out.color[r * C + c] = static_cast<scalar_t>(color_acc[c] + (bg ? transmittance * acc(bg[c]) : acc(0)));
    }
    out.depth[r] = static_cast<scalar_t>(depth_acc);
    out.opacity[r] = static_cast<scalar_t>(opacity);
  }
  return invalid;
}

// Backward of rays [first, last): buffer a holds T_{i+1} (a reverse pass cannot rebuild it
// without subtracting sums), b expm1(-tau_i) and c exp(-tau_i); then one reverse pass per ray
// carries G, all in double (see the file comment).
template <typename scalar_t, typename Rays>
void composite_backward_group(const CompositeInputs<scalar_t>& in, const CompositeGrads<scalar_t>& g, Rays rays,
                              int64_t first, int64_t last, int64_t rows, GroupBuffers& buf) {
  using acc = ray_acc;
  const int64_t C = in.channels;
  buf.fit(rows);
  int64_t p = 0;
  for (int64_t r = first; r < last; ++r) {
    const composite_layout::RaySpan span = rays(r);
    acc optical_depth = 0;
    for (int64_t i = span.offset; i < span.offset + span.count; ++i, ++p) {
      const acc tau = Sample<scalar_t>(in, i).tau;
      optical_depth += tau;
      buf.a[p] = -optical_depth;
      buf.b[p] = buf.c[p] = -tau;
    }
  }
  exp_in_place(buf.a, rows);
  expm1_in_place(buf.b, rows);
  exp_in_place(buf.c, rows);
  p = 0;
  for (int64_t r = first; r < last; ++r) {
    const composite_layout::RaySpan span = rays(r);
    const acc* transmittance_after = buf.a.data() + p;
    const acc transmittance_end = span.count > 0 ? transmittance_after[span.count - 1] : acc(1);
    const scalar_t* grad_color = g.color ? g.color + r * C : nullptr;
    const acc grad_depth = g.depth ? acc(g.depth[r]) : acc(0);

    acc G = g.opacity ? -acc(g.opacity[r]) : acc(0);
    if (in.background && grad_color) {
      const scalar_t* bg = in.background + r * in.background_stride;
      for (int64_t c = 0; c < C; ++c) G += acc(grad_color[c]) * acc(bg[c]);
    }
    if (g.background_rows) {
      for (int64_t c = 0; c < C; ++c) {
        g.background_rows[r * C + c] =
            static_cast<acc_t<scalar_t>>(grad_color ? acc(grad_color[c]) * transmittance_end : acc(0));
      }
    }
    for (int64_t k = span.count - 1; k >= 0; --k) {
      const int64_t i = span.offset + k;
      const Sample<scalar_t> s(in, i);
      const acc decay_m1 = buf.b[p + k];  // exp(-tau) - 1
      const acc alpha = -decay_m1;
      // exp(-tau) as 1 + expm1(-tau) where that is exact to an ulp, else exp's own value
      const acc decay = decay_m1 >= acc(-0.5) ? acc(1) + decay_m1 : buf.c[p + k];
      const acc w = (k > 0 ? transmittance_after[k - 1] : acc(1)) * alpha;
      const scalar_t* rgb = in.rgbs + i * C;
      acc g_i = grad_depth * s.midpoint() + (g.weights ? acc(g.weights[i]) : acc(0));
      for (int64_t c = 0; c < C; ++c) {
        const acc gc = grad_color ? acc(grad_color[c]) : acc(0);
        g_i += gc * acc(rgb[c]);
        g.rgbs[i * C + c] = static_cast<scalar_t>(gc * w);
      }
      const acc grad_tau = transmittance_after[k] * (g_i - G);
      G = alpha * g_i + decay * G;
      g.sigmas[i] = static_cast<scalar_t>(grad_tau * (s.t_end - s.t_start));
      if (g.t_starts) {
        const acc from_depth = acc(0.5) * grad_depth * w;
        g.t_starts[i] = static_cast<scalar_t>(from_depth - grad_tau * s.sigma);
        g.t_ends[i] = static_cast<scalar_t>(from_depth + grad_tau * s.sigma);
      }
    }
    p += span.count;
  }
}

int64_t ray_grain(int64_t samples, int64_t rays) {
  return std::max<int64_t>(1, 4096 * std::max<int64_t>(1, rays) / std::max<int64_t>(1, samples));
}

// The composite ops' CPU kernels, for CompositeOps (composite.h).
struct Cpu {
  static constexpr at::DeviceType kind = at::kCPU;
  // The CPU backward finds a ray's transmittances itself (one thread walks the whole ray).
  static int64_t chunk_transmittance_entries(int64_t, int64_t) { return 0; }

  template <typename Rays>
  static CompositeForward forward(const CompositeTensors& tensors, int64_t R, Rays rays) {
    auto outputs = empty_outputs(tensors.sigmas, tensors.rgbs, R, 0);
    const int64_t C = tensors.rgbs.size(-1);
    std::atomic<int32_t> invalid{0};
    MIXER_NERF_DISPATCH_FLOATING(tensors.sigmas.scalar_type(), "composite_fwd_cpu", [&] {
      const auto in = tensors.pointers<scalar_t>();
      const auto out = outputs_of<scalar_t>(outputs);
      at::parallel_for(0, R, ray_grain(tensors.sigmas.numel(), R), [&](int64_t begin, int64_t end) {
        std::vector<ray_acc> color_acc(C);
        GroupBuffers buf;
        int32_t bits = 0;
        for_each_group(rays, begin, end, 1, [&](int64_t first, int64_t last, int64_t rows) {
          bits |= composite_forward_group(in, rays, R, first, last, rows, buf, color_acc.data(), out);
        });
        invalid.fetch_or(bits, std::memory_order_relaxed);
      });
    });
    std::get<5>(outputs).fill_(invalid.load());
    return outputs;
  }

  template <typename Rays>
  static void backward(const Upstream& up, const CompositeTensors& tensors, const at::Tensor& /*chunk_transmittances*/,
                       CompositeGradTensors& grads, int64_t R, Rays rays) {
    MIXER_NERF_DISPATCH_FLOATING(tensors.sigmas.scalar_type(), "composite_bwd_cpu", [&] {
      const auto in = tensors.pointers<scalar_t>();
      const auto g = grads.pointers<scalar_t>(up);
      at::parallel_for(0, R, ray_grain(tensors.sigmas.numel(), R), [&](int64_t begin, int64_t end) {
        GroupBuffers buf;
        for_each_group(rays, begin, end, 0, [&](int64_t first, int64_t last, int64_t rows) {
          composite_backward_group(in, g, rays, first, last, rows, buf);
        });
      });
    });
  }
};

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CPU, m) { CompositeOps<Cpu>::register_ops(m); }

}  // namespace mixer_nerf
