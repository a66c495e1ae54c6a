// Helpers shared by the CPU and CUDA kernels of every op.
#pragma once

#include <ATen/ATen.h>
#include <ATen/OpMathType.h>
#include <ATen/Parallel.h>
#include <c10/macros/Macros.h>

namespace mixer_nerf {

// Accumulation type: float for half/bfloat16/float, double for double.
template <typename scalar_t>
using acc_t = at::opmath_type<scalar_t>;

// Defensive checks inside kernels' host code; user-facing validation with clear messages
// happens in Python (mixer_nerf/ops/_checks.py) before any kernel runs.
#define MIXER_NERF_CHECK_INPUT(t, dev)                                                        \
  TORCH_CHECK((t).device().type() == (dev), #t " must be on ", (dev), ", got ", (t).device()); \
  TORCH_CHECK((t).is_contiguous(), #t " must be contiguous")

// Floating dtypes every kernel accepts: float, double, half, bfloat16.
#define MIXER_NERF_DISPATCH_FLOATING(TYPE, NAME, ...) \
  AT_DISPATCH_FLOATING_TYPES_AND2(at::ScalarType::Half, at::ScalarType::BFloat16, TYPE, NAME, __VA_ARGS__)

}  // namespace mixer_nerf
