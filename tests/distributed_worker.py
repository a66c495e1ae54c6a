"""Run by tests/test_distributed.py under torchrun: trains (or resumes) the run a JSON TrainConfig
file describes, rank ``--fail-rank`` raising just before step ``--fail-step`` and rank 0 seeing a
loss spike at step ``--spike-step``, then saves this rank's final fields (weights and occupancy
grid), its spike rollbacks and a probe of the gradient mean to ``rank<r>.pt`` in the run folder."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from mixer_nerf.train import TrainConfig, Trainer


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("config")
    parser.add_argument("--resume", action="store_true")
    parser.add_argument("--fail-rank", type=int, default=-1)
    parser.add_argument("--fail-step", type=int, default=0)
    parser.add_argument("--spike-step", type=int, default=0)
    args = parser.parse_args()
    cfg = TrainConfig(**json.loads(Path(args.config).read_text()))
    trainer = Trainer(cfg, resume=args.resume)
    if trainer.rank == args.fail_rank:
        step = trainer.train_step

        def failing_step():
            if trainer.step + 1 == args.fail_step:
                raise RuntimeError(f"injected failure on rank {trainer.rank} at step {args.fail_step}")
            return step()

        trainer.train_step = failing_step
    if trainer.rank == 0 and args.spike_step:  # only rank 0 reads the loss
        observe = trainer.spikes.observe
        trainer.spikes.observe = lambda step, loss: (
            f"loss spike at step {step}: injected" if step == args.spike_step else observe(step, loss))
    trainer.fit()
    # The gradient mean on its own: rank r's gradient is r + 1; the second parameter has none on rank 0.
    device = trainer.device
    probe = [torch.zeros(n, device=device, requires_grad=True) for n in (3, 2)]
    probe[0].grad = torch.full((3,), trainer.rank + 1.0, device=device)
    if trainer.rank:
        probe[1].grad = torch.ones(2, device=device)
    trainer.ranks.start_gradient_mean(probe).finish()
    probed = [p.grad.cpu() for p in probe]
    torch.save({"step": trainer.step, "fields": trainer.fields.state_dict(), "probe": probed,
                "rollbacks": trainer.rollback.used},
               Path(cfg.out) / f"rank{trainer.rank}.pt")


if __name__ == "__main__":
    main()
