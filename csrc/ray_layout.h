// Where a ray's rows lie, for every op's CPU and CUDA kernels: the padded (R, S) layout and the
// packed (ragged, CSR) one. The namespace keeps the name of its first user, composite: it is
// part of the symbol of every kernel templated on a layout.
#pragma once

#include <c10/macros/Macros.h>

#include <cstdint>

namespace mixer_nerf {
namespace composite_layout {

// A ray's rows: `count` consecutive rows from `offset`.
struct RaySpan {
  int64_t offset;
  int64_t count;
};

// Padded (R, S): ray r holds rows r * S .. r * S + S - 1.
struct DenseRays {
  int64_t samples_per_ray;
  C10_HOST_DEVICE RaySpan operator()(int64_t ray) const { return {ray * samples_per_ray, samples_per_ray}; }
  C10_HOST_DEVICE bool well_formed(int64_t /*ray*/, int64_t /*rays*/) const { return true; }
};

// Packed (CSR): ray r owns rows offsets[r] .. offsets[r+1] - 1 of N. Offsets are validated in
// Python unless the caller opts out; unchecked ones are clamped into [0, N] (an end never before
// its start), so no kernel reads or writes outside the arrays, and taken as 0 before the first ray
// and N after the last, as valid ones are: then every row has a ray that writes its outputs (the
// clamped bounds only jump down, so each row lies on a ray between 0 and N), never left unwritten.
struct PackedRays {
  const int64_t* offsets;  // (R + 1)
  int64_t total;           // N
  int64_t num_rays;        // R
  C10_HOST_DEVICE RaySpan operator()(int64_t ray) const {
    const int64_t begin = ray == 0 ? 0 : clamp(offsets[ray], 0, total);
    const int64_t end = ray + 1 == num_rays ? total : clamp(offsets[ray + 1], begin, total);
    return {begin, end - begin};
  }
  // Whether ray `ray` of `rays` has offsets a validation would accept: in [0, N], not decreasing,
  // from 0 (first ray) and to N (last ray). Kernels that check values in place report the rest.
  C10_HOST_DEVICE bool well_formed(int64_t ray, int64_t rays) const {
    const int64_t begin = offsets[ray], end = offsets[ray + 1];
    return 0 <= begin && begin <= end && end <= total && (ray > 0 || begin == 0) && (ray + 1 < rays || end == total);
  }
  C10_HOST_DEVICE static int64_t clamp(int64_t x, int64_t lo, int64_t hi) { return x < lo ? lo : (x > hi ? hi : x); }
};

}  // namespace composite_layout
}  // namespace mixer_nerf
