// ray_marching on CUDA: one thread per ray, the two passes of the CPU kernel (count the kept
// samples of every ray; scan counts into offsets; march again writing them). The march is in
// ray_marching_math.h, shared with ray_marching.cpp; its mul()/add() keep nvcc from contracting
// products into FMAs, so this kernel's samples are bit-identical to the CPU kernel's. The grid
// is a bitfield (256 KiB at 128^3): lookups hit L1/L2. Not differentiable: no backward.
#include <torch/library.h>

#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <optional>
#include <tuple>

#include "common.h"
#include "ray_marching.h"
#include "ray_marching_math.h"

namespace mixer_nerf {
namespace {

using namespace ray_marching_math;

constexpr int kThreads = 128;

template <typename scalar_t, typename T>
__global__ void count_samples_kernel(MarchInputs<scalar_t, T> in, int64_t R, int64_t* counts) {
  const int64_t r = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (r >= R) return;
  CountOnly<T> count;
  counts[r] = in.march(r, count);
}

template <typename scalar_t, typename T>
__global__ void write_samples_kernel(MarchInputs<scalar_t, T> in, int64_t R, const int64_t* offsets,
                                     scalar_t* t_starts, scalar_t* t_ends, int64_t* ray_indices) {
  const int64_t r = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (r >= R) return;
  const int64_t first = offsets[r];
  WriteSamples<scalar_t, T> write{t_starts + first, t_ends + first, ray_indices + first, r};
  in.march(r, write);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> ray_marching_fwd_cuda(
    const at::Tensor& rays_o, const at::Tensor& rays_d, const at::Tensor& near, const at::Tensor& far,
    const std::optional<at::Tensor>& jitter, const at::Tensor& bitfield, const at::Tensor& aabb,
    at::IntArrayRef resolution, double step_size, double cone_angle, std::optional<int64_t> max_samples_per_ray) {
  check_ray_marching_inputs(rays_o, rays_d, near, far, jitter, bitfield, aabb, resolution, step_size, cone_angle,
                            max_samples_per_ray, at::kCUDA);
  const c10::cuda::CUDAGuard guard(rays_o.device());
  const auto stream = c10::cuda::getCurrentCUDAStream();
  const int64_t R = rays_o.size(0);
  const auto index_options = rays_o.options().dtype(at::kLong);
  at::Tensor offsets = at::zeros({R + 1}, index_options);
  if (R == 0) {
    return {at::empty({0}, rays_o.options()), at::empty({0}, rays_o.options()), at::empty({0}, index_options),
            offsets};
  }
  const unsigned blocks = unsigned((R + kThreads - 1) / kThreads);
  at::Tensor t_starts, t_ends, ray_indices;
  MIXER_NERF_DISPATCH_FLOATING(rays_o.scalar_type(), "ray_marching_fwd_cuda", [&] {
    using T = acc_t<scalar_t>;
    const auto in = march_inputs<scalar_t, T>(rays_o, rays_d, near, far, jitter, bitfield, aabb, resolution,
                                              step_size, cone_angle, max_samples_per_ray);
    at::Tensor counts = offsets.narrow(0, 1, R);
    count_samples_kernel<scalar_t, T><<<blocks, kThreads, 0, stream>>>(in, R, counts.data_ptr<int64_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    at::cumsum_out(counts, counts, 0);
    const int64_t N = offsets[R].item<int64_t>();  // the outputs' size: one sync, unavoidable
    t_starts = at::empty({N}, rays_o.options());
    t_ends = at::empty({N}, rays_o.options());
    ray_indices = at::empty({N}, index_options);
    if (N == 0) return;
    write_samples_kernel<scalar_t, T><<<blocks, kThreads, 0, stream>>>(
        in, R, offsets.data_ptr<int64_t>(), t_starts.data_ptr<scalar_t>(), t_ends.data_ptr<scalar_t>(),
        ray_indices.data_ptr<int64_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {t_starts, t_ends, ray_indices, offsets};
}

}  // namespace

TORCH_LIBRARY_IMPL(mixer_nerf, CUDA, m) { m.impl("ray_marching_fwd", &ray_marching_fwd_cuda); }

}  // namespace mixer_nerf
