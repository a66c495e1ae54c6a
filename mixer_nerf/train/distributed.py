"""Training on several processes with ``torch.distributed``, launched by ``torchrun``.

One process per GPU (NCCL), or per CPU worker (gloo). Each rank draws its own rays; after each
backward pass the gradients are averaged with one flat all-reduce, started before the next batch
is prepared so that the two overlap; grid refreshes are split across ranks and max-reduced; every
decision that follows a clock is rank 0's, broadcast over a host-side gloo group so that the GPU
never waits for it. One process without torchrun's variables gets ``None`` from :func:`join` and
trains exactly as before (docs/distributed.md).
"""

from __future__ import annotations

import atexit
import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist

from ..render.skipping import CellShare

NO_MULTICAST = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}
"""NVLink multicast off: on shared hosts it can put every GPU out of service (docs/distributed.md)."""


class DistributedError(RuntimeError):
    """The training processes cannot work together: torchrun's layout does not fit this machine
    (more ranks than GPUs), or another process stopped during a collective."""


def launched_ranks() -> int:
    """WORLD_SIZE as torchrun sets it (1 when not launched by torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def rank_seed(seed: int, rank: int, step: int = 0) -> int:
    """The ray-sampling seed of ``rank`` starting at ``step``: ``seed`` itself for rank 0 at step
    0 (one process draws as it always did), else an independent stream from numpy's SeedSequence."""
    if rank == 0 and step == 0:
        return seed
    return int(np.random.SeedSequence(seed, spawn_key=(rank, step)).generate_state(1, np.uint64)[0] >> 1)


def restore_rank_sampler(generator: torch.Generator, saved: list[torch.Tensor], rank: int, seed: int,
                         step: int) -> None:
    """Give ``rank`` (> 0) its own ray stream back from a checkpoint's ``rank_samplers``, or a
    fresh one when the run that saved it had fewer ranks."""
    if rank < len(saved):
        generator.set_state(saved[rank])
    else:
        generator.manual_seed(rank_seed(seed, rank, step))


@dataclass
class Ranks:
    """This process's place among ``world_size`` training processes (see :func:`join`)."""

    rank: int
    world_size: int
    decisions: dist.ProcessGroup  # gloo: host-side values, no GPU synchronisation

    def decide(self, value: float) -> float:
        """Rank 0's ``value`` on every rank (e.g. its training clock)."""
        t = torch.tensor([value], dtype=torch.float64)
        with collective("a broadcast of rank 0's clock"):
            dist.broadcast(t, src=0, group=self.decisions)
        return float(t)

    def gather_objects(self, value: object) -> list[object]:
        """Every rank's ``value``, in rank order, on every rank (host-side)."""
        values: list[object] = [None] * self.world_size
        with collective("a gather of the ranks' random states"):
            dist.all_gather_object(values, value, group=self.decisions)
        return values

    def start_gradient_mean(self, params: list[torch.Tensor]) -> GradientMean:
        """Start averaging the gradients of ``params`` over the ranks; a parameter without a
        gradient on a rank counts as a zero gradient there. Call ``finish()`` before stepping."""
        grads = [torch.zeros_like(p) if p.grad is None else p.grad for p in params]
        flat = torch.cat([g.reshape(-1) for g in grads])
        return GradientMean(params, flat, dist.all_reduce(flat, async_op=True), self.world_size)

    def cell_share(self) -> CellShare:
        """This rank's share of an occupancy-grid refresh, max-reduced over the ranks."""
        return CellShare(self.rank, self.world_size, _max_reduce)


@dataclass
class GradientMean:
    """An all-reduce of flattened gradients in flight (see :meth:`Ranks.start_gradient_mean`)."""

    params: list[torch.Tensor]
    flat: torch.Tensor
    work: dist.Work
    world_size: int

    def finish(self) -> None:
        """Wait for the sum and give every parameter its mean gradient."""
        with collective("the gradient all-reduce"):
            self.work.wait()
        self.flat.div_(self.world_size)
        offset = 0
        for p in self.params:
            n = p.numel()
            p.grad = self.flat[offset : offset + n].view_as(p)
            offset += n


def join(device: str) -> Ranks | None:
    """Join the process group torchrun's variables describe (None: one process, nothing to join).

    On CUDA each rank takes GPU ``LOCAL_RANK`` and talks NCCL; on CPU, gloo. Call it before
    anything is put on the device.

    Raises:
        DistributedError: naming what is wrong, before any collective (too few GPUs).
    """
    world_size = launched_ranks()
    if world_size == 1:
        return None
    for name, value in NO_MULTICAST.items():
        os.environ.setdefault(name, value)
    gpu = None
    if device.startswith("cuda"):
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        if local_rank >= torch.cuda.device_count():
            raise DistributedError(
                f"rank {os.environ.get('RANK')} wants GPU {local_rank} but this machine has "
                f"{torch.cuda.device_count()}; launch at most that many processes per node"
            )
        gpu = torch.device("cuda", local_rank)
        torch.cuda.set_device(gpu)
    if not dist.is_initialized():
        dist.init_process_group("gloo" if gpu is None else "nccl", device_id=gpu)
        atexit.register(_leave)
    decisions = dist.group.WORLD if gpu is None else dist.new_group(backend="gloo")
    return Ranks(dist.get_rank(), dist.get_world_size(), decisions)


@contextlib.contextmanager
def collective(what: str) -> Iterator[None]:
    """Turn the backend's error when another rank has died during ``what`` into one clear line."""
    try:
        yield
    except RuntimeError as e:  # gloo and NCCL raise RuntimeError subclasses with pages of advice
        raise DistributedError(
            f"{what} failed: another training process stopped (its own error says why)"
        ) from e


def _max_reduce(t: torch.Tensor) -> None:
    with collective("the occupancy-grid max-reduce"):
        dist.all_reduce(t, op=dist.ReduceOp.MAX)


def leave() -> None:
    """Leave the process group together, once training is over: a barrier, then the group's
    teardown on every rank. A rank that exited while another still used the group (rank 0
    evaluates after training) sometimes aborted in its exit ("terminate called without an active
    exception"). A no-op without a group."""
    if dist.is_initialized():
        with collective("leaving the process group"):
            dist.barrier()
        _leave()


def _leave() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()

