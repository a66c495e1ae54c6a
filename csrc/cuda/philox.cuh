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

// A uniform value in [0, 1) with the full precision of T (24 bits for float, 53 for double).
template <typename T>
__device__ __forceinline__ T uniform(uint4 bits) {
  if constexpr (sizeof(T) == 8) {
    return T((uint64_t(bits.x) << 21) | (bits.y >> 11)) * T(1.0 / 9007199254740992.0);  // 2^-53
  } else {
    return T(bits.x >> 8) * T(1.0f / 16777216.0f);  // 2^-24
  }
}

}  // namespace philox
}  // namespace mixer_nerf
