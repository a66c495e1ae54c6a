"""Run by tests/test_distributed.py under torchrun: trains (or resumes) the run a JSON TrainConfig
file describes, rank ``--fail-rank`` raising just before step ``--fail-step``, then saves this
rank's final fields (weights and occupancy grid) to ``rank<r>.pt`` in the run folder."""

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
    trainer.fit()
    torch.save({"step": trainer.step, "fields": trainer.fields.state_dict()},
               Path(cfg.out) / f"rank{trainer.rank}.pt")


if __name__ == "__main__":
    main()
