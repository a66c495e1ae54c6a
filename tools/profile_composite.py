"""Run the composite kernels at the benchmark sizes for a profiler (e.g. Nsight Compute):

    ncu --set full --import-source no --kernel-name regex:composite --launch-skip 4 --launch-count 2 \
        python tools/profile_composite.py [--packed]

Three forward+backward calls of ``composite`` at R=65536, S=192, C=3 float32 (the ``bench_ops``
case), or with ``--packed`` of ``composite_packed`` on its ``bench_ops`` case (0..64 samples per
ray); skipping four launches profiles the third call's forward and backward kernels.
"""

import argparse

import torch

from benchmarks.cases_composite import make_inputs, make_packed_inputs
from mixer_nerf.ops.composite import composite, composite_packed

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--packed", action="store_true", help="composite_packed on the packed case")
args = parser.parse_args()
device = torch.device("cuda")
if args.packed:
    inputs = make_packed_inputs(65536, device)
    extra = (inputs["offsets"], inputs["background"])
    op = composite_packed
else:
    inputs = make_inputs(65536, 192, device)
    extra = (inputs["background"],)
    op = composite
sigmas, rgbs = inputs["sigmas"].requires_grad_(), inputs["rgbs"].requires_grad_()
for _ in range(3):
    color, depth, opacity, _ = op(sigmas, rgbs, inputs["t_starts"], inputs["t_ends"], *extra)
    (color.sum() + depth.sum() + opacity.sum()).backward()
torch.cuda.synchronize()
print(f"{op.__name__} ran 3 x forward+backward")
