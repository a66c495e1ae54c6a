"""LossSpikeWatch: a note once per spike of the logged training loss, none on ordinary training."""

from __future__ import annotations

import re

import numpy as np
import pytest

from mixer_nerf.train.loss_spikes import LossSpikeWatch


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
    assert notes(0.002 * (1 + 0.2 * rng.standard_normal(500))) == []


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

