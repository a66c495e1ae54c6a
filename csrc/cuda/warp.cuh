// Warp-level helpers shared by the CUDA kernels. Every caller runs whole warps (a kernel retires
// a warp's lanes together), so the full mask is right for every shuffle.
#pragma once

namespace mixer_nerf {

constexpr int kWarpSize = 32;
constexpr unsigned kFullMask = 0xffffffffu;

struct Plus {
  template <typename T>
  __device__ __forceinline__ T operator()(T a, T b) const { return a + b; }
};
struct Times {
  template <typename T>
  __device__ __forceinline__ T operator()(T a, T b) const { return a * b; }
};

// x of lanes 0..lane combined by `op` (associative): a Hillis-Steele scan up the warp.
template <typename T, typename Op = Plus>
__device__ __forceinline__ T warp_inclusive_scan(T x, int lane, Op op = {}) {
#pragma unroll
  for (int d = 1; d < kWarpSize; d <<= 1) {
    const T y = __shfl_up_sync(kFullMask, x, d);
    if (lane >= d) x = op(y, x);
  }
  return x;
}

// x of lanes lane..31 combined by `op`: the same scan down the warp.
template <typename T, typename Op = Plus>
__device__ __forceinline__ T warp_reverse_inclusive_scan(T x, int lane, Op op = {}) {
#pragma unroll
  for (int d = 1; d < kWarpSize; d <<= 1) {
    const T y = __shfl_down_sync(kFullMask, x, d);
    if (lane + d < kWarpSize) x = op(x, y);
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
