// exp(-x) and -expm1(-x) together, in double, without libm: one range reduction and one
// polynomial give both (the composite kernels need exp(-tau) and alpha = -expm1(-tau) of every
// sample). Branch-free: no special-case path, two integer operations.
//
// Method: y = -x = k ln2 + r with k = rint(y / ln2) and |r| <= ln2/2 (Cody-Waite: ln2's high
// part has trailing zeros, so k * ln2_hi is exact for |k| < 2^11), p = expm1(r) = r + r^2 q(r),
// q a degree-8 Chebyshev fit of (expm1(r) - r) / r^2 on [-ln2/2, ln2/2] whose relative error in
// p is below 2^-48 (mpmath). Then exp(y) = 2^k (1 + p) and -expm1(y) = (1 - 2^k) - 2^k p, each one
// fma: 1 - 2^k is exact for k >= -53 (and rounds to 1 below, where expm1 is -1 in double), so
// alpha keeps p's relative accuracy at k = 0 (thin samples: r = y exactly) and has no
// cancellation elsewhere (|result| >= 0.29 for k != 0). Both are within ~2^-47 relative of the
// truth, against ~2^-53 for libm: far below the 2^-24 of the float32 (or coarser) results they
// feed, which is why only the kernels of non-double inputs use them.
//
// Range: y is clamped to [-708, 708], where 2^k is a normal double; exp(y) is 0 below -708
// (exp(-708) ~ 3e-308: no float32 output can hold a product of it with finite float32 values)
// and alpha is 1 there. Above 708 (negative densities only, which the kernels report as
// invalid input) both stay at their value at 708. NaN propagates.
#pragma once

#include <c10/macros/Macros.h>

#include <cstdint>
#include <cstring>

namespace mixer_nerf {

struct NegExp {
  double exp;    // exp(-x)
  double alpha;  // 1 - exp(-x) = -expm1(-x), +0 at x = 0
};

C10_HOST_DEVICE inline int64_t bits_of(double value) {
#ifdef __CUDA_ARCH__
  return __double_as_longlong(value);
#else
  int64_t bits;
  std::memcpy(&bits, &value, sizeof bits);
  return bits;
#endif
}

C10_HOST_DEVICE inline double double_of(int64_t bits) {
#ifdef __CUDA_ARCH__
  return __longlong_as_double(bits);
#else
  double value;
  std::memcpy(&value, &bits, sizeof value);
  return value;
#endif
}

// q's coefficients, highest degree first. In __constant__ memory on the device, so that each DFMA
// reads its coefficient as a constant-bank operand: a double literal costs two uniform moves
// (its 64 bits are no immediate), 16 of the backward's ~350 instructions per sample.
constexpr int kExpm1PolyTerms = 9;
#ifdef __CUDA_ARCH__
__constant__
#else
constexpr
#endif
    double kExpm1Poly[kExpm1PolyTerms] = {
        2.7613795662346626e-07, 2.7625102134822924e-06, 2.4801536408869822e-05,
        1.9841208756759125e-04, 1.3888888905871442e-03, 8.333333353717274e-03,
        4.1666666666651364e-02, 1.6666666666648303e-01, 0.5};

C10_HOST_DEVICE inline NegExp neg_exp_poly(double x) {
  constexpr double kInvLn2 = 1.4426950408889634;
  constexpr double kLn2Hi = 6.93147180369123816490e-01;  // 0x3fe62e42fee00000
  constexpr double kLn2Lo = 1.90821492927058770002e-10;
  constexpr double kRound = 6755399441055744.0;  // 1.5 * 2^52: adding it rounds to an integer
  constexpr double kLimit = 708.0;
  const double y = -x;
  // Selects, not fmin/fmax: those would turn NaN into the bound.
  const double yc = y < -kLimit ? -kLimit : (y > kLimit ? kLimit : y);
  const double shifted = fma(yc, kInvLn2, kRound);
  const double k = shifted - kRound;
  double r = fma(k, -kLn2Hi, yc);
  r = fma(k, -kLn2Lo, r);
  double q = kExpm1Poly[0];
#pragma unroll
  for (int i = 1; i < kExpm1PolyTerms; ++i) q = fma(q, r, kExpm1Poly[i]);
  const double p = fma(r * r, q, r);  // expm1(r)
  // 2^k from the bits of 1.5 * 2^52 + k, whose low word is k (two's complement).
  const double scale = double_of(int64_t(static_cast<int32_t>(bits_of(shifted)) + 1023) << 52);
  return {y < -kLimit ? 0.0 : fma(scale, p, scale), fma(-scale, p, 1.0 - scale)};
}

}  // namespace mixer_nerf
