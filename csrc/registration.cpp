// The schemas of every mixer_nerf op, in one place. Kernels are attached per device in the op's
// own source: csrc/<op>.cpp (CPU) and csrc/cuda/<op>.cu (CUDA), with TORCH_LIBRARY_IMPL.
#include <Python.h>
#include <torch/library.h>

TORCH_LIBRARY(mixer_nerf, m) {
  // positional_encoding: x (..., D) -> (..., D * (include_input + 2 * num_freqs))
  m.def("positional_encoding_fwd(Tensor x, int num_freqs, bool include_input, float scale) -> Tensor");
  m.def("positional_encoding_bwd(Tensor grad_out, Tensor x, int num_freqs, bool include_input, float scale) -> Tensor");
  // sample_pdf: bins (R, B+1), weights (R, B), u (R, N) -> samples (R, N)
  m.def("sample_pdf_fwd(Tensor bins, Tensor weights, Tensor u, float weight_padding) -> Tensor");
  m.def("sample_pdf_bwd(Tensor grad_samples, Tensor bins, Tensor weights, Tensor u, float weight_padding) -> (Tensor, Tensor)");
  //   the same with stratified positions drawn by the op from generator: (n + U[0, 1)) / num_samples
  //   -> samples (R, N), the positions drawn u (R, N) (what sample_pdf_bwd takes; (R, 0), not written,
  //   unless keep_positions), invalid (1) int32 (sample_pdf.h InvalidInput bits)
  m.def("sample_pdf_stratified_fwd(Tensor bins, Tensor weights, int num_samples, Generator? generator, float weight_padding, bool keep_positions) -> (Tensor, Tensor, Tensor)");
  // sample_pdf_packed: ray r has B_r = offsets[r+1] - offsets[r] bins: weights (N), edges (N + R) (ray r's
  //   B_r + 1 edges from offsets[r] + r), u (S) or (R, S) -> samples (R, S)
  m.def("sample_pdf_packed_fwd(Tensor bins, Tensor weights, Tensor offsets, Tensor u, float weight_padding) -> Tensor");
  m.def("sample_pdf_packed_stratified_fwd(Tensor bins, Tensor weights, Tensor offsets, int num_samples, Generator? generator, float weight_padding, bool keep_positions) -> (Tensor, Tensor, Tensor)");
  m.def("sample_pdf_packed_bwd(Tensor grad_samples, Tensor bins, Tensor weights, Tensor offsets, Tensor u, float weight_padding) -> (Tensor, Tensor)");
  // hierarchical_samples: z_coarse (R, S), weights (R, S), u (R, N) -> merged depths (R, S+N), invalid (1) int32
  m.def("hierarchical_samples_fwd(Tensor z_coarse, Tensor weights, Tensor u, float weight_padding) -> (Tensor, Tensor)");
  //   the same with stratified positions drawn by the op from generator: (n + U[0, 1)) / num_samples
  m.def("hierarchical_samples_stratified_fwd(Tensor z_coarse, Tensor weights, int num_samples, Generator? generator, float weight_padding) -> (Tensor, Tensor)");
  // composite: sigmas (R, S), rgbs (R, S, C), t_starts/t_ends (R, S), background (C) or (R, C)
  //   -> color (R, C), depth (R), opacity (R), weights (R, S), chunk_transmittances float64 (what the backward
  //   starts from; none on the CPU), invalid (1) int32 (composite.h InvalidInput bits)
  m.def("composite_fwd(Tensor sigmas, Tensor rgbs, Tensor t_starts, Tensor t_ends, Tensor? background) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");
  //   backward: absent upstream gradients are zeros; interval_grads=False skips grad_t_starts/t_ends
  m.def("composite_bwd(Tensor? grad_color, Tensor? grad_depth, Tensor? grad_opacity, Tensor? grad_weights, Tensor sigmas, Tensor rgbs, Tensor t_starts, Tensor t_ends, Tensor? background, Tensor chunk_transmittances, bool interval_grads, bool background_grad) -> (Tensor, Tensor, Tensor?, Tensor?, Tensor?)");
  // composite_packed: the same on packed samples: sigmas/t_starts/t_ends (N), rgbs (N, C), offsets (R+1) int64
  //   (ray r owns rows offsets[r]:offsets[r+1]) -> color (R, C), depth (R), opacity (R), weights (N),
  //   chunk_transmittances, invalid (1)
  m.def("composite_packed_fwd(Tensor sigmas, Tensor rgbs, Tensor t_starts, Tensor t_ends, Tensor? background, Tensor offsets) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.def("composite_packed_bwd(Tensor? grad_color, Tensor? grad_depth, Tensor? grad_opacity, Tensor? grad_weights, Tensor sigmas, Tensor rgbs, Tensor t_starts, Tensor t_ends, Tensor? background, Tensor offsets, Tensor chunk_transmittances, bool interval_grads, bool background_grad) -> (Tensor, Tensor, Tensor?, Tensor?, Tensor?)");
  // ray_marching: rays_o/rays_d (R, 3), near/far (R), jitter (R) or None, occupancy bitfield uint8 (one bit
  //   per cell), aabb (2, 3) -> t_starts (N), t_ends (N), ray_indices (N) int64, offsets (R+1) int64, total (1)
  //   int64 (the samples marched). With a capacity the outputs have that many rows (no host sync): the
  //   samples past it are cut, offsets clamped to it, the rows after the samples zero. No backward.
  m.def("ray_marching_fwd(Tensor rays_o, Tensor rays_d, Tensor near, Tensor far, Tensor? jitter, Tensor bitfield, Tensor aabb, int[] resolution, float step_size, float cone_angle, int? max_samples_per_ray, int? capacity=None) -> (Tensor, Tensor, Tensor, Tensor, Tensor)");
  // transmittance_filter_fwd: sigmas, t_starts, t_ends (N) and offsets (R+1) -> keep (N) bool, the samples
  //   early termination (threshold, 0: off) and the alpha threshold (0: off) keep; rows past offsets[R] dropped
  m.def("transmittance_filter_fwd(Tensor sigmas, Tensor t_starts, Tensor t_ends, Tensor offsets, float threshold, float alpha_threshold) -> Tensor");
  // select_fixed_fwd: PackedSamples.select_fixed: keep (N) bool, t_starts, t_ends, ray_indices (N), offsets (R+1)
  //   -> the kept rows (of those before offsets[R]) in order in `capacity` rows, then zero rows: t_starts, t_ends,
  //   ray_indices (capacity), offsets (R+1) clamped to capacity, total (1) int64 kept before the cut
  m.def("select_fixed_fwd(Tensor keep, Tensor t_starts, Tensor t_ends, Tensor ray_indices, Tensor offsets, int capacity) -> (Tensor, Tensor, Tensor, Tensor, Tensor)");
  // padding_rays_fwd: packed samples' offsets (R+1) and ray_indices (N), the samples in rows [0, offsets[R])
  //   -> (ray_indices (N), offsets (R+1+P)) with P = ceil(N / rows_per_ray) rays owning the rows past the samples
  m.def("padding_rays_fwd(Tensor offsets, Tensor ray_indices, int rows_per_ray) -> (Tensor, Tensor)");
  // segment_mean / ray_scale (squeeze-and-excitation on packed samples), offsets (R+1) int64 (ray r
  //   owns rows offsets[r]:offsets[r+1]): segment_mean: values (N, C) -> per-ray mean (R, C), 0 for
  //   an empty ray; ray_scale: features (N, C), scale (R, C) -> features[i] * scale[ray(i)] (N, C);
  //   each forward also returns invalid (1) int32, kBadOffsets (csrc/segment_ops.h) for bad offsets
  m.def("segment_mean_fwd(Tensor values, Tensor offsets) -> (Tensor, Tensor)");
  m.def("segment_mean_bwd(Tensor grad, Tensor offsets, int num_rows) -> Tensor");
  m.def("ray_scale_fwd(Tensor features, Tensor scale, Tensor offsets) -> (Tensor, Tensor)");
  //   backward -> (grad_features (N, C), grad_scale (R, C))
  m.def("ray_scale_bwd(Tensor grad_out, Tensor features, Tensor scale, Tensor offsets) -> (Tensor, Tensor)");
  // bias_grad: grad (N, C) -> its column sums (C), a linear layer's bias gradient; relu_bias_bwd: grad and the
  //   layer's ReLU output y (N, C) -> (grad where y > 0 (N, C), the column sums of that (C))
  m.def("bias_grad(Tensor grad) -> Tensor");
  m.def("relu_bias_bwd(Tensor grad, Tensor out) -> (Tensor, Tensor)");
  // mlca: encoded (N, T*D) token-major, lift (C, D), token_weight (T, T), token_bias (T), channel_weight (C, C),
  //   channel_bias (C) -> (N, T*C); all one dtype. Backward: grads of (encoded, lift, token_weight, token_bias,
  //   channel_weight, channel_bias); input_grad=False skips grad_encoded (returned as None).
  m.def("mlca_fwd(Tensor encoded, Tensor lift, Tensor token_weight, Tensor token_bias, Tensor channel_weight, Tensor channel_bias) -> Tensor");
  m.def("mlca_bwd(Tensor grad_out, Tensor encoded, Tensor lift, Tensor token_weight, Tensor token_bias, Tensor channel_weight, Tensor channel_bias, bool input_grad) -> (Tensor?, Tensor, Tensor, Tensor, Tensor, Tensor)");
}

// The ahead-of-time build imports this library as the Python module mixer_nerf._C; the JIT
// build loads it with torch.ops.load_library. Either way only the registrations above matter.
#define MIXER_NERF_CONCAT_(a, b) a##b
#define MIXER_NERF_CONCAT(a, b) MIXER_NERF_CONCAT_(a, b)
extern "C" PyObject* MIXER_NERF_CONCAT(PyInit_, TORCH_EXTENSION_NAME)(void) {
  static PyModuleDef module = {};
  module.m_base = PyModuleDef_HEAD_INIT;
  module.m_name = "_C";
  module.m_doc = "mixer_nerf kernels; the ops live in torch.ops.mixer_nerf";
  module.m_size = -1;
  return PyModule_Create(&module);
}
