"""Run one op's kernels at its benchmark size for a profiler (e.g. Nsight Compute):

    ncu --set full --import-source no --kernel-name "regex:$(python tools/profile_op.py --kernel CASE)" \
        --launch-skip 4 --launch-count 2 python tools/profile_op.py CASE

Skipping four launches of the case's kernels then profiles two: of composite's three forward+backward
calls the third one's forward and backward, of the forward-only op's six calls the last two:
  composite             ``composite`` at R=65536, S=192, C=3 float32 (the ``bench_ops`` case)
  composite_packed      ``composite_packed`` on its ``bench_ops`` case (0..64 samples per ray)
  hierarchical_samples  the default call at R=65536, S=64, N=128 (stratified positions drawn)
"""

import argparse

import torch

from benchmarks import cases_composite, cases_sample_pdf
from mixer_nerf.ops.composite import composite, composite_packed
from mixer_nerf.ops.hierarchical_samples import hierarchical_samples

KERNELS = {"composite": "composite", "composite_packed": "composite",
           "hierarchical_samples": "sample_forward"}
"""Each case's kernel-name pattern for ncu's ``--kernel-name regex:``."""


def run_composite(packed: bool, device: torch.device) -> None:
    if packed:
        inputs = cases_composite.make_packed_inputs(65536, device)
        op, extra = composite_packed, (inputs["offsets"], inputs["background"])
    else:
        inputs = cases_composite.make_inputs(65536, 192, device)
        op, extra = composite, (inputs["background"],)
    sigmas, rgbs = inputs["sigmas"].requires_grad_(), inputs["rgbs"].requires_grad_()
    for _ in range(3):
        color, depth, opacity, _ = op(sigmas, rgbs, inputs["t_starts"], inputs["t_ends"], *extra)
        (color.sum() + depth.sum() + opacity.sum()).backward()


def run_hierarchical(device: torch.device) -> None:
    inputs = cases_sample_pdf.make_inputs(65536, device)
    for _ in range(6):
        hierarchical_samples(inputs["z"], inputs["weights"], cases_sample_pdf.FINE)


parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("case", nargs="?", choices=sorted(KERNELS), default="composite")
parser.add_argument("--kernel", choices=sorted(KERNELS),
                    help="print this case's kernel-name pattern and exit")
args = parser.parse_args()
if args.kernel:
    print(KERNELS[args.kernel])
    raise SystemExit
device = torch.device("cuda")
if args.case == "hierarchical_samples":
    run_hierarchical(device)
else:
    run_composite(args.case == "composite_packed", device)
torch.cuda.synchronize()
print(f"{args.case}: done")
