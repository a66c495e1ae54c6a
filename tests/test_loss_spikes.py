"""LossSpikeWatch: a note once per spike of the logged training loss, none on ordinary training;
SpikeRollback: back to the trained state from before a spike, bit for bit, in place."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from mixer_nerf.train.loss_spikes import LossSpikeWatch, SpikeRollback


def notes(losses, **kwargs) -> list[str]:
    watch = LossSpikeWatch(**kwargs)
    said = [watch.observe(100 * (i + 1), float(v)) for i, v in enumerate(losses)]
    return [n for n in said if n is not None]


def falling_loss(rng, n=400) -> np.ndarray:
    """A training loss: decaying, with the batch-to-batch noise of a logged single step."""
    return 0.03 * np.exp(-np.arange(n) / 60) + 0.002 * (1 + 0.15 * rng.standard_normal(n))


def test_ordinary_training_says_nothing():
    rng = np.random.default_rng()
    assert notes(falling_loss(rng)) == []
    # a flat loss with falling_loss's noise: at 20% a 2x ratio to the median of 10 came up in
    # 1.8% of runs, at 15% in none of 4000
    assert notes(0.002 * (1 + 0.15 * rng.standard_normal(500))) == []


def test_a_spike_is_said_once_with_its_step_and_ratio():
    rng = np.random.default_rng()
    loss = falling_loss(rng)
    loss[250:254] = 3 * loss[240:250].mean()  # four logs up, as A's spike on Fern
    said = notes(loss)
    assert len(said) == 1 and said[0].startswith("loss spike at step 25100: ")
    assert re.search(r" [23]\.\dx the median of the 10 losses logged before", said[0]), said[0]


def test_each_separate_spike_is_said():
    loss = np.full(100, 0.002)
    loss[[30, 31, 70]] = 0.01
    assert [n.split(":")[0] for n in notes(loss)] == ["loss spike at step 3100", "loss spike at step 7100"]


def test_zero_and_non_finite_losses_say_nothing_and_raise_nothing():
    assert notes([0.0] * 10 + [0.01]) == []
    assert notes([0.002] * 10 + [float("nan"), float("inf"), 0.002]) == []
    assert len(notes([0.002] * 5 + [float("nan")] + [0.002] * 5 + [0.01])) == 1  # the window skips it


def test_nothing_is_said_before_the_window_is_full():
    assert notes([0.001, 0.01, 0.1], window=3) == []
    assert len(notes([0.001, 0.001, 0.001, 0.01], window=3)) == 1


@pytest.mark.parametrize("kwargs", [{"ratio": 1.0}, {"ratio": 0.5}, {"window": 0}])
def test_bad_settings_are_refused(kwargs):
    with pytest.raises(ValueError, match="ratio"):
        LossSpikeWatch(**kwargs)


def adam_run(steps: int):
    """Two parameters of an Adam optimiser after ``steps`` random steps (state made), and a step."""
    gen = torch.Generator().manual_seed(int(np.random.default_rng().integers(2**31)))
    params = [torch.randn(5, 3, generator=gen, requires_grad=True), torch.randn(4, generator=gen, requires_grad=True)]
    optimizer = torch.optim.Adam(params, lr=1e-2)

    def step():
        optimizer.zero_grad()
        sum((p * torch.randn(p.shape, generator=gen)).sum() for p in params).backward()
        optimizer.step()

    for _ in range(steps):
        step()
    return params, optimizer, step


def state_of(params, optimizer) -> list[torch.Tensor]:
    return [p.detach().clone() for p in params] + [
        v.clone() for p in params for v in optimizer.state[p].values() if isinstance(v, torch.Tensor)]


def assert_state(params, optimizer, expected) -> None:
    for got, want in zip(state_of(params, optimizer), expected, strict=True):
        assert torch.equal(got, want)


def test_a_rollback_writes_back_the_older_of_the_last_two_copies_in_place():
    params, optimizer, step = adam_run(3)
    rollback = SpikeRollback(params, optimizer, limit=2)
    memory = [t.data_ptr() for t in rollback._tensors()]
    rollback.keep(100)
    for kept in (200, 300):
        step()
        rollback.keep(kept)  # the copy of 100 leaves the window: the one of 200 is the older
    step()
    assert rollback.restore() == 200
    assert [t.data_ptr() for t in rollback._tensors()] == memory  # in place, as a CUDA graph replays it
    assert rollback.used == 1 and rollback.left == 1


def test_restored_parameters_and_optimiser_state_equal_the_copy_bit_for_bit():
    params, optimizer, step = adam_run(4)
    rollback = SpikeRollback(params, optimizer, limit=1)
    rollback.keep(1)
    expected = state_of(params, optimizer)
    step()
    rollback.keep(2)  # the newer copy: forgotten by the restore
    for _ in range(3):
        step()
    assert rollback.restore() == 1
    assert_state(params, optimizer, expected)
    step()  # training goes on from there
    assert rollback.restore() is None  # limit reached
    assert rollback.used == 1


def test_after_a_rollback_the_restored_copy_stays_the_one_to_go_back_to():
    params, optimizer, step = adam_run(2)
    rollback = SpikeRollback(params, optimizer, limit=3)
    rollback.keep(10)
    expected = state_of(params, optimizer)
    step()
    rollback.keep(20)
    step()
    assert rollback.restore() == 10
    step()
    assert rollback.restore() == 10  # a second spike before two new copies: back to the same state
    assert_state(params, optimizer, expected)
    step()
    rollback.keep(30)
    step()
    rollback.keep(40)
    assert rollback.restore() == 30


def test_no_copy_and_no_limit_mean_no_rollback():
    params, optimizer, step = adam_run(1)
    assert SpikeRollback(params, optimizer, limit=2).restore() is None
    off = SpikeRollback(params, optimizer, limit=0)
    off.keep(1)  # keeps nothing: a run with rollbacks off pays no copies
    assert not off._copies and off.restore() is None
    with pytest.raises(ValueError, match="spike_rollbacks must be >= 0"):
        SpikeRollback(params, optimizer, limit=-1)


def test_a_copy_leaving_the_window_lends_its_buffers():
    params, optimizer, step = adam_run(1)
    rollback = SpikeRollback(params, optimizer, limit=1)
    rollback.keep(1)
    first = rollback._copies[0][2]
    step()
    rollback.keep(2)
    step()
    rollback.keep(3)
    assert all(a is b for a, b in zip(rollback._copies[-1][2], first))
    assert rollback._copies[0][0] == 2
