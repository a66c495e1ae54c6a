// Per-ray inverse-CDF sampling math shared by the CPU and CUDA kernels of sample_pdf and
// hierarchical_samples (sample_pdf.cpp, cuda/sample_pdf.cu). The formulation, and the gradient
// convention at clamps, is the one of mixer_nerf/ops/sample_pdf_reference.py:
//
//   w_k = weights_k + pad, flushed to 0 below the smallest normal number (so 1 / w_k is finite
//   and "empty" has one meaning; NaN stays NaN),  C_k = w_0 + ... + w_{k-1} (summed
//   sequentially, so C is non-decreasing and exactly flat over zero-weight bins),  W = C_B,
//   v = u W,  k = #{j in 1..B-1 : C_j < v},  t = clamp((v - C_k) / w_k, 0, 1) (0 if w_k == 0),
//   s = min(e_k + t (e_{k+1} - e_k), e_{k+1});  rays with W == 0 (or beyond the accumulation
//   type's range) sample s = min(e_0 + u (e_B - e_0), e_B) instead, and rays with a NaN weight
//   (so W is NaN) sample NaN, with NaN gradients for all their weights and edges.
// Both clamps only undo rounding, so gradients pass straight through them.
#pragma once

#include <ATen/ATen.h>
#include <c10/macros/Macros.h>

#include <cfloat>
#include <cmath>  // NAN

#include "common.h"
#include "ray_layout.h"

namespace mixer_nerf {
namespace sample_pdf_math {

// Where a ray's bins lie: its weights from `weights`, its num_bins + 1 edges from `edges` (element
// offsets into the weights and edges arrays).
struct RayBins {
  int64_t weights;
  int64_t edges;
  int num_bins;
};

// Dense: weights (R, B), edges (R, B+1).
struct DenseBins {
  int num_bins;
  C10_HOST_DEVICE RayBins operator()(int64_t ray) const {
    return {ray * num_bins, ray * (num_bins + 1), num_bins};
  }
  C10_HOST_DEVICE bool well_formed(int64_t /*ray*/) const { return true; }
};

// Packed: ray r has B_r = offsets[r+1] - offsets[r] >= 0 bins, weights offsets[r] .. offsets[r+1]-1
// of (N), edges offsets[r] + r .. offsets[r+1] + r of (N + R): the packed rows of ray_layout.h,
// clamped the same way. N < 2^30 (checked), so B_r fits an int.
struct PackedBins {
  const int64_t* offsets;  // (R + 1)
  int64_t total;           // N
  int64_t num_rays;        // R
  C10_HOST_DEVICE RayBins operator()(int64_t ray) const {
    const composite_layout::RaySpan weights = composite_layout::PackedRays{offsets, total, num_rays}(ray);
    return {weights.offset, weights.offset + ray, static_cast<int>(weights.count)};
  }
  // Whether ray `ray`'s offsets are ones validation accepts (the value checks report the rest).
  C10_HOST_DEVICE bool well_formed(int64_t ray) const {
    return composite_layout::PackedRays{offsets, total, num_rays}.well_formed(ray, num_rays);
  }
};

// The CDF, v = u W and the position t inside a bin are carried in double for every input dtype:
// t = (v - C_k) / w_k subtracts two numbers close to W, which in float32 would cost
// ~log2(W / w_k) bits of t. In double the float32 samples keep nearly full accuracy, and the
// sum stays sequential (non-decreasing and exactly flat over zero-weight bins) and cheap.
using cdf_t = double;

C10_HOST_DEVICE inline float smallest_normal(float) { return FLT_MIN; }
C10_HOST_DEVICE inline double smallest_normal(double) { return DBL_MIN; }
C10_HOST_DEVICE inline float largest_finite(float) { return FLT_MAX; }
C10_HOST_DEVICE inline double largest_finite(double) { return DBL_MAX; }

// A ray with a NaN weight: flush_weight keeps the NaN and the sum carries it into the total.
// Its samples are NaN and so are the gradients of all its weights and edges; other rays are
// untouched.
C10_HOST_DEVICE inline bool nan_pdf(cdf_t total) { return total != total; }

// The samples of such a ray (and its gradients).
template <typename acc_t>
C10_HOST_DEVICE inline acc_t not_a_number() {
  return static_cast<acc_t>(NAN);
}

// A ray whose total weight is zero (after flushing subnormal weights) or exceeds the
// accumulation type's range has no usable PDF: it samples uniformly between its first and last
// edge. A NaN total is not one of them (see nan_pdf).
template <typename acc_t>
C10_HOST_DEVICE inline bool no_pdf(cdf_t total) {
  return total < cdf_t(smallest_normal(acc_t{})) || total > cdf_t(largest_finite(acc_t{}));
}

// Padded weights of one ray as the accumulation type, read from any element type; subnormal
// (and, unchecked, negative) weights count as 0 and get no gradient. NaN stays NaN (nan_pdf).
template <typename acc_t>
C10_HOST_DEVICE inline acc_t flush_weight(acc_t w) {
  return w < smallest_normal(acc_t{}) ? acc_t(0) : w;
}

template <typename acc_t, typename T>
struct PaddedWeights {
  const T* w;
  acc_t pad;
  C10_HOST_DEVICE acc_t operator()(int k) const { return flush_weight(static_cast<acc_t>(w[k]) + pad); }
};

// Bin edges of one ray: given directly ...
template <typename acc_t, typename T>
struct GivenEdges {
  const T* e;
  C10_HOST_DEVICE acc_t operator()(int k) const { return static_cast<acc_t>(e[k]); }
};

// ... or, as in NeRF's fine pass, the midpoints of the coarse depths.
template <typename acc_t, typename T>
struct MidpointEdges {
  const T* z;
  C10_HOST_DEVICE acc_t operator()(int k) const {
    return acc_t(0.5) * (static_cast<acc_t>(z[k]) + static_cast<acc_t>(z[k + 1]));
  }
};

// The CDF is summed in groups of cdf_group_bins(B) consecutive bins: within a group a running sum
// of its weights, the group's start the previous group's start plus that group's sum. That order
// keeps the CDF exactly flat over zero-weight bins and monotone (start + partial, rounded, grows
// with partial; a group ends at the next group's start), as a plain running sum does, and lets a
// warp build it with a chain of ~sqrt(B) adds (one lane per group) where a running sum takes B;
// the CPU and CUDA kernels sum in this same order, so their CDFs agree bit for bit.
C10_HOST_DEVICE inline int cdf_group_bins(int num_bins) {
  int bins = 1;
  while (bins * bins < num_bins) ++bins;  // ceil(sqrt(B)), at most 32 groups
  return bins > (num_bins + 31) / 32 ? bins : (num_bins + 31) / 32;
}

// cdf[0..B] = the unnormalised CDF; returns the total weight W = cdf[B].
template <typename Weights>
C10_HOST_DEVICE inline cdf_t build_cdf(Weights weights, int num_bins, cdf_t* cdf) {
  const int group = cdf_group_bins(num_bins);
  cdf_t start = 0;
  cdf[0] = start;
  for (int first = 0; first < num_bins; first += group) {
    const int end = first + group < num_bins ? first + group : num_bins;
    cdf_t partial = 0;
    for (int k = first; k < end; ++k) {
      partial += weights(k);
      cdf[k + 1] = start + partial;
    }
    start = cdf[end];
  }
  return start;
}

// The bin k holding v: #{j in 1..B-1 : cdf[j] < v}, by binary search.
C10_HOST_DEVICE inline int find_bin(const cdf_t* cdf, int num_bins, cdf_t v) {
  int lo = 1, hi = num_bins;  // answer + 1 lies in [lo, hi]
  while (lo < hi) {
    const int mid = (lo + hi) / 2;
    if (cdf[mid] < v) lo = mid + 1;
    else hi = mid;
  }
  return lo - 1;
}

// The same bin found by walking forward from `k`, the bin of a smaller v (sorted u).
C10_HOST_DEVICE inline int walk_to_bin(const cdf_t* cdf, int num_bins, cdf_t v, int k) {
  while (k < num_bins - 1 && cdf[k + 1] < v) ++k;
  return k;
}

// Where v falls inside bin k. `t` is clamped to [0, 1]; the clamp only undoes rounding (the
// search puts v in (C_k, C_k + w_k]), so gradients take `t_raw` unclamped (straight through).
// `weighted` is false only for w_k == 0, reached by v == 0 before the first weight: t = 0 and the
// weights get no gradient from this sample.
template <typename acc_t>
struct Fraction {
  acc_t t;
  acc_t t_raw;
  bool weighted;
};

template <typename acc_t>
C10_HOST_DEVICE inline Fraction<acc_t> fraction_in_bin(cdf_t v, cdf_t cdf_k, acc_t w_k) {
  if (!(w_k > 0)) return {acc_t(0), acc_t(0), false};
  const cdf_t t = (v - cdf_k) / w_k;
  return {static_cast<acc_t>(t < 0 ? 0 : (t > 1 ? 1 : t)), static_cast<acc_t>(t), true};
}

// lo + t (hi - lo) for t in [0, 1], capped at hi, which rounding can pass (the cap is, again,
// transparent to gradients). Keeps samples in their bin, hence sorted.
template <typename acc_t>
C10_HOST_DEVICE inline acc_t lerp_in_bin(acc_t lo, acc_t hi, acc_t t) {
  const acc_t s = lo + t * (hi - lo);
  return s > hi ? hi : s;
}

// One sample of a ray with a PDF, given its bin.
template <typename acc_t, typename Weights, typename Edges>
C10_HOST_DEVICE inline acc_t sample_in_bin(cdf_t v, int k, const cdf_t* cdf, Weights weights, Edges edges) {
  return lerp_in_bin(edges(k), edges(k + 1), fraction_in_bin(v, cdf[k], weights(k)).t);
}

// One sample of a ray without a PDF.
template <typename acc_t, typename Edges>
C10_HOST_DEVICE inline acc_t sample_uniform(acc_t u, int num_bins, Edges edges) {
  return lerp_in_bin(edges(0), edges(num_bins), u);
}

// Gradients of one ray's samples (B >= 0) with respect to its edges and weights, O(B + N), in one
// reverse pass over the sorted samples. ds/de_k = 1 - t, ds/de_{k+1} = t; with
// a_n = dL/ds_n (e_{k+1} - e_k) / w_{k_n} for weighted samples,
// dt_n/dw_i = (u_n - [i < k_n] - [i == k_n] t_n) / w_{k_n}, so
//   dL/dw_i = sum_n a_n u_n - sum_{n: k_n > i} a_n - sum_{n: k_n == i} a_n t_n.
// Walking the samples from the last one down, the middle sum is a running suffix. Every element
// of grad_bins (B+1) and grad_weights (B) is written exactly once; cdf (B+1) is scratch that
// also holds the partial weight gradients until the last step.
//
// The terms a_n, t_n and every running sum are doubles for every input dtype (grad_t), and each
// gradient is rounded once. dL/dw_i is a difference of sums of up to N terms that largely cancel.
// With float32 sums (N roundings each) float32 weight gradients were ~2 ulps off in the median,
// twice the reference path's error, and up to 0.37 relative where the cancellation is deep;
// the three float32 roundings of a_n alone would still leave ~1e-4 there. In double, float32
// gradients of weights and edges are the float64 ones rounded once (benchmarks/error_budget.py:
// within half an ulp on typical PDFs), at no measurable cost. Only the CPU kernel calls this function;
// the CUDA backward (cuda/sample_pdf.cu) computes the same sums with warp scans, in the same grad_t.
using grad_t = cdf_t;

template <typename acc_t, typename scalar_t>
C10_HOST_DEVICE inline void sample_pdf_ray_backward(
    const scalar_t* grad, const scalar_t* bins, const scalar_t* weights, const acc_t* u, int num_bins,
    int num_samples, acc_t pad, cdf_t* cdf, scalar_t* grad_bins, scalar_t* grad_weights) {
  const PaddedWeights<acc_t, scalar_t> padded{weights, pad};
  const GivenEdges<acc_t, scalar_t> edges{bins};
  const cdf_t total = build_cdf(padded, num_bins, cdf);

  if (nan_pdf(total)) {
    for (int k = 0; k < num_bins; ++k) grad_weights[k] = static_cast<scalar_t>(not_a_number<acc_t>());
    for (int k = 0; k <= num_bins; ++k) grad_bins[k] = static_cast<scalar_t>(not_a_number<acc_t>());
    return;
  }
  if (no_pdf<acc_t>(total)) {
    grad_t first = 0, last = 0;
    for (int n = 0; n < num_samples; ++n) {
      const grad_t g = static_cast<grad_t>(grad[n]);
      first += g - g * u[n];
      last += g * u[n];
    }
    for (int k = 0; k < num_bins; ++k) grad_weights[k] = scalar_t(0);
    for (int k = 1; k < num_bins; ++k) grad_bins[k] = scalar_t(0);
    // A ray without bins (packed) has one edge, both ends of its degenerate range.
    grad_bins[0] = static_cast<scalar_t>(num_bins > 0 ? first : first + last);
    if (num_bins > 0) grad_bins[num_bins] = static_cast<scalar_t>(last);
    return;
  }

  grad_t sum_a_u = 0;   // sum_n a_n u_n, common to every weight
  grad_t suffix_a = 0;  // sum of a_n over the bins above the current one
  grad_t bin_a = 0, bin_a_t = 0;  // the current bin's sum of a_n and of a_n t_n
  grad_t bin_lo = 0, bin_hi = 0;  // gradient reaching the current bin's lower / upper edge
  grad_t above_lo = 0;            // gradient reaching edge k+1 as the lower edge of bin k+1
  int k = num_bins - 1;
  auto close_bin = [&]() {
    grad_bins[k + 1] = static_cast<scalar_t>(above_lo + bin_hi);
    above_lo = bin_lo;
    cdf[k] = -(suffix_a + bin_a_t);  // C_k is no longer needed
    suffix_a += bin_a;
    bin_a = bin_a_t = bin_lo = bin_hi = 0;
  };
  for (int n = num_samples - 1; n >= 0; --n) {
    const cdf_t v = cdf_t(u[n]) * total;
    while (k > 0 && !(cdf[k] < v)) {
      close_bin();
      --k;
    }
    const grad_t g = static_cast<grad_t>(grad[n]);
    const grad_t w_k = padded(k);
    const Fraction<grad_t> f = fraction_in_bin(v, cdf[k], w_k);
    bin_lo += g - g * f.t;
    bin_hi += g * f.t;
    if (f.weighted) {
      const grad_t a = g * (grad_t(edges(k + 1)) - grad_t(edges(k))) / w_k;
      sum_a_u += a * u[n];
      bin_a += a;
      bin_a_t += a * f.t_raw;
    }
  }
  for (; k >= 0; --k) close_bin();
  grad_bins[0] = static_cast<scalar_t>(above_lo);
  for (int i = 0; i < num_bins; ++i) {
    grad_weights[i] = padded(i) > 0 ? static_cast<scalar_t>(cdf[i] + sum_a_u) : scalar_t(0);
  }
}

}  // namespace sample_pdf_math
}  // namespace mixer_nerf
