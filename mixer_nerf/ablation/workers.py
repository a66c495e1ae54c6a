"""An ablation spread over several GPUs: one worker process per GPU, each training its share of
the runs into the shared folder (the plan, records and checkpoints are written atomically)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable, Sequence

from .plan import AblationError, AblationPlan
from .runner import RUN_RECORD

Run = tuple[str, int]


def parse_gpus(text: str) -> tuple[int, ...]:
    """"0,1" -> (0, 1): CUDA device indices, each given once."""
    try:
        gpus = tuple(dict.fromkeys(int(p) for p in text.replace(" ", ",").split(",") if p))
    except ValueError:
        gpus = ()
    if not gpus or min(gpus) < 0:
        raise AblationError(f"--gpus takes device indices separated by commas, e.g. 0,1; got {text!r}")
    return gpus


def format_runs(runs: Sequence[Run]) -> str:
    return ",".join(f"{preset}:{seed}" for preset, seed in runs)


def parse_runs(text: str, plan: AblationPlan) -> list[Run]:
    """"A:0,D:1" -> [("A", 0), ("D", 1)], each a run of ``plan``."""
    runs = []
    for item in filter(None, text.split(",")):
        preset, _, seed = item.partition(":")
        run = (preset.strip().upper(), int(seed)) if seed.strip().lstrip("-").isdigit() else None
        if run not in plan.runs():
            raise AblationError(f"--runs: {item!r} is not a run of this ablation "
                                "(PRESET:SEED of --presets and --seeds)")
        runs.append(run)
    return runs


def train_on_gpus(plan: AblationPlan, argv: Sequence[str], gpus: Sequence[int],
                  log: Callable[[str], None] = print) -> None:
    """Train ``plan``'s runs in one ``mixer-nerf ablate`` process per GPU of ``gpus`` (``argv``: the
    command's own arguments without ``--gpus``): the i-th run not yet done on GPU i mod len(gpus),
    so that a resumed ablation keeps every GPU busy; each process sees only its GPU and appends to
    ``<out>/worker_gpu<N>.log``. Waits for all of them.

    Raises:
        AblationError: a worker failed (naming its log).
    """
    workers = []
    # `timeout` (a GPU call's limit) sends SIGTERM: end as on Ctrl-C, so the workers stop with us.
    previous = signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    left = [run for run in plan.runs() if not (plan.run_folder(*run) / RUN_RECORD).is_file()]
    try:
        for index, gpu in enumerate(gpus):
            share = left[index :: len(gpus)]
            if not share:
                continue
            log_path = plan.out / f"worker_gpu{gpu}.log"
            command = [sys.executable, "-m", "mixer_nerf", *argv, "--resume", "--no-progress",
                       "--runs", format_runs(share)]
            with open(log_path, "a") as log_file:  # a resumed ablation's workers add to their logs
                process = subprocess.Popen(command, env={**os.environ, "CUDA_VISIBLE_DEVICES": str(gpu)},
                                           stdout=log_file, stderr=subprocess.STDOUT)
            workers.append((gpu, process, log_path))
            log(f"GPU {gpu}: runs {format_runs(share)}, log {log_path}")
        codes = [(gpu, process.wait(), path) for gpu, process, path in workers]
    finally:
        signal.signal(signal.SIGTERM, previous)
        for _, process, _ in workers:  # interrupted: no orphan keeps training
            if process.poll() is None:
                process.terminate()
                process.wait()
    failed = [(gpu, code, path) for gpu, code, path in codes if code != 0]
    if failed:
        gpu, code, path = failed[0]
        raise AblationError(f"the worker on GPU {gpu} failed (exit {code}); see {path}")
