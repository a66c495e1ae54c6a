// CUDA kernels of mlca, per point with X = encoded row (T, D) (see mlca.cpp for the math):
//   L = X lift^T,  Y = L + GELU(W_t L + b_t),  Z = Y + GELU(Y W_c^T + b_c)   -> (N, T*C)
//
// Mapping: a block takes a tile of P whole points and one thread per (point, channel), P = threads
// / C. Token mixing is independent per channel, so a thread keeps its channel's column L[:, c] of
// all T tokens in registers (arrays sized by a compile-time bucket kT >= T, zero-padded, fully
// unrolled) and reads W_t from shared memory (warp-uniform addresses: broadcasts). Channel mixing
// needs the other channels of the same token: Y goes through a shared-memory tile. The tile's
// rows are one contiguous span of global memory, so encoded, grad_out, out and grad_encoded are
// moved between global and shared memory with consecutive threads on consecutive addresses.
//
// Backward: a persistent grid loops over tiles and recomputes L, Y and the pre-activations from
// encoded. Weight gradients are sums over points, three small matrix products per tile read from
// shared memory: dW_t | db_t = gP [L; 1]^T over the tile's (point, channel) columns, dW_c | db_c =
// gQ^T [Y, 1] and dlift = dL^T X over its (point, token) rows (the biases through a row or column
// of ones). Each thread owns a register block of each (see BlockSums), kA x kB sums of one slice
// of the terms, kept in registers across all of the block's tiles: a term reads kA + kB shared
// values for kA kB FMAs. At the end the blocks go through shared memory, each entry's slices are
// added in a fixed order into the block's row of a (blocks, params) buffer, and the rows are
// summed afterwards. No atomics: the result is deterministic for a given grid.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>  // = at::cuda::getCurrentCUDAStream, without the cuSPARSE/cuBLAS headers

#include <algorithm>
#include <cstdint>
#include <type_traits>
#include <utility>

#include "columns.cuh"
#include "common.h"
#include "mlca.h"

namespace mixer_nerf {
namespace {

namespace mm = mlca;
using mm::Sizes;

constexpr int kForwardThreads = 256;
constexpr int kBackwardThreads = 128;  // smaller tiles: the backward's shared memory is ~3x the forward's
constexpr int kDefaultSharedBytes = 48 * 1024;

struct Problem {
  int64_t points;  // N
  int T, C, D;
  int tile;     // P, points per tile
  int threads;  // per block: a kernel's constant, set in the kernel (folds like the sizes below)
};

// The model's sizes (T = kT, C = 8 or 3, D = 3; positions and directions) as compile-time constants:
// every shared-memory stride and loop bound then folds into the instructions instead of being
// computed at run time. Other sizes take the run-time path (kC = 0).
using mm::kExactChannels, mm::kExactTokenDim, mm::kNarrowChannels;

// This kernel's problem: pr with the block size, and with the exact sizes where kC says so.
template <int kT, int kC, int kThreads>
__device__ __forceinline__ Problem fixed(Problem pr) {
  pr.threads = kThreads;
  if constexpr (kC > 0) {
    pr.T = kT;
    pr.C = kC;
    pr.D = kExactTokenDim;
    pr.tile = kThreads / kC;
  }
  return pr;
}

// Register blocks of the backward's weight-gradient sums (rows x columns of sums per thread, see
// BlockSums): W_t's take most of the work, and kT = 32 has the fewest registers to spare.
constexpr int token_block_rows(int kT) { return kT == 32 ? 4 : 3; }
constexpr int token_block_cols(int kT) { return kT == 21 ? 8 : 4; }
constexpr int kChannelBlockRows = 4, kChannelBlockCols = 3;  // dW_c (C x C+1 with db_c) and dlift (C x D)

// Offsets (in accumulation-type elements) of the shared-memory arrays of a block.
struct Layout {
  int token_stride, channel_stride, lift_stride, k_stride;
  int y_stride, grad_stride;                           // rows of the backward's (P, T, .) tiles
  int token, token_bias, channel, channel_bias, lift;  // the weights
  int x, grad, a, b;                                   // tiles; grad, a, b in the backward only
  int total;
};

C10_HOST_DEVICE inline Layout make_layout(int kT, const Problem& pr, int threads, bool backward) {
  Layout l{};
  const int T = pr.T, C = pr.C, D = pr.D, K = pr.tile * C;
  l.token_stride = (kT + 3) / 4 * 4;  // aligned rows: 16-byte broadcasts of W_t
  l.channel_stride = C | 1;           // odd strides: threads of different channels hit different banks
  l.lift_stride = D | 1;
  l.k_stride = K | 1;
  l.y_stride = (C + 1) | 1;  // Y and a column of ones (for db_c)
  l.grad_stride = C | 1;
  int at = 0;
  auto take = [&](int n) { const int start = at; at += n; return start; };
  l.token = take(kT * l.token_stride);
  l.token_bias = take(kT);
  l.channel = take(C * l.channel_stride);
  l.channel_bias = take(C);
  l.lift = take(C * l.lift_stride);
  l.x = take(pr.tile * T * D);
  if (!backward) {
    l.a = take(pr.tile * T * C);
  } else {
    l.grad = take(pr.tile * T * l.grad_stride);
    const int y = pr.tile * T * l.y_stride, gp = T * l.k_stride;
    l.a = take(y > gp ? y : gp);       // (P, T, C + 1) or (T, K) layouts
    l.b = take((T + 1) * l.k_stride);  // L and a row of ones (for db_t)
    // After the tile loop, the tiles take every thread's register block of one set of sums.
    const int token = token_block_rows(kT) * token_block_cols(kT), channel = kChannelBlockRows * kChannelBlockCols;
    const int dump = l.x + threads * (token > channel ? token : channel);
    if (at < dump) at = dump;
  }
  l.total = at;
  return l;
}

template <typename scalar_t>
struct Weights {
  const scalar_t* lift;            // (C, D)
  const scalar_t* token_weight;    // (T, T)
  const scalar_t* token_bias;      // (T)
  const scalar_t* channel_weight;  // (C, C)
  const scalar_t* channel_bias;    // (C)
};

template <typename acc>
__device__ acc* shared_memory() {
  extern __shared__ __align__(16) unsigned char shared_bytes[];
  return reinterpret_cast<acc*>(shared_bytes);
}

// Weights into shared memory, W_t zero-padded to kT x kT (padded tokens then stay exactly zero).
template <int kT, typename scalar_t, typename acc>
__device__ void load_weights(acc* sm, const Layout& l, const Weights<scalar_t>& w, const Problem& pr) {
  const int T = pr.T, C = pr.C, D = pr.D, threads = pr.threads;
  for (int i = threadIdx.x; i < kT * l.token_stride; i += threads) {
    const int t = i / l.token_stride, s = i - t * l.token_stride;
    sm[l.token + i] = t < T && s < T ? static_cast<acc>(w.token_weight[t * T + s]) : acc(0);
  }
  for (int i = threadIdx.x; i < kT; i += threads) {
    sm[l.token_bias + i] = i < T ? static_cast<acc>(w.token_bias[i]) : acc(0);
  }
  for (int i = threadIdx.x; i < C * C; i += threads) {
    sm[l.channel + i / C * l.channel_stride + i % C] = static_cast<acc>(w.channel_weight[i]);
  }
  for (int i = threadIdx.x; i < C; i += threads) sm[l.channel_bias + i] = static_cast<acc>(w.channel_bias[i]);
  for (int i = threadIdx.x; i < C * D; i += threads) {
    sm[l.lift + i / D * l.lift_stride + i % D] = static_cast<acc>(w.lift[i]);
  }
}

// L[t] = sum_k lift[c, k] X[t, k] of this thread's point (x: its (T, D) rows) and channel c.
template <int kT, typename acc>
__device__ void lift_tokens(const acc* sm, const Layout& l, const acc* x, int c, const Problem& pr, acc (&L)[kT]) {
  const acc* lift = sm + l.lift + c * l.lift_stride;
#pragma unroll
  for (int t = 0; t < kT; ++t) L[t] = 0;
  for (int k = 0; k < pr.D; ++k) {  // k outermost: each lift weight read once, the same sums in the same order
    const acc w = lift[k];
#pragma unroll
    for (int t = 0; t < kT; ++t) {
      if (t < pr.T) L[t] += w * x[t * pr.D + k];
    }
  }
}

// The token-mixing pre-activation of token t: b_t[t] + sum_s W_t[t, s] L[s].
template <int kT, typename acc>
__device__ acc token_pre(const acc* sm, const Layout& l, int t, const acc (&L)[kT]) {
  const acc* row = sm + l.token + t * l.token_stride;
  acc pre = sm[l.token_bias + t];
#pragma unroll
  for (int s = 0; s < kT; ++s) pre += row[s] * L[s];
  return pre;
}

// The channel-mixing pre-activation of channel c of one token: b_c[c] + sum_e W_c[c, e] y[e].
template <typename acc>
__device__ acc channel_pre(const acc* sm, const Layout& l, int c, const acc* y, int C) {
  const acc* row = sm + l.channel + c * l.channel_stride;
  acc pre = sm[l.channel_bias + c];
  for (int e = 0; e < C; ++e) pre += row[e] * y[e];
  return pre;
}

template <typename scalar_t, int kT, int kC>
__global__ void __launch_bounds__(kForwardThreads) mlca_forward(const scalar_t* __restrict__ encoded,
                                                                Weights<scalar_t> w, scalar_t* __restrict__ out,
                                                                Problem problem) {
  using acc = acc_t<scalar_t>;
  acc* sm = shared_memory<acc>();
  const Problem pr = fixed<kT, kC, kForwardThreads>(problem);
  const Layout l = make_layout(kT, pr, pr.threads, false);
  const int T = pr.T, C = pr.C, D = pr.D;
  const int64_t first = static_cast<int64_t>(blockIdx.x) * pr.tile;
  const int points = static_cast<int>(pr.points - first < pr.tile ? pr.points - first : pr.tile);
  load_weights<kT>(sm, l, w, pr);
  acc* xs = sm + l.x;
  acc* ys = sm + l.a;  // (P, T, C): Y, then Z
  for (int j = threadIdx.x; j < points * T * D; j += pr.threads) xs[j] = static_cast<acc>(encoded[first * T * D + j]);
  __syncthreads();

  const int p = threadIdx.x / C, c = threadIdx.x - p * C;
  const bool active = p < points;
  acc Y[kT];
  if (active) {
    acc L[kT];
    lift_tokens(sm, l, xs + p * T * D, c, pr, L);
#pragma unroll
    for (int t = 0; t < kT; ++t) {
      Y[t] = t < T ? L[t] + mm::gelu(token_pre(sm, l, t, L)) : acc(0);
      if (t < T) ys[(p * T + t) * C + c] = Y[t];
    }
  }
  __syncthreads();
  if (active) {
#pragma unroll
    for (int t = 0; t < kT; ++t) {
      if (t < T) Y[t] += mm::gelu(channel_pre(sm, l, c, ys + (p * T + t) * C, C));
    }
  }
  __syncthreads();  // every Y read: overwrite the tile with Z
  if (active) {
#pragma unroll
    for (int t = 0; t < kT; ++t) {
      if (t < T) ys[(p * T + t) * C + c] = Y[t];
    }
  }
  __syncthreads();
  for (int j = threadIdx.x; j < points * T * C; j += pr.threads) out[first * T * C + j] = static_cast<scalar_t>(ys[j]);
}

// One set of a block's weight-gradient sums: S[a][b] = sum over m < terms of A(m, a) B(m, b) for
// a < rows, b < cols, with A(m, a) at sm[a_at + a a_row + m a_term] and B(m, b) likewise.
struct Sums {
  int a_at, a_row, a_term;
  int b_at, b_row, b_term;
  int rows, cols, terms;
  bool interleave;  // slice s takes terms s, s + slices, ... instead of a contiguous range
  int threads;      // of the block
};

// How a block's threads share a set of sums in kA x kB register blocks: thread slice * groups +
// group owns rows ga + i row_groups (i < kA) and columns gb + j col_groups (j < kB), group = gb
// row_groups + ga, for one slice of the terms. Interleaved rows and columns put the threads of a
// warp on neighbouring rows, i.e. on different banks.
template <int kA, int kB>
struct Split {
  int row_groups, col_groups, groups, slices;
  __device__ Split(int rows, int cols, int threads)
      : row_groups((rows + kA - 1) / kA),
        col_groups((cols + kB - 1) / kB),
        groups(row_groups * col_groups),
        slices(threads > groups ? threads / groups : 1) {}
};

// This thread's kA x kB block of a set of sums, in registers across all the tiles of the block: each
// term reads kA + kB shared values for kA kB FMAs (one value per FMA would be shared-load bound).
// Rows and columns past the end repeat the last one and are never written out.
template <int kA, int kB, typename acc>
struct BlockSums {
  acc sum[kA][kB];

  __device__ BlockSums() {
#pragma unroll
    for (int i = 0; i < kA; ++i) {
#pragma unroll
      for (int j = 0; j < kB; ++j) sum[i][j] = 0;
    }
  }

  // Adds this tile's terms of this thread's slice.
  __device__ void add(const acc* sm, const Sums& d) {
    const Split<kA, kB> sp(d.rows, d.cols, d.threads);
    const int tid = threadIdx.x;
    if (tid >= sp.groups * sp.slices) return;
    const int slice = tid / sp.groups, group = tid - slice * sp.groups;
    const int ga = group % sp.row_groups, gb = group / sp.row_groups;
    int a_at[kA], b_at[kB];
#pragma unroll
    for (int i = 0; i < kA; ++i) a_at[i] = d.a_at + min(ga + i * sp.row_groups, d.rows - 1) * d.a_row;
#pragma unroll
    for (int j = 0; j < kB; ++j) b_at[j] = d.b_at + min(gb + j * sp.col_groups, d.cols - 1) * d.b_row;
    const int begin = d.interleave ? slice : d.terms * slice / sp.slices;
    const int end = d.interleave ? d.terms : d.terms * (slice + 1) / sp.slices;
    const int step = d.interleave ? sp.slices : 1;
    for (int m = begin; m < end; m += step) {
      acc a[kA], b[kB];
#pragma unroll
      for (int i = 0; i < kA; ++i) a[i] = sm[a_at[i] + m * d.a_term];
#pragma unroll
      for (int j = 0; j < kB; ++j) b[j] = sm[b_at[j] + m * d.b_term];
#pragma unroll
      for (int i = 0; i < kA; ++i) {
#pragma unroll
        for (int j = 0; j < kB; ++j) sum[i][j] += a[i] * b[j];
      }
    }
  }

  // The block's totals into row[index(a, b)]: every thread's block through dump (sum (i, j) of
  // thread tid at (i kB + j) owners + tid), then each entry's slices added in order.
  template <typename Index>
  __device__ void write_totals(acc* dump, const Sums& d, acc* row, Index index) const {
    const Split<kA, kB> sp(d.rows, d.cols, d.threads);
    const int tid = threadIdx.x, owners = sp.groups * sp.slices;
    if (tid < owners) {
#pragma unroll
      for (int i = 0; i < kA; ++i) {
#pragma unroll
        for (int j = 0; j < kB; ++j) dump[(i * kB + j) * owners + tid] = sum[i][j];
      }
    }
    __syncthreads();
    for (int e = tid; e < d.rows * d.cols; e += d.threads) {
      const int a = e / d.cols, b = e - a * d.cols;
      const int i = a / sp.row_groups, j = b / sp.col_groups;
      const acc* slot = dump + (i * kB + j) * owners + (b - j * sp.col_groups) * sp.row_groups + a - i * sp.row_groups;
      acc total = 0;
      for (int slice = 0; slice < sp.slices; ++slice) total += slot[slice * sp.groups];
      row[index(a, b)] = total;
    }
    __syncthreads();  // dump is reused by the next set
  }
};

// Every thread owns a block of every set (the sums of one group must cover all entries).
constexpr bool blocks_cover(int kA, int kB, int rows, int cols) {
  return (rows + kA - 1) / kA * ((cols + kB - 1) / kB) <= kBackwardThreads;
}
static_assert(blocks_cover(token_block_rows(9), token_block_cols(9), 9, 10) &&
              blocks_cover(token_block_rows(21), token_block_cols(21), 21, 22) &&
              blocks_cover(token_block_rows(32), token_block_cols(32), 32, 33) &&
              blocks_cover(kChannelBlockRows, kChannelBlockCols, 32, 33));

template <typename scalar_t, int kT, int kC>
__global__ void __launch_bounds__(kBackwardThreads) mlca_backward(
    const scalar_t* __restrict__ grad_out, const scalar_t* __restrict__ encoded, Weights<scalar_t> w,
    scalar_t* __restrict__ grad_encoded, acc_t<scalar_t>* __restrict__ partials, Problem problem) {
  using acc = acc_t<scalar_t>;
  acc* sm = shared_memory<acc>();
  const Problem pr = fixed<kT, kC, kBackwardThreads>(problem);
  const Layout l = make_layout(kT, pr, pr.threads, true);
  const int T = pr.T, C = pr.C, D = pr.D, P = pr.tile, K = P * C, Kp = l.k_stride;
  const int Cy = l.y_stride, Cg = l.grad_stride;
  load_weights<kT>(sm, l, w, pr);
  acc* xs = sm + l.x;     // (P, T, D): X
  acc* gs = sm + l.grad;  // (P, T, Cg): G, then gQ, then dL
  acc* as = sm + l.a;     // (P, T, Cy): Y and ones, then (T, Kp): gP
  acc* bs = sm + l.b;     // (T + 1, Kp): L and ones
  const acc* channel = sm + l.channel;
  const acc* lift = sm + l.lift;
  for (int k = threadIdx.x; k < K; k += pr.threads) bs[T * Kp + k] = 1;  // never overwritten

  // dW_t | db_t = gP [L; 1]^T over the tile's (point, channel) columns k, dW_c | db_c = gQ^T [Y, 1]
  // and dlift = dL^T X over its (point, token) rows m (interleaved slices: the rows' odd strides
  // put consecutive slices on different banks).
  const Sums token{l.a, Kp, 1, l.b, Kp, 1, T, T + 1, K, false, pr.threads};
  const Sums channel_sums{l.grad, 1, Cg, l.a, 1, Cy, C, C + 1, P * T, true, pr.threads};
  const Sums lift_sums{l.grad, 1, Cg, l.x, 1, D, C, D, P * T, true, pr.threads};
  BlockSums<token_block_rows(kT), token_block_cols(kT), acc> d_token;
  BlockSums<kChannelBlockRows, kChannelBlockCols, acc> d_channel, d_lift;

  const int p = threadIdx.x / C, c = threadIdx.x - p * C, k = threadIdx.x;  // k = p C + c
  const bool active = p < P;  // rows past the last point are zero: they add nothing to the sums
  // G moves to rows of stride Cg: element j = m C + e of the tile, tracked without dividing by C.
  const int m_step = pr.threads / C, e_step = pr.threads - m_step * C;
  const int64_t tiles = (pr.points + P - 1) / P;
  for (int64_t tile = blockIdx.x; tile < tiles; tile += gridDim.x) {
    const int64_t first = tile * P;
    const int points = static_cast<int>(pr.points - first < P ? pr.points - first : P);
    for (int j = threadIdx.x; j < P * T * D; j += pr.threads) {
      xs[j] = j < points * T * D ? static_cast<acc>(encoded[first * T * D + j]) : acc(0);
    }
    for (int j = threadIdx.x, m = p, e = c; j < P * T * C; j += pr.threads, m += m_step, e += e_step) {
      if (e >= C) {
        e -= C;
        ++m;
      }
      gs[m * Cg + e] = j < points * T * C ? static_cast<acc>(grad_out[first * T * C + j]) : acc(0);
    }
    for (int m = threadIdx.x; m < P * T; m += pr.threads) as[m * Cy + C] = 1;
    __syncthreads();

    // Recompute L (kept in bs for dW_t), Y (into as) and GELU'(P).
    acc dp[kT], dy[kT];  // GELU'(P) then gP; dY then dL
    if (active) {
      acc L[kT];
      lift_tokens(sm, l, xs + p * T * D, c, pr, L);
#pragma unroll
      for (int t = 0; t < kT; ++t) {
        acc g = 0;
        dp[t] = 0;
        if (t < T) mm::gelu_and_grad(token_pre(sm, l, t, L), g, dp[t]);
        if (t < T) {
          as[(p * T + t) * Cy + c] = L[t] + g;
          bs[t * Kp + k] = L[t];
        }
      }
    }
    __syncthreads();
    // Channel mixing: gQ = G GELU'(Q), in place of G; Q = b_c + Y W_c^T with e outermost (each
    // weight read once, the same sums in the same order as channel_pre).
    if (active) {
      acc q[kT];
#pragma unroll
      for (int t = 0; t < kT; ++t) q[t] = sm[l.channel_bias + c];
      for (int e = 0; e < C; ++e) {
        const acc we = channel[c * l.channel_stride + e];
        const acc* y = as + p * T * Cy + e;
#pragma unroll
        for (int t = 0; t < kT; ++t) {
          if (t < T) q[t] += we * y[t * Cy];
        }
      }
#pragma unroll
      for (int t = 0; t < kT; ++t) {
        dy[t] = 0;
        if (t < T) {
          const int at = (p * T + t) * Cg + c;
          dy[t] = gs[at];
          gs[at] = dy[t] * mm::gelu_grad(q[t]);
        }
      }
    }
    __syncthreads();
    d_channel.add(sm, channel_sums);
    __syncthreads();  // Y read: as takes gP
    // dY = G + gQ W_c (i outermost), gP = dY GELU'(P), dL = dY + W_t^T gP.
    if (active) {
      for (int i = 0; i < C; ++i) {
        const acc wi = channel[i * l.channel_stride + c];
        const acc* gq = gs + p * T * Cg + i;
#pragma unroll
        for (int t = 0; t < kT; ++t) {
          if (t < T) dy[t] += gq[t * Cg] * wi;
        }
      }
#pragma unroll
      for (int t = 0; t < kT; ++t) {
        if (t < T) {
          dp[t] *= dy[t];
          as[t * Kp + k] = dp[t];
        }
      }
#pragma unroll
      for (int t = 0; t < kT; ++t) {
        const acc* row = sm + l.token + t * l.token_stride;
#pragma unroll
        for (int s = 0; s < kT; ++s) dy[s] += row[s] * dp[t];
      }
    }
    __syncthreads();  // gQ read: gs takes dL
    if (active) {
#pragma unroll
      for (int t = 0; t < kT; ++t) {
        if (t < T) gs[(p * T + t) * Cg + c] = dy[t];
      }
    }
    __syncthreads();
    d_token.add(sm, token);
    d_lift.add(sm, lift_sums);
    if (grad_encoded != nullptr) {  // dX = dL lift, element j of the tile's contiguous rows
      for (int j = threadIdx.x; j < points * T * D; j += pr.threads) {
        const int m = j / D, e = j - m * D;
        acc sum = 0;
        for (int i = 0; i < C; ++i) sum += gs[m * Cg + i] * lift[i * l.lift_stride + e];
        grad_encoded[first * T * D + j] = static_cast<scalar_t>(sum);
      }
    }
    __syncthreads();
  }

  const Sizes s{T, C, D};
  acc* row = partials + static_cast<int64_t>(blockIdx.x) * s.params();
  d_token.write_totals(xs, token, row, [&](int a, int b) { return b < T ? a * T + b : T * T + a; });
  d_channel.write_totals(xs, channel_sums, row + s.channel_weight(),
                         [&](int a, int b) { return b < C ? a * C + b : C * C + a; });
  d_lift.write_totals(xs, lift_sums, row + s.lift(), [&](int a, int b) { return a * D + b; });
}

// Calls f(std::integral_constant<int, kT>) with the smallest token bucket kT >= T (T <= 32): the
// model's T = 9 (directions) and 21 (positions) exactly, anything else up to 32 zero-padded.
template <typename F>
void dispatch_tokens(int64_t T, F&& f) {
  if (T <= 9) {
    f(std::integral_constant<int, 9>{});
  } else if (T <= 21) {
    f(std::integral_constant<int, 21>{});
  } else {
    f(std::integral_constant<int, 32>{});
  }
}

int device_attribute(cudaDeviceAttr attribute, int device) {
  int value = 0;
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&value, attribute, device));
  return value;
}

// The largest tile (one point per C threads at most) whose shared memory fits the device, and
// its size in bytes; raises if not even one point fits.
std::pair<int, size_t> choose_tile(Problem& pr, int kT, int threads, bool backward, size_t element_bytes,
                                   int device) {
  const size_t limit = static_cast<size_t>(device_attribute(cudaDevAttrMaxSharedMemoryPerBlockOptin, device));
  for (pr.tile = threads / pr.C; pr.tile > 0; --pr.tile) {
    const size_t bytes = static_cast<size_t>(make_layout(kT, pr, threads, backward).total) * element_bytes;
    if (bytes <= limit) return {pr.tile, bytes};
  }
  MIXER_NERF_CHECK(false, "mlca: T=", pr.T, ", C=", pr.C, ", D=", pr.D, " need more shared memory than the device has");
  return {0, 0};
}

// Whether pr has the exact sizes of the kernel for kT tokens and kC channels, and its tile is the
// whole block (it is wherever the shared memory fits).
template <int kT, int kC>
bool exact_sizes(const Problem& pr, int threads) {
  return pr.T == kT && pr.C == kC && pr.D == kExactTokenDim && pr.tile == threads / kC;
}

// of(kC): the kernel for channels kC, for pr: for float at the model's sizes an exact-size one
// (kC = 8, the default, or 3, MLCA without widening the tokens), else the run-time-size one (kC = 0).
template <typename scalar_t, int kT, typename Of>
auto pick_kernel(const Problem& pr, int threads, Of of) {
  if constexpr (std::is_same_v<scalar_t, float> && kT != 32) {
    if (exact_sizes<kT, kExactChannels>(pr, threads)) return of(std::integral_constant<int, kExactChannels>{});
    if (exact_sizes<kT, kNarrowChannels>(pr, threads)) return of(std::integral_constant<int, kNarrowChannels>{});
  }
  return of(std::integral_constant<int, 0>{});
}

template <typename Kernel>
void allow_shared_bytes(Kernel kernel, size_t bytes) {
  if (bytes > kDefaultSharedBytes) {
    C10_CUDA_CHECK(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, static_cast<int>(bytes)));
  }
}

template <typename scalar_t>
Weights<scalar_t> weights_of(const at::Tensor& lift, const at::Tensor& token_weight, const at::Tensor& token_bias,
                             const at::Tensor& channel_weight, const at::Tensor& channel_bias) {
  return {lift.const_data_ptr<scalar_t>(), token_weight.const_data_ptr<scalar_t>(),
          token_bias.const_data_ptr<scalar_t>(), channel_weight.const_data_ptr<scalar_t>(),
          channel_bias.const_data_ptr<scalar_t>()};
}

Problem problem_of(const at::Tensor& encoded, const Sizes& s) {
  MIXER_NERF_CHECK(s.T <= 32 && s.C <= 32 && s.D <= 32, "mlca: the CUDA kernel takes T <= 32, C <= 32, D <= 32, got T=",
                   s.T, ", C=", s.C, ", D=", s.D);
  return {encoded.size(0), static_cast<int>(s.T), static_cast<int>(s.C), static_cast<int>(s.D), 0};
}

at::Tensor mlca_fwd_cuda(const at::Tensor& encoded, const at::Tensor& lift, const at::Tensor& token_weight,
                         const at::Tensor& token_bias, const at::Tensor& channel_weight,
                         const at::Tensor& channel_bias) {
  const Sizes s = mm::check_args(encoded, lift, token_weight, token_bias, channel_weight, channel_bias, at::kCUDA);
  Problem pr = problem_of(encoded, s);
  at::Tensor out = at::empty({pr.points, s.T * s.C}, encoded.options());
  if (pr.points == 0) return out;
  const c10::cuda::CUDAGuard guard(encoded.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  MIXER_NERF_DISPATCH_FLOATING(encoded.scalar_type(), "mlca_fwd_cuda", [&] {
    const auto w = weights_of<scalar_t>(lift, token_weight, token_bias, channel_weight, channel_bias);
    dispatch_tokens(s.T, [&](auto bucket) {
      constexpr int kT = decltype(bucket)::value;
      const auto [tile, bytes] =
          choose_tile(pr, kT, kForwardThreads, false, sizeof(acc_t<scalar_t>), encoded.device().index());
      const auto kernel = pick_kernel<scalar_t, kT>(
          pr, kForwardThreads, [](auto kC) { return mlca_forward<scalar_t, kT, decltype(kC)::value>; });
      allow_shared_bytes(kernel, bytes);
      const auto blocks = static_cast<unsigned>((pr.points + tile - 1) / tile);
      kernel<<<blocks, kForwardThreads, bytes, stream>>>(encoded.const_data_ptr<scalar_t>(), w,
                                                        out.mutable_data_ptr<scalar_t>(), pr);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  });
  return out;
}

// The weight gradients in the weights' dtype: the blocks' partial rows (blocks, params) summed in block
// order straight into the five tensors (one launch, where a sum, a cast and five copies were seven).
template <typename scalar_t>
mm::Grads weight_grads(std::optional<at::Tensor> grad_encoded, const at::Tensor& partials, const Sizes& s,
                       const at::TensorOptions& options, cudaStream_t stream) {
  at::Tensor lift = at::empty({s.C, s.D}, options), token_weight = at::empty({s.T, s.T}, options),
             token_bias = at::empty({s.T}, options), channel_weight = at::empty({s.C, s.C}, options),
             channel_bias = at::empty({s.C}, options);
  // in the order of a partial row (mlca.h's Sizes)
  const columns::Destinations<scalar_t, 5> out{
      {token_weight.data_ptr<scalar_t>(), token_bias.data_ptr<scalar_t>(), channel_weight.data_ptr<scalar_t>(),
       channel_bias.data_ptr<scalar_t>(), lift.data_ptr<scalar_t>()},
      {0, s.token_bias(), s.channel_weight(), s.channel_bias(), s.lift(), s.params()}};
  columns::sum_rows_kernel<<<columns::sum_rows_grid(s.params()), columns::sum_rows_block(), 0, stream>>>(
      partials.const_data_ptr<acc_t<scalar_t>>(), partials.size(0), s.params(), out);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {std::move(grad_encoded), lift, token_weight, token_bias, channel_weight, channel_bias};
}

mm::Grads mlca_bwd_cuda(const at::Tensor& grad_out, const at::Tensor& encoded, const at::Tensor& lift,
                        const at::Tensor& token_weight, const at::Tensor& token_bias,
                        const at::Tensor& channel_weight, const at::Tensor& channel_bias, bool input_grad) {
  const Sizes s = mm::check_args(encoded, lift, token_weight, token_bias, channel_weight, channel_bias, at::kCUDA);
  mm::check_grad_out(grad_out, encoded, s);
  Problem pr = problem_of(encoded, s);
  const c10::cuda::CUDAGuard guard(encoded.device());
  at::Tensor grad_encoded = input_grad ? at::empty_like(encoded) : at::Tensor();
  std::optional<at::Tensor> maybe_grad_encoded = input_grad ? std::optional<at::Tensor>(grad_encoded) : std::nullopt;
  const at::ScalarType acc_type = encoded.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  if (pr.points == 0) {
    return mm::split_grads(at::zeros({s.params()}, encoded.options().dtype(acc_type)), maybe_grad_encoded, s,
                           encoded.scalar_type());
  }
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const int device = encoded.device().index();
  mm::Grads grads;
  MIXER_NERF_DISPATCH_FLOATING(encoded.scalar_type(), "mlca_bwd_cuda", [&] {
    using acc = acc_t<scalar_t>;
    const auto w = weights_of<scalar_t>(lift, token_weight, token_bias, channel_weight, channel_bias);
    dispatch_tokens(s.T, [&](auto bucket) {
      constexpr int kT = decltype(bucket)::value;
      const auto [tile, bytes] = choose_tile(pr, kT, kBackwardThreads, true, sizeof(acc), device);
      const auto kernel = pick_kernel<scalar_t, kT>(
          pr, kBackwardThreads, [](auto kC) { return mlca_backward<scalar_t, kT, decltype(kC)::value>; });
      allow_shared_bytes(kernel, bytes);
      int per_sm = 0;
      C10_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, kernel, kBackwardThreads, bytes));
      const int64_t tiles = (pr.points + tile - 1) / tile;
      const int64_t resident = static_cast<int64_t>(std::max(per_sm, 1)) *
                               device_attribute(cudaDevAttrMultiProcessorCount, device);
      const auto blocks = static_cast<unsigned>(std::min(tiles, resident));
      const at::Tensor partials =
          at::empty({static_cast<int64_t>(blocks), s.params()}, encoded.options().dtype(acc_type));
      kernel<<<blocks, kBackwardThreads, bytes, stream>>>(
          grad_out.const_data_ptr<scalar_t>(), encoded.const_data_ptr<scalar_t>(), w,
          input_grad ? grad_encoded.mutable_data_ptr<scalar_t>() : nullptr, partials.mutable_data_ptr<acc>(), pr);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
      grads = weight_grads<scalar_t>(maybe_grad_encoded, partials, s, encoded.options(), stream);
    });
  });
  return grads;
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) {
  m.impl("mlca_fwd", &mlca_fwd_cuda);
  m.impl("mlca_bwd", &mlca_bwd_cuda);
}

}  // namespace mixer_nerf
