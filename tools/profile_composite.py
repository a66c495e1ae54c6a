"""Run the composite kernels at the benchmark size for a profiler (e.g. Nsight Compute):

    ncu --set full --import-source no --kernel-name regex:composite --launch-skip 4 --launch-count 2 \
        python tools/profile_composite.py

Three forward+backward calls of ``composite`` at R=65536, S=192, C=3 float32 (the ``bench_ops``
case); skipping four launches profiles the third call's forward and backward kernels.
"""

import torch

from benchmarks.cases_composite import make_inputs
from mixer_nerf.ops.composite import composite

inputs = make_inputs(65536, 192, torch.device("cuda"))
sigmas, rgbs = inputs["sigmas"].requires_grad_(), inputs["rgbs"].requires_grad_()
for _ in range(3):
    color, depth, opacity, _ = composite(sigmas, rgbs, inputs["t_starts"], inputs["t_ends"], inputs["background"])
    (color.sum() + depth.sum() + opacity.sum()).backward()
torch.cuda.synchronize()
print("composite ran 3 x forward+backward")
