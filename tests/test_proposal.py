"""Tests of the proposal sampler: options, sampling, the interval-overlap loss, scene contraction,
and that trained proposal networks put the main field's samples where the surface is."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from mixer_nerf.model.contraction import contract
from mixer_nerf.model.proposal_network import ProposalNetwork
from mixer_nerf.render.skipping import (
    ProposalOptions,
    ProposalSampler,
    proposal_loss,
    proposal_update_due,
    render_rays_proposal,
)
from mixer_nerf.render.skipping.proposal import ProposalRound


def rays(n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    o = torch.zeros(n, 3)
    o[:, :2] = torch.rand(n, 2, generator=gen) * 0.2 - 0.1
    d = torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1)
    return o, d


def sampler(rounds=(16, 8), samples=6, spacing="linear", intervals="drawn") -> ProposalSampler:
    nets = [ProposalNetwork(num_freqs=2, width=16) for _ in rounds]
    return ProposalSampler(nets, ProposalOptions(rounds, samples, spacing, intervals=intervals))


@pytest.mark.parametrize("kwargs, match", [
    ({"samples_per_round": ()}, "samples_per_round"), ({"samples_per_round": (4, 0)}, "samples_per_round"),
    ({"num_samples": 0}, "num_samples"), ({"spacing": "log"}, "spacing"), ({"weight_padding": -1.0}, "padding"),
    ({"jitter": "per_bin"}, "jitter"), ({"residual": "far"}, "residual"), ({"intervals": "mid"}, "intervals")])
def test_options_reject_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ProposalOptions(**kwargs)


def test_one_network_per_round():
    with pytest.raises(ValueError, match="1 proposal networks for 2 rounds"):
        ProposalSampler([ProposalNetwork()], ProposalOptions((8, 4)))


@pytest.mark.parametrize("intervals", ["drawn", "between"])
@pytest.mark.parametrize("spacing, near, far", [("linear", 0.0, 1.0), ("disparity", 0.5, 50.0)])
@pytest.mark.parametrize("stratified", [False, True])
def test_samples_are_sorted_contiguous_intervals_inside_near_far(spacing, near, far, stratified, intervals):
    gen = torch.Generator().manual_seed(0)
    o, d = rays(32, gen)
    prop = sampler(spacing=spacing, intervals=intervals)
    s = prop.sample(o, d, near, far, stratified=stratified, generator=gen)
    assert s.t_starts.shape == (32, 6) and s.edges.shape == (32, 7)
    assert (s.t_ends >= s.t_starts).all() and torch.equal(s.t_starts[:, 1:], s.t_ends[:, :-1])
    assert (s.t_starts >= near - 1e-6).all() and (s.t_ends <= far * (1 + 1e-5)).all()
    assert [r.weights.shape for r in s.rounds] == [(32, 16), (32, 8)]
    assert all(torch.isfinite(r.weights).all() for r in s.rounds)


def test_per_ray_jitter_spaces_a_rays_positions_equally_with_its_own_offset():
    """With uniform weights the resampled edges are the positions u themselves: per ray, equal steps
    of 1 / count from one random offset; per sample, steps that vary."""
    gen = torch.Generator().manual_seed(0)
    edges = torch.linspace(0, 1, 9).repeat(64, 1)
    weights = torch.ones(64, 8)
    spaced = {}
    for jitter in ("per_ray", "per_sample"):
        s = ProposalSampler([ProposalNetwork(num_freqs=2, width=8)], ProposalOptions((8,), 4, jitter=jitter))
        spaced[jitter] = s._resample(edges, weights, 17, True, gen, "torch")
    steps = spaced["per_ray"].diff(dim=-1)
    torch.testing.assert_close(steps, torch.full_like(steps, 1 / 17))
    assert spaced["per_ray"][:, 0].std() > 0.01  # an offset of each ray's own
    assert spaced["per_sample"].diff(dim=-1).std() > 0.01


def test_proposal_updates_ramp_from_every_step_to_every_nth():
    assert all(proposal_update_due(step, 1) for step in range(3000))
    due = [step for step in range(2000) if proposal_update_due(step, 6)]
    assert due[:3] == [0, 1, 2]  # every step at first
    late = [step for step in due if step >= 1000]
    assert late == list(range(1002, 2000, 6))
    ramp = [step for step in due if step < 1000]
    assert 200 < len(ramp) < 1000  # the interval grows over the ramp


def test_sample_rejects_a_disparity_spacing_from_zero_and_infinite_far():
    o, d = rays(4, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="near > 0"):
        sampler(spacing="disparity").sample(o, d, 0.0, 1.0, stratified=False)
    with pytest.raises(ValueError, match="far < inf"):
        sampler().sample(o, d, 0.0, float("inf"), stratified=False)


def test_loss_is_zero_when_each_round_bounds_the_weights_and_reaches_only_the_proposals():
    edges = torch.linspace(0, 1, 9).expand(3, 9)
    w = torch.rand(3, 8)
    w = w / w.sum(-1, keepdim=True)
    bounding = ProposalRound(edges, w.clone().requires_grad_())
    assert proposal_loss([bounding], edges, w).item() == pytest.approx(0.0, abs=1e-7)
    short = ProposalRound(edges, (0.5 * w).requires_grad_())
    main = w.clone().requires_grad_()
    loss = proposal_loss([short], edges, main)
    loss.backward()
    assert loss.item() > 0 and short.weights.grad.abs().sum() > 0 and main.grad is None


class Transparent(nn.Module):
    """A proposal network that sees nothing on any ray."""

    def density(self, x: torch.Tensor) -> torch.Tensor:
        return x.new_zeros(x.shape[:-1])


def test_residual_last_gives_the_remaining_transmittance_to_the_last_interval_with_gradient():
    w = (torch.rand(5, 7) / 10).requires_grad_()
    kept = ProposalSampler([Transparent()], ProposalOptions((4,), 6, residual="last")).target_weights(w)
    torch.testing.assert_close(kept.sum(-1), torch.ones(5))
    torch.testing.assert_close(kept[:, :-1], w[:, :-1])
    kept[:, -1].sum().backward()  # the last weight is 1 - (the others' sum)
    torch.testing.assert_close(w.grad, torch.cat([-torch.ones(5, 6), torch.zeros(5, 1)], -1))
    assert ProposalSampler([Transparent()], ProposalOptions((4,), 6)).target_weights(w) is w


def test_a_ray_the_proposals_see_as_transparent_is_sampled_along_it_or_at_its_far_end():
    """Nothing seen: dropping the residual leaves each round's PDF uniform (samples spread along
    the ray); giving it to the last interval puts every sample in the last quarter of the ray,
    as nerfacc's estimator does."""
    gen = torch.Generator().manual_seed(0)
    o, d = rays(64, gen)

    def far_share(residual: str) -> float:
        prop = ProposalSampler([Transparent(), Transparent()], ProposalOptions((8, 4), 8, residual=residual))
        s = prop.sample(o, d, 2.0, 6.0, stratified=True, generator=gen)
        return (0.5 * (s.t_starts + s.t_ends) >= 5.0).float().mean().item()

    assert far_share("drop") < 0.3 and far_share("last") == 1.0


@pytest.mark.parametrize("n", [1, 2, 5])
def test_intervals_between_drawn_positions_reach_both_ends_of_a_uniform_pdf(n):
    """Deterministic positions (i + 1/2) / n of a uniform PDF on [0.2, 0.6]: edges halfway between
    them and half a spacing beyond, i.e. the n + 1 quantiles i / n, ends included."""
    prop = ProposalSampler([Transparent()], ProposalOptions((4,), n, intervals="between"))
    edges = torch.tensor([[0.2, 0.3, 0.6]])
    got = prop._intervals(edges, torch.tensor([[1.0, 3.0]]), n, False, None, "auto")
    torch.testing.assert_close(got, torch.linspace(0.2, 0.6, n + 1)[None])
    drawn = ProposalSampler([Transparent()], ProposalOptions((4,), n))._intervals(
        edges, torch.tensor([[1.0, 3.0]]), n, False, None, "auto")
    assert drawn[0, 0] > 0.2 and drawn[0, -1] < 0.6  # drawn edges stop short of the ends


def test_intervals_between_stay_inside_the_previous_span_when_positions_crowd_an_end():
    gen = torch.Generator().manual_seed(0)
    prop = ProposalSampler([Transparent()], ProposalOptions((4,), 8, intervals="between"))
    edges = torch.tensor([[0.0, 0.01, 1.0]]).repeat(64, 1)
    weights = torch.tensor([[1.0, 1e-6]]).repeat(64, 1)  # nearly all mass in the first 1% of the span
    got = prop._intervals(edges, weights, 8, True, gen, "auto")
    assert got.shape == (64, 9) and (got[:, 0] >= 0).all() and (got[:, -1] <= 1).all()
    assert (got[:, 1:] >= got[:, :-1]).all()


def test_a_coarse_round_bounds_fine_intervals_by_the_weight_of_those_it_overlaps():
    coarse = torch.tensor([[0.0, 0.5, 1.0]])
    fine = torch.tensor([[0.0, 0.25, 0.5, 0.75, 1.0]])
    w_fine = torch.tensor([[0.1, 0.2, 0.3, 0.4]])
    # Each fine interval lies inside one coarse one: bounded exactly by 0.3 and 0.7.
    ok = ProposalRound(coarse, torch.tensor([[0.3, 0.7]]))
    assert proposal_loss([ok], fine, w_fine).item() == pytest.approx(0.0, abs=1e-7)
    low = ProposalRound(coarse, torch.tensor([[0.3, 0.35]]))  # the second half falls short
    expected = (0.4 - 0.35) ** 2 / 0.4  # only the last fine interval outweighs its coarse bound
    assert proposal_loss([low], fine, w_fine).item() == pytest.approx(expected, rel=1e-5)


def test_contraction_keeps_the_unit_ball_and_squeezes_the_rest_inside_radius_two():
    x = torch.randn(1000, 3, dtype=torch.float64) * torch.logspace(-2, 8, 1000, dtype=torch.float64)[:, None]
    y = contract(x)
    inside = x.norm(dim=-1) <= 1
    assert torch.equal(y[inside], x[inside]) and (y.norm(dim=-1) < 2).all() and torch.isfinite(y).all()
    # continuous with its gradient at |x| = 1
    u = torch.tensor([[0.6, 0.8, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(contract(u * (1 + 1e-9)), u, atol=1e-8, rtol=0)
    assert torch.autograd.gradcheck(contract, (torch.tensor([[1.5, -2.0, 0.3]], dtype=torch.float64,
                                                            requires_grad=True),))


def test_trained_proposals_put_the_main_samples_on_the_surface():
    """A wall at t = 0.6: after fitting the proposals to the wall's weights, most of the main
    field's samples lie within 0.1 of it (uniform sampling would put 20% there)."""
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)

    class Wall(nn.Module):
        def forward(self, x, d):
            sigma = 200.0 * ((x[..., 2] - 0.6).abs() < 0.02).float()
            return sigma, torch.full_like(x, 0.5)

    prop = ProposalSampler([ProposalNetwork(num_freqs=6, width=32) for _ in range(2)],
                           ProposalOptions((32, 16), 8))
    opt = torch.optim.Adam(prop.parameters(), lr=1e-2)
    for _ in range(150):
        o, d = rays(64, gen)
        out, samples = render_rays_proposal(Wall(), prop, o, d, 0.0, 1.0, generator=gen, backend="torch")
        loss = proposal_loss(samples.rounds, samples.edges, out.weights)
        opt.zero_grad()
        loss.backward()
        opt.step()
    o, d = rays(64, gen)
    _, samples = render_rays_proposal(Wall(), prop, o, d, 0.0, 1.0, stratified=False, backend="torch")
    mids = 0.5 * (samples.t_starts + samples.t_ends)
    assert ((mids - 0.6).abs() < 0.1).float().mean() > 0.6
