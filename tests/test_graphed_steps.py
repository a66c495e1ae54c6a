"""GraphedSteps: training steps of two kinds replayed as CUDA graphs, against the same steps run
eagerly (the trainer's use of it: tests/test_train.py)."""

from __future__ import annotations

import pytest
import torch

from mixer_nerf.train.graphed_steps import GraphedSteps

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")


def test_a_generator_off_the_gpu_is_refused():
    with pytest.raises(ValueError, match="CUDA generator"):
        GraphedSteps(lambda kind: {}, [], torch.Generator())


class Toy:
    """A linear model trained on random inputs from its own generator; ``kind`` scales the loss."""

    def __init__(self) -> None:
        torch.manual_seed(0)
        self.net = torch.nn.Linear(4, 1).cuda()
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=torch.tensor(0.01, device="cuda"),
                                          fused=True, capturable=True)
        self.generator = torch.Generator(device="cuda").manual_seed(1)

    def step(self, kind: bool) -> dict[str, torch.Tensor]:
        x = torch.randn(64, 4, device="cuda", generator=self.generator)
        loss = (self.net(x) * (2.0 if kind else 1.0)).square().mean()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return {"loss": loss.detach()}


@pytest.mark.cuda
@cuda
def test_replays_of_two_kinds_draw_and_learn_as_eager_steps():
    eager, graphed = Toy(), Toy()
    steps = GraphedSteps(graphed.step, list(graphed.net.parameters()), graphed.generator)
    for kind in (True, False, True, True, False, False, True):
        expected = eager.step(kind)["loss"].item()
        assert steps(kind)["loss"].item() == pytest.approx(expected, rel=1e-5)
    assert set(steps.captured) == {True, False}
    for p, q in zip(eager.net.parameters(), graphed.net.parameters(), strict=True):
        torch.testing.assert_close(q, p)
        torch.testing.assert_close(q.grad, p.grad)  # the last step's gradient, whichever graph made it
