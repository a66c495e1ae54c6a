// sin/cos of pi * c * 2^k * x with an exact range reduction, shared by the CPU and CUDA
// positional-encoding kernels (positional_encoding.cpp, cuda/positional_encoding.cu).
//
// The phase in half-turns (angle = pi * p) is p = c 2^k x with c = scale / pi split as
// c_hi + c_lo, c_hi holding 29 significant bits. For inputs of at most 24 bits (float, half,
// bf16) c_hi 2^k x is exact in double; it is reduced exactly to quarter turns plus a remainder in
// [-1/4, 1/4], and the small c_lo 2^k x is added to that remainder. The phase error is thus
// ~2^-80 |p|: high frequencies keep the accuracy of low ones (sin(scale 2^k x) in float32 loses
// |scale 2^k x| 2^-24). For double inputs c_hi 2^k x rounds once (relative 2^-53). sin/cos of
// pi * remainder come from double polynomials, rounded once to the output's accumulation type.
#pragma once

#include <c10/macros/Macros.h>

#include <cmath>

namespace mixer_nerf {
namespace positional_encoding_math {

// The phase is carried in double whatever the input dtype.
using phase_t = double;

// Round to nearest even: one instruction on the GPU. On the host, add-and-subtract magic numbers
// (no libm call, no data-dependent select) so loops vectorise on plain SSE2: the first step
// rounds |v| < 2^52, the second fixes the integer residual left for larger |v|. Exact for all
// finite doubles (checked exhaustively by binade in the tests' development).
C10_HOST_DEVICE inline double round_even(double v) {
#ifdef __CUDA_ARCH__
  return rint(v);
#else
  constexpr double kTwo52 = 4503599627370496.0, kThreeTwo51 = 6755399441055744.0;
  const double a = std::fabs(v);
  const double t = (a + kTwo52) - kTwo52;
  return std::copysign(t + (((a - t) + kThreeTwo51) - kThreeTwo51), v);
#endif
}

// sin(pi f), cos(pi f) for |f| <= 1/4 by their Taylor series in double. For double results the
// first omitted term is below 1e-19 of the result; for float (also half/bf16) results the series
// stops earlier, its first omitted term below 7e-12 relative: either way the one final rounding
// to the accumulation type dominates (float: at most ~0.5 ulp + 7e-12).
template <bool kDoubleResult>
C10_HOST_DEVICE inline void sincospi_quarter(double f, double& s, double& c) {
  const double z = f * f;
  if constexpr (kDoubleResult) {
    s = f * (3.141592653589793 +
             z * (-5.16771278004997 +
                  z * (2.5501640398773455 +
                       z * (-0.5992645293207921 +
                            z * (0.08214588661112823 +
                                 z * (-0.0073704309457143504 +
                                      z * (0.00046630280576761255 +
                                           z * (-2.1915353447830217e-05 + z * 7.952054001475513e-07))))))));
    c = 1.0 + z * (-4.934802200544679 +
                   z * (4.0587121264167685 +
                        z * (-1.3352627688545895 +
                             z * (0.2353306303588932 +
                                  z * (-0.02580689139001406 +
                                       z * (0.0019295743094039231 +
                                            z * (-0.0001046381049248457 +
                                                 z * (4.303069587032947e-06 + z * -1.3878952462213771e-07))))))));
  } else {
    s = f * (3.141592653589793 +
             z * (-5.16771278004997 +
                  z * (2.5501640398773455 +
                       z * (-0.5992645293207921 + z * (0.08214588661112823 + z * -0.0073704309457143504)))));
    c = 1.0 + z * (-4.934802200544679 +
                   z * (4.0587121264167685 +
                        z * (-1.3352627688545895 +
                             z * (0.2353306303588932 + z * (-0.02580689139001406 + z * 0.0019295743094039231)))));
  }
}

// sin(pi p), cos(pi p), rounded once to T, for a phase p = hi + lo in half-turns, |lo| << |hi|, both
// finite (see bounded_input; a NaN phase gives NaN sin and cos). hi is reduced exactly; lo joins
// the remainder, which is reduced once more. Branch-free, so host loops over it vectorise.
template <typename T>
C10_HOST_DEVICE inline void sincospi(phase_t hi, phase_t lo, T& s, T& c) {
  const double n_hi = round_even(2 * hi);      // quarter turns of hi; 2 hi is exact
  const double r = (hi - 0.5 * n_hi) + lo;      // hi - n_hi/2 is exact, |.| <= 1/4
  const double n_r = round_even(2 * r);         // -1, 0 or 1 unless lo is huge
  const double f = r - 0.5 * n_r;               // exact, |f| <= 1/4
  double q = (n_hi - 4 * round_even(0.25 * n_hi)) + n_r;  // quarter turns mod 4, then
  q -= 4 * round_even(0.25 * q);                           // into {-2, -1, 0, 1, 2}
  double sf, cf;
  sincospi_quarter<(sizeof(T) >= 8)>(f, sf, cf);
  // angle = pi f + q pi/2: odd q swaps sin and cos, and the signs follow the quadrant.
#ifdef __CUDA_ARCH__
  // On the GPU as integer selects, sparing the (slower) double pipe.
  const int quadrant = static_cast<int>(q) & 3;  // {-2, -1, 0, 1, 2} -> {2, 3, 0, 1, 2}
  const double sin_mag = (quadrant & 1) ? cf : sf, cos_mag = (quadrant & 1) ? sf : cf;
  s = static_cast<T>((quadrant & 2) ? -sin_mag : sin_mag);       // negative in quadrants 2, 3
  c = static_cast<T>(((quadrant + 1) & 2) ? -cos_mag : cos_mag);  // negative in quadrants 1, 2
#else
  // On the host as a rotation by cos(q pi/2) = 1 - |q| and sin(q pi/2) = q (2 - |q|), both in
  // {-1, 0, 1}: every product and sum is exact, and branch-free loops vectorise.
  const double rot_cos = 1 - std::fabs(q), rot_sin = q * (2 - std::fabs(q));
  s = static_cast<T>(sf * rot_cos + cf * rot_sin);
  c = static_cast<T>(cf * rot_cos - sf * rot_sin);
#endif
}

// x itself, or x - x where |c_hi x| >= 2^900: such phases are meaningless at any precision. For
// finite x that is 0, which keeps every octave's phase (up to 2^63 times larger) finite, so no
// NaN/Inf comes out of finite inputs; for x = +-inf it is NaN, which reaches every sin/cos and
// the gradient (as sin(inf) does). NaN stays NaN. A select, no branch: host loops vectorise.
C10_HOST_DEVICE inline double bounded_input(double x, double c_hi) {
  constexpr double kMaxPhase = 0x1p900;
  return std::fabs(c_hi * x) >= kMaxPhase ? x - x : x;
}

// c = scale / pi in half-turns per radian, as hi + lo with hi of 29 significant bits (so hi times
// a 24-bit input is exact in double) and hi + lo within ~2^-80 relative of scale / pi. scale equal
// to math.pi (the double nearest pi) is read as pi itself: c = (1, 0), an exact phase.
struct HalfTurns {
  double hi, lo;
};

inline HalfTurns half_turns(double scale) {
  constexpr double kPiHi = 3.141592653589793, kPiLo = 1.2246467991473532e-16;  // pi = hi + lo
  if (scale == kPiHi) return {1.0, 0.0};
  const double c = scale / kPiHi;
  const double split = c * 16777217.0;  // 2^24 + 1: Veltkamp split, hi keeps 53 - 24 bits
  const double hi = split - (split - c);
  // scale - hi pi: the fma residual against kPiHi is exact; hi kPiLo is a ~2^-53 correction.
  const double lo = (std::fma(-hi, kPiHi, scale) - hi * kPiLo) / kPiHi;
  return {hi, lo};
}

}  // namespace positional_encoding_math
}  // namespace mixer_nerf
