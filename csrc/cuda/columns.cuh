// Row-major (N, C) tensors walked by columns, shared by the segment ops, the bias gradient and
// mlca's weight gradients: threads form a (x, y) grid, x over columns of V channels moved as one
// 16-byte access where C and every pointer allow it, y over rows, and sums over rows reduced
// across y in a fixed order.
#pragma once

#include <cstdint>
#include <initializer_list>
#include <type_traits>

namespace mixer_nerf {
namespace columns {

constexpr int kThreads = 256;
constexpr int kVectorBytes = 16;

// V channels moved as one load or store (alignas makes it one 16-byte access when V fills 16 bytes).
template <typename scalar_t, int V>
struct alignas(sizeof(scalar_t) * V) Column {
  scalar_t v[V];
};

// Sums each thread's V accumulators over threadIdx.y (a power of two), in a fixed order; the
// totals end in the threads of threadIdx.y == 0. Every thread of the block must call it.
// Laid out channel-major ([V][kThreads]) so that a warp's stores hit distinct banks.
template <typename acc, int V>
__device__ void sum_over_rows(acc (&sum)[V], acc* scratch) {
  if (blockDim.y == 1) return;
  const int slot = threadIdx.y * blockDim.x + threadIdx.x;
#pragma unroll
  for (int j = 0; j < V; ++j) scratch[j * kThreads + slot] = sum[j];
  __syncthreads();
  for (int half = blockDim.y / 2; half > 0; half /= 2) {
    if (threadIdx.y < half) {
#pragma unroll
      for (int j = 0; j < V; ++j) scratch[j * kThreads + slot] += scratch[j * kThreads + slot + half * blockDim.x];
    }
    __syncthreads();
  }
#pragma unroll
  for (int j = 0; j < V; ++j) sum[j] = scratch[j * kThreads + threadIdx.x];
  __syncthreads();  // the scratch is reused by the next pass over columns
}

// Calls launch(std::integral_constant<int, V>) with V = 16 bytes of channels when C and every
// pointer allow 16-byte accesses, else V = 1.
template <typename scalar_t, typename Launch>
void with_column_width(int64_t C, std::initializer_list<const void*> pointers, Launch&& launch) {
  constexpr int V = kVectorBytes / sizeof(scalar_t);
  bool aligned = C % V == 0;
  for (const void* p : pointers) aligned = aligned && reinterpret_cast<uintptr_t>(p) % kVectorBytes == 0;
  if (aligned) {
    launch(std::integral_constant<int, V>{});
  } else {
    launch(std::integral_constant<int, 1>{});
  }
}

// Where sum_rows_kernel writes column c: K tensors, tensor k taking columns [begin[k], begin[k+1]).
template <typename T, int K>
struct Destinations {
  T* ptr[K];
  int64_t begin[K + 1];
  __device__ T& operator[](int64_t c) const {
    int k = 0;
    while (c >= begin[k + 1]) ++k;
    return ptr[k][c - begin[k]];
  }
};

// out[c] = the sum over r of partials[r][c] (rows of C acc values), in row order within each thread
// and across threads in sum_over_rows's fixed order: deterministic. Launch with blocks of (32,
// kThreads / 32) threads, (C + 31) / 32 of them: x over columns, y over rows.
template <typename acc, typename T, int K>
__global__ void __launch_bounds__(kThreads)
    sum_rows_kernel(const acc* partials, int64_t rows, int64_t C, Destinations<T, K> out) {
  __shared__ acc scratch[kThreads];
  const int64_t c = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  acc sum[1] = {acc(0)};
  if (c < C) {
#pragma unroll 4
    for (int64_t r = threadIdx.y; r < rows; r += blockDim.y) sum[0] += partials[r * C + c];
  }
  sum_over_rows<acc, 1>(sum, scratch);
  if (c < C && threadIdx.y == 0) out[c] = static_cast<T>(sum[0]);
}

inline dim3 sum_rows_grid(int64_t C) { return dim3(static_cast<unsigned>((C + 31) / 32)); }
inline dim3 sum_rows_block() { return dim3(32, kThreads / 32); }

// x over columns (a power of two, at most the block), y over rows.
inline dim3 block_for(int64_t cols) {
  int x = 1;
  while (x < cols && x < kThreads) x *= 2;
  return dim3(x, kThreads / x);
}

}  // namespace columns
}  // namespace mixer_nerf
