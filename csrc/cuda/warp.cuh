// Warp-level helpers shared by the CUDA kernels. Every caller runs whole warps (a kernel retires
// a warp's lanes together), so the full mask is right for every shuffle.
#pragma once

namespace mixer_nerf {

constexpr int kWarpSize = 32;
constexpr unsigned kFullMask = 0xffffffffu;

// Sum of x over lanes 0..lane (Hillis-Steele scan up the warp).
template <typename T>
__device__ __forceinline__ T warp_inclusive_sum(T x, int lane) {
#pragma unroll
  for (int d = 1; d < kWarpSize; d <<= 1) {
    const T y = __shfl_up_sync(kFullMask, x, d);
    if (lane >= d) x += y;
  }
  return x;
}

// Sum of x over lanes lane..31 (the same scan down the warp).
template <typename T>
__device__ __forceinline__ T warp_reverse_inclusive_sum(T x, int lane) {
#pragma unroll
  for (int d = 1; d < kWarpSize; d <<= 1) {
    const T y = __shfl_down_sync(kFullMask, x, d);
    if (lane + d < kWarpSize) x += y;
  }
  return x;
}

// Sum of x over the warp, the same value in every lane: each butterfly step adds the same two
// numbers everywhere, so no lane's rounding differs.
template <typename T>
__device__ __forceinline__ T warp_sum(T x) {
#pragma unroll
  for (int d = kWarpSize / 2; d > 0; d >>= 1) x += __shfl_xor_sync(kFullMask, x, d);
  return x;
}

}  // namespace mixer_nerf
