// Helpers shared by the CPU and CUDA kernels of every op.
#pragma once

#include <ATen/ATen.h>
#include <ATen/OpMathType.h>
#include <ATen/Parallel.h>
#include <c10/macros/Macros.h>

#include <string>
#include <type_traits>
#include <vector>

namespace mixer_nerf {

// CPU loops built twice, for AVX2 and for the x86-64 baseline the extension is compiled for, the
// clone picked at load time by the CPU: twice the vector lanes of SSE2 where a loop vectorises.
// AVX2 without FMA, so every clone rounds every operation the same way.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(__CUDACC__)
#define MIXER_NERF_CPU_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define MIXER_NERF_CPU_CLONES
#endif

// Accumulation type: float for half/bfloat16/float, double for double.
template <typename scalar_t>
using acc_t = at::opmath_type<scalar_t>;

// Defensive checks inside kernels' host code; user-facing validation with clear messages
// happens in Python (mixer_nerf/ops/_checks.py) before any kernel runs.
//
// MIXER_NERF_CHECK(cond, parts...) is TORCH_CHECK with the message built here, from string
// pieces, integers, shapes, devices and dtypes, and handed to torch as one C string: on the GPU
// machine a TORCH_CHECK whose message streams a value killed the process instead of raising
// (docs/numerics.md, "Bad input"; tools/diagnose_exception_crash.py reproduces it).
namespace check_message {
inline void append(std::string& out, const char* part) { out += part; }
inline void append(std::string& out, const std::string& part) { out += part; }
template <typename T, std::enable_if_t<std::is_arithmetic_v<T>, int> = 0>
void append(std::string& out, T value) {
  out += std::to_string(value);
}
inline void append(std::string& out, c10::IntArrayRef shape) {
  out += '[';
  for (size_t i = 0; i < shape.size(); ++i) out += (i ? ", " : "") + std::to_string(shape[i]);
  out += ']';
}
inline void append(std::string& out, const std::vector<int64_t>& shape) { append(out, c10::IntArrayRef(shape)); }
inline void append(std::string& out, c10::DeviceType type) { out += c10::DeviceTypeName(type, /*lower_case=*/true); }
inline void append(std::string& out, const c10::Device& device) { out += device.str(); }
inline void append(std::string& out, c10::ScalarType dtype) { out += c10::toString(dtype); }

template <typename... Parts>
std::string build(const Parts&... parts) {
  std::string out;
  (append(out, parts), ...);
  return out;
}
}  // namespace check_message

#define MIXER_NERF_CHECK(cond, ...)                                                  \
  do {                                                                               \
    if (C10_UNLIKELY(!(cond))) {                                                     \
      const std::string mixer_nerf_message = ::mixer_nerf::check_message::build(__VA_ARGS__); \
      TORCH_CHECK(false, mixer_nerf_message.c_str());                                \
    }                                                                                \
  } while (false)

#define MIXER_NERF_CHECK_INPUT(t, dev)                                                             \
  MIXER_NERF_CHECK((t).device().type() == (dev), #t " must be on ", (dev), ", got ", (t).device()); \
  MIXER_NERF_CHECK((t).is_contiguous(), #t " must be contiguous")

// Floating dtypes every kernel accepts: float, double, half, bfloat16.
#define MIXER_NERF_DISPATCH_FLOATING(TYPE, NAME, ...) \
  AT_DISPATCH_FLOATING_TYPES_AND2(at::ScalarType::Half, at::ScalarType::BFloat16, TYPE, NAME, __VA_ARGS__)

}  // namespace mixer_nerf
