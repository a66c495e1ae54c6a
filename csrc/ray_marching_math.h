// Marching one ray through an occupancy grid, shared by the CPU and CUDA ray-marching kernels
// (ray_marching.cpp, cuda/ray_marching.cu); mixer_nerf/ops/ray_marching_reference.py spells out
// the same definition with dense tensors.
//
// A ray is clipped to the box: [t_lo, t_hi] = [near, far] n box. Its sample lattice starts at
// t_0 = t_lo + u step (u: stratified jitter in [0, 1), else 0); steps are `step` long while
// t cone_angle < step, then grow with distance (t_{k+1} = t_k (1 + cone_angle)). In closed form
//   t_k = t_0 + k step                      for k <= K0 = max(0, ceil((step / cone_angle - t_0) / step)),
//   t_k = t_K0 (1 + cone_angle)^(k - K0)    after (K0 is infinite when cone_angle is 0),
// so a kernel can jump to any index. Sample k is [t_k, min(t_{k+1}, t_hi)] for t_k < t_hi; it is
// kept iff the grid cell holding its midpoint is occupied, up to max_samples per ray.
//
// Empty space costs about two lookups per cell crossed: from a sample in an empty cell the march
// jumps to index floor(k(t_exit) - 1/2), k(t) being the fractional lattice index of the cell's
// exit, so every skipped sample ends half a step before the exit and lies in the same empty cell
// (the sample jumped to is tested as usual; usually it is the cell's last). Which samples are
// kept therefore depends only on the per-sample test, never on the jumps.
//
// Each product that feeds a sum goes through mul()/add(), which nvcc never contracts into an
// FMA (the host build has no FMA without -mfma, nor has eager PyTorch): lattice points,
// midpoints and cells are bit-identical on CPU, GPU and in the reference, and so are the sample
// sets for cone_angle = 0. (With cone_angle > 0, pow may differ by an ulp between libraries.)
#pragma once

#include <c10/macros/Macros.h>

#include <cmath>
#include <cstdint>

namespace mixer_nerf {
namespace ray_marching_math {

C10_HOST_DEVICE inline float mul(float a, float b) {
#ifdef __CUDA_ARCH__
  return __fmul_rn(a, b);
#else
  return a * b;
#endif
}
C10_HOST_DEVICE inline double mul(double a, double b) {
#ifdef __CUDA_ARCH__
  return __dmul_rn(a, b);
#else
  return a * b;
#endif
}
C10_HOST_DEVICE inline float add(float a, float b) {
#ifdef __CUDA_ARCH__
  return __fadd_rn(a, b);
#else
  return a + b;
#endif
}
C10_HOST_DEVICE inline double add(double a, double b) {
#ifdef __CUDA_ARCH__
  return __dadd_rn(a, b);
#else
  return a + b;
#endif
}

C10_HOST_DEVICE inline float ceil_(float x) { return ceilf(x); }
C10_HOST_DEVICE inline double ceil_(double x) { return ::ceil(x); }
C10_HOST_DEVICE inline float pow_(float a, float b) { return powf(a, b); }
C10_HOST_DEVICE inline double pow_(double a, double b) { return ::pow(a, b); }
C10_HOST_DEVICE inline float log_(float x) { return logf(x); }
C10_HOST_DEVICE inline double log_(double x) { return ::log(x); }
C10_HOST_DEVICE inline float log1p_(float x) { return log1pf(x); }
C10_HOST_DEVICE inline double log1p_(double x) { return ::log1p(x); }
template <typename T>
C10_HOST_DEVICE inline bool finite_(T x) {
#ifdef __CUDA_ARCH__
  return ::isfinite(x);
#else
  return std::isfinite(x);
#endif
}
template <typename T>
C10_HOST_DEVICE inline T min_(T a, T b) { return b < a ? b : a; }
template <typename T>
C10_HOST_DEVICE inline T max_(T a, T b) { return a < b ? b : a; }

// Indices past this are never reached; it keeps float-to-int conversions defined.
constexpr double kMaxIndex = 1099511627776.0;  // 2^40

// The box and occupancy bits of a grid of res[0] x res[1] x res[2] cells, x-major
// (cell = (ix * res[1] + iy) * res[2] + iz), bit `cell` at byte cell / 8, bit cell % 8.
template <typename T>
struct Grid {
  const uint8_t* bits;
  T lo[3], hi[3];
  T scale[3];      // cells per unit length: res / (hi - lo)
  T cell_size[3];  // (hi - lo) / res
  int64_t res[3];

  C10_HOST_DEVICE Grid(const uint8_t* bits_, const T* aabb, const int64_t* res_) : bits(bits_) {
    for (int a = 0; a < 3; ++a) {
      lo[a] = aabb[a];
      hi[a] = aabb[3 + a];
      res[a] = res_[a];
      scale[a] = T(res[a]) / (hi[a] - lo[a]);
      cell_size[a] = (hi[a] - lo[a]) / T(res[a]);
    }
  }

  // Cell index along axis a of finite coordinate x, clamped into the grid (x is inside the box
  // up to rounding). Clamping first makes truncation a floor, without a libm call on the host.
  C10_HOST_DEVICE int64_t axis_cell(int a, T x) const {
    return int64_t(min_(max_((x - lo[a]) * scale[a], T(0)), T(res[a] - 1)));
  }

  C10_HOST_DEVICE int64_t flat(const int64_t c[3]) const { return (c[0] * res[1] + c[1]) * res[2] + c[2]; }

  C10_HOST_DEVICE bool occupied(int64_t cell) const { return (bits[cell >> 3] >> (cell & 7)) & 1; }

  // Where the ray leaves cell c (+inf if it never does); inv_d = 1 / d (inf where d is 0).
  C10_HOST_DEVICE T cell_exit(const int64_t c[3], const T o[3], const T d[3], const T inv_d[3]) const {
    T t = T(INFINITY);
    for (int a = 0; a < 3; ++a) {
      if (d[a] == T(0)) continue;
      const T face = add(lo[a], mul(T(c[a] + (d[a] > T(0))), cell_size[a]));
      t = min_(t, (face - o[a]) * inv_d[a]);
    }
    return t;
  }
};

// [t_lo, t_hi] = [near, far] clipped to the box [lo, hi]. False when that is empty or not
// finite: the ray misses, its direction is zero, or an input is not finite (far may be +inf).
template <typename T>
C10_HOST_DEVICE bool clip_to_box(const T o[3], const T d[3], T near, T far, const Grid<T>& grid, T& t_lo, T& t_hi) {
  if (!finite_(near) || far != far) return false;
  t_lo = near;
  t_hi = far;
  bool moving = false;
  for (int a = 0; a < 3; ++a) {
    if (!finite_(o[a]) || !finite_(d[a])) return false;
    if (d[a] == T(0)) {  // parallel to this slab: inside it for all t, or never
      if (o[a] < grid.lo[a] || o[a] > grid.hi[a]) return false;
      continue;
    }
    moving = true;
    const T t_a = (grid.lo[a] - o[a]) / d[a], t_b = (grid.hi[a] - o[a]) / d[a];
    t_lo = max_(t_lo, min_(t_a, t_b));
    t_hi = min_(t_hi, max_(t_a, t_b));
  }
  return moving && t_lo < t_hi && finite_(t_hi);
}

// The sample lattice of one ray (see the top of this file).
template <typename T>
struct Lattice {
  T t0, step, inv_step, growth, log_growth;
  T geo_t0;  // t_K0, where steps start to grow; +inf when they never do
  int64_t k0;

  C10_HOST_DEVICE Lattice(T t_lo, T jitter, T step_, T cone_angle) : t0(add(t_lo, mul(jitter, step_))), step(step_), inv_step(T(1) / step_) {
    growth = T(1) + cone_angle;
    log_growth = log1p_(cone_angle);
    if (cone_angle > T(0)) {
      const T k = ceil_((step / cone_angle - t0) / step);
      k0 = int64_t(min_(max_(k, T(0)), T(kMaxIndex)));
      geo_t0 = add(t0, mul(T(k0), step));
    } else {
      k0 = int64_t(kMaxIndex);
      geo_t0 = T(INFINITY);
    }
  }

  C10_HOST_DEVICE T at(int64_t k) const {
    return k <= k0 ? add(t0, mul(T(k), step)) : mul(geo_t0, pow_(growth, T(k - k0)));
  }

  // Fractional index i with at(i) ~= t, for t >= t0; off by far less than one.
  C10_HOST_DEVICE T index_of(T t) const {
    return t <= geo_t0 ? (t - t0) * inv_step : T(k0) + log_(t / geo_t0) / log_growth;
  }
};

// Marches one ray; calls emit(n, t_start, t_end) for its n-th kept sample and returns how many
// it kept. Every iteration advances k (or stops), so it ends after at most as many iterations
// as the ray has lattice points.
template <typename T, typename Emit>
C10_HOST_DEVICE int64_t march_ray(const Grid<T>& grid, const T o[3], const T d[3], T t_hi, const Lattice<T>& lattice,
                                  int64_t max_samples, Emit& emit) {
  T inv_d[3];
  for (int a = 0; a < 3; ++a) inv_d[a] = T(1) / d[a];
  int64_t n = 0;
  int64_t k = 0;
  int64_t skipped_cell = -1;  // the empty cell last jumped through
  T t_start = lattice.at(0);
  while (n < max_samples && t_start < t_hi) {
    const T t_next = lattice.at(k + 1);
    const T t_end = min_(t_next, t_hi);
    const T mid = (t_start + t_end) * T(0.5);
    int64_t c[3];
    for (int a = 0; a < 3; ++a) c[a] = grid.axis_cell(a, add(o[a], mul(mid, d[a])));
    const int64_t cell = grid.flat(c);
    if (grid.occupied(cell)) {
      emit(n++, t_start, t_end);
    } else if (cell != skipped_cell) {
      const T t_exit = grid.cell_exit(c, o, d, inv_d);
      if (!(t_exit < t_hi)) break;  // the rest of the ray lies in this empty cell
      const T jump = lattice.index_of(t_exit) - T(0.5);  // > k: truncation is floor
      if (jump >= T(k + 2)) {
        k = int64_t(min_(jump, T(kMaxIndex)));
        skipped_cell = cell;
        t_start = lattice.at(k);
        continue;
      }
    }
    // Next sample; also after a jump, which lands on the cell's last sample (still empty).
    ++k;
    t_start = t_next;
  }
  return n;
}

// Per-ray inputs of a batch; pointers index rays (3 values per ray for o and d).
template <typename scalar_t, typename T>
struct MarchInputs {
  const scalar_t* rays_o;
  const scalar_t* rays_d;
  const scalar_t* near;
  const scalar_t* far;
  const scalar_t* jitter;  // nullptr: no jitter
  const uint8_t* bits;
  const T* aabb;  // (2, 3): min corner, max corner
  int64_t res[3];
  T step, cone_angle;
  int64_t max_samples;

  // Clips ray r to the box and returns march(grid, o, d, t_hi, lattice), or 0 for a ray that
  // misses it. `march` walks the lattice: march_ray on the host, a warp per ray on the GPU.
  template <typename March>
  C10_HOST_DEVICE int64_t clip_and(int64_t r, March&& march) const {
    const Grid<T> grid(bits, aabb, res);
    T o[3], d[3];
    for (int a = 0; a < 3; ++a) {
      o[a] = T(rays_o[3 * r + a]);
      d[a] = T(rays_d[3 * r + a]);
    }
    T t_lo, t_hi;
    if (!clip_to_box(o, d, T(near[r]), T(far[r]), grid, t_lo, t_hi)) return 0;
    const Lattice<T> lattice(t_lo, jitter ? T(jitter[r]) : T(0), step, cone_angle);
    return march(grid, o, d, t_hi, lattice);
  }

  // Marches ray r sample by sample; see march_ray.
  template <typename Emit>
  C10_HOST_DEVICE int64_t march(int64_t r, Emit& emit) const {
    return clip_and(r, [&](const Grid<T>& grid, const T* o, const T* d, T t_hi, const Lattice<T>& lattice) {
      return march_ray(grid, o, d, t_hi, lattice, max_samples, emit);
    });
  }
};

// Emit functors for the two passes.
template <typename T>
struct CountOnly {
  C10_HOST_DEVICE void operator()(int64_t, T, T) const {}
};

template <typename scalar_t, typename T>
struct WriteSamples {
  scalar_t* t_starts;  // the outputs' first row
  scalar_t* t_ends;
  int64_t* ray_indices;
  int64_t first;  // the ray's first row
  int64_t limit;  // rows the ray may fill: a fixed-size output cuts off the samples past its end
  int64_t ray;
  C10_HOST_DEVICE void operator()(int64_t n, T t_start, T t_end) const {
    if (n >= limit) return;
    t_starts[first + n] = scalar_t(t_start);
    t_ends[first + n] = scalar_t(t_end);
    ray_indices[first + n] = ray;
  }
};

// Rows ray r may fill from its first row `first`: all of them, or those before `capacity`.
C10_HOST_DEVICE inline int64_t rows_before(int64_t first, int64_t capacity) {
  return capacity < 0 ? INT64_MAX : (capacity > first ? capacity - first : 0);
}

}  // namespace ray_marching_math
}  // namespace mixer_nerf
