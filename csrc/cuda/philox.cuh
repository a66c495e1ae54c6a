// Philox-4x32-10 (Salmon et al., "Parallel random numbers: as easy as 1, 2, 3", SC 2011): a
// counter-based generator, so a kernel draws the value of any (sequence, block) directly, with
// no state to carry. Seeds and offsets come from PyTorch's CUDA generator (PhiloxCudaState), so
// draws follow torch.manual_seed and stay correct under CUDA graph capture.
#pragma once

#include <cstdint>

namespace mixer_nerf {
namespace philox {

// The 128 random bits of block `block` of sequence `sequence` under `seed`.
__device__ __forceinline__ uint4 block_bits(uint64_t seed, uint64_t block, uint64_t sequence) {
  constexpr uint32_t kMul0 = 0xD2511F53u, kMul1 = 0xCD9E8D57u;  // round multipliers
  constexpr uint32_t kKey0 = 0x9E3779B9u, kKey1 = 0xBB67AE85u;  // key schedule (golden ratio, sqrt(3) - 1)
  uint4 c{uint32_t(block), uint32_t(block >> 32), uint32_t(sequence), uint32_t(sequence >> 32)};
  uint32_t k0 = uint32_t(seed), k1 = uint32_t(seed >> 32);
#pragma unroll
  for (int round = 0; round < 10; ++round) {
    const uint32_t hi0 = __umulhi(kMul0, c.x), lo0 = kMul0 * c.x;
    const uint32_t hi1 = __umulhi(kMul1, c.z), lo1 = kMul1 * c.z;
    c = uint4{hi1 ^ c.y ^ k0, lo1, hi0 ^ c.w ^ k1, lo0};
    k0 += kKey0;
    k1 += kKey1;
  }
  return c;
}

// Uniform values in [0, 1) a block gives with the full precision of T (24 bits for float, 53 for
// double): four floats or two doubles.
template <typename T>
constexpr int kValuesPerBlock = sizeof(T) == 8 ? 2 : 4;

// Value `k` (< kValuesPerBlock<T>) of a block's bits.
template <typename T>
__device__ __forceinline__ T uniform(uint4 bits, int k) {
  if constexpr (sizeof(T) == 8) {
    const uint32_t hi = k == 0 ? bits.x : bits.z, lo = k == 0 ? bits.y : bits.w;
    return T((uint64_t(hi) << 21) | (lo >> 11)) * T(1.0 / 9007199254740992.0);  // 2^-53
  } else {
    const uint32_t word = k == 0 ? bits.x : k == 1 ? bits.y : k == 2 ? bits.z : bits.w;
    return T(word >> 8) * T(1.0f / 16777216.0f);  // 2^-24
  }
}

}  // namespace philox
}  // namespace mixer_nerf
