r"""The measurement noise scale of every agent estimated from its links'
innovations (NoiseAdaptation): its statistic against plain float64 loops,
its fading sums, and a filter given noise 3 times too small (in standard
deviation) made consistent while a correct model is left alone."""
import math

import pytest
import torch

from tg_nebp.filters import GaussianBP, NoiseAdaptation
from tg_nebp.metrics import nees
from tg_nebp.models import GaussianRange, NLOSRange, StudentTRange
from tg_nebp.nn.conv import GaussianBelief

from helpers import gen, linear_offset_model, tiny_scenario


def _beliefs(generator, num_nodes, size=4):
    mean = torch.randn(num_nodes, size, generator=generator,
                       dtype=torch.float64) * 5
    root = torch.randn(num_nodes, size, size, generator=generator,
                       dtype=torch.float64)
    cov = root @ root.transpose(-1, -2) * 0.1 + 0.05 * torch.eye(
        size, dtype=torch.float64)
    return mean, cov


def test_range_statistic_is_the_normalized_innovation_less_the_spread():
    # for a Gaussian range, e = ((z - d)^2 - q) / sigma^2 and rho = sigma^2
    # / (sigma^2 + q), q the variance of the predicted distance along the
    # link from both ends' position covariances (an anchor's is zero):
    # written here link by link from that formula, not from the code's
    # score and pseudo-inverse
    g = gen(0)
    num_nodes = 6
    mean, cov = _beliefs(g, num_nodes)
    anchor = torch.tensor([True, False, False, True, False, False])
    edge_index = torch.tensor([[0, 2, 1, 3, 4, 5, 1], [1, 1, 2, 4, 5, 4, 5]])
    z = torch.rand(edge_index.size(1), 1, generator=g,
                   dtype=torch.float64) * 10
    model = GaussianRange(sigma=0.7)
    belief = GaussianBelief(mean, torch.linalg.inv(cov))
    statistic, weight = NoiseAdaptation().statistics(
        model, belief, edge_index, z, anchor)
    var = model.sigma ** 2
    for k in range(edge_index.size(1)):
        j, i = edge_index[:, k].tolist()
        offset = (mean[j, :2] - mean[i, :2]).tolist()
        d = math.hypot(*offset)
        u = [c / d for c in offset]
        q = 0.0
        for node in (j, i):
            if not anchor[node]:
                q += sum(u[a] * float(cov[node, a, b]) * u[b]
                         for a in range(2) for b in range(2))
        residual = float(z[k, 0]) - d
        assert float(statistic[k]) == pytest.approx(
            (residual ** 2 - q) / var, rel=1e-9, abs=1e-9)
        assert float(weight[k]) == pytest.approx(var / (var + q), rel=1e-9)


def test_linear_statistic_is_the_normalized_innovation_less_the_spread():
    # a measurement of full rank 2 (the displacement): e = (|nu|^2 -
    # tr(P_j + P_i)) / (2 sigma^2) with the residual nu, rho = 2 / (2 +
    # tr(P_j + P_i) / sigma^2)
    g = gen(1)
    mean, cov = _beliefs(g, 4)
    anchor = torch.tensor([True, False, False, False])
    edge_index = torch.tensor([[0, 1, 3], [1, 2, 2]])
    model = linear_offset_model()(sigma=0.4)
    z = (mean[edge_index[0], :2] - mean[edge_index[1], :2] + model.OFFSET +
         torch.randn(3, 2, generator=g, dtype=torch.float64))
    statistic, weight = NoiseAdaptation().statistics(
        model, GaussianBelief(mean, torch.linalg.inv(cov)), edge_index, z,
        anchor)
    var = model.sigma ** 2
    for k in range(3):
        j, i = edge_index[:, k].tolist()
        residual = (z[k] - model.OFFSET - (mean[j, :2] - mean[i, :2]))
        spread = sum(float(cov[n, 0, 0] + cov[n, 1, 1]) for n in (j, i)
                     if not anchor[n])
        assert float(statistic[k]) == pytest.approx(
            (float(residual.square().sum()) - spread) / (2 * var), rel=1e-9)
        assert float(weight[k]) == pytest.approx(2 / (2 + spread / var),
                                                 rel=1e-9)


def test_scale_is_the_faded_weighted_mean_clipped_at_one():
    # the sums by plain loops: every link added at both of its ends (an
    # anchor's row keeps scale 1), the old sums faded by the memory
    g = gen(2)
    mean, cov = _beliefs(g, 5)
    anchor = torch.tensor([True, False, False, False, False])
    edge_index = torch.tensor([[0, 1, 2, 0, 3], [1, 2, 3, 4, 4]])
    z = torch.rand(5, 1, generator=g, dtype=torch.float64) * 20
    model = GaussianRange(sigma=0.5)
    belief = GaussianBelief(mean, torch.linalg.inv(cov))
    adaptation = NoiseAdaptation(memory=0.8, prior_count=2.0, max_scale=30.0)
    memory = adaptation.initial_memory(5)
    memory[:, 0] = torch.tensor([0.0, 3.0, -1.0, 40.0, 2.0])
    memory[:, 1] = torch.tensor([0.0, 1.0, 2.0, 1.0, 0.5])
    statistic, weight = adaptation.statistics(model, belief, edge_index, z,
                                              anchor)
    new = adaptation.updated(memory, model, belief, edge_index, z, anchor)
    for node in range(5):
        total = 0.8 * float(memory[node, 0])
        count = 0.8 * float(memory[node, 1])
        for k in range(5):
            if node in edge_index[:, k].tolist():
                total += float(weight[k] * statistic[k])
                count += float(weight[k])
        scale = (total + 2.0) / (count + 2.0)
        expected = 1.0 if anchor[node] else min(max(scale, 1.0), 30.0)
        assert float(new[node, 0]) == pytest.approx(total, rel=1e-12)
        assert float(new[node, 1]) == pytest.approx(count, rel=1e-12)
        assert float(new[node, 2]) == pytest.approx(expected, rel=1e-12)
    # the messages to a node are tempered by its scale: each message
    # edge's weight is 1 over its target's, whatever its source
    assert torch.equal(NoiseAdaptation.scale(new), new[:, 2])
    factors = GaussianBP().conv.factors(edge_index, anchor, 4)
    weights = NoiseAdaptation.message_weights(new, factors)
    for m, (source, target) in enumerate(factors.index.t().tolist()):
        assert float(weights[m]) == pytest.approx(1 / float(new[target, 2]),
                                                  rel=1e-12)
    assert len(set(factors.index[1].tolist())) > 1


def _track(tracker, graphs):
    # every agent's NEES and squared error of the steps from the tenth on,
    # and every agent's last noise scale
    scores, errors, scales = [], [], []
    for data in graphs:
        agents = ~data.anchor
        state = tracker.initial_state(data)
        for t, ((edges, attr), control) in enumerate(zip(
                data.edges_by_step(), tracker.controls_of(data))):
            out, state = tracker.step(state, edges, attr, data.anchor, t,
                                      control=control)
            if t < 10:
                continue
            truth = data.states[agents, t, :2]
            scores.append(nees(out.mean[agents, :2], out.cov[agents, :2, :2],
                               truth))
            errors.append((out.mean[agents, :2] - truth).square().sum(-1))
        if tracker.noise_adaptation is not None:
            scales.append(NoiseAdaptation.scale(state.memory)[agents])
    scales = torch.cat(scales) if scales else None
    return torch.cat(scores), torch.cat(errors), scales


@pytest.fixture(scope='module')
def networks():
    # six agents between three anchors, ranges of standard deviation 1 m
    scenario = tiny_scenario(steps=40).replace(num_agents=6)
    return [scenario.generate(gen(seed)) for seed in range(6)]


def test_noise_three_times_too_small_is_found_and_a_correct_model_kept(
        networks):
    # the data's ranges have sigma 1; a filter told 1/3 is overconfident
    # (its NEES many times the 2 of a consistent one) and stays so; with
    # the adaptation each agent's scale finds about the 9 of the data (the
    # links between agents understate it a little), and the NEES of the
    # steps after the first ten is near 2; the correct model's scales stay
    # near 1 and its estimates as accurate as without the adaptation
    chi2_95 = 5.991  # the 0.95 quantile of chi-square with 2 dof
    runs = {}
    for sigma in (1.0, 1 / 3):
        for adaptation in (None, NoiseAdaptation()):
            tracker = GaussianBP.recommended(
                measurement=GaussianRange(sigma=sigma), report_inflation=1.0,
                noise_adaptation=adaptation)
            runs[sigma, adaptation is not None] = _track(tracker, networks)
    tight, _, _ = runs[1 / 3, False]
    adapted, adapted_errors, scales = runs[1 / 3, True]
    assert float(tight.mean()) > 8  # overconfident without it
    assert float((tight <= chi2_95).double().mean()) < 0.75
    assert 5 < float(scales.median()) < 11
    assert 1.3 < float(adapted.mean()) < 3.2
    assert float((adapted <= chi2_95).double().mean()) > 0.88
    plain, plain_errors, _ = runs[1.0, False]
    kept, kept_errors, kept_scales = runs[1.0, True]
    assert float(kept_scales.median()) < 1.2
    assert float(kept_errors.mean().sqrt()) < 1.02 * float(
        plain_errors.mean().sqrt())
    assert float(kept.mean()) == pytest.approx(float(plain.mean()), rel=0.1)
    # adapted, the misspecified filter is as accurate as the correct one
    assert float(adapted_errors.mean().sqrt()) < 1.1 * float(
        plain_errors.mean().sqrt())


def test_options_are_checked_by_name():
    for options, name in ((dict(memory=1.0), 'memory'),
                          (dict(memory=0.0), 'memory'),
                          (dict(prior_count=-1.0), 'prior_count'),
                          (dict(max_scale=0.5), 'max_scale'),
                          (dict(max_scale=float('inf')), 'max_scale')):
        with pytest.raises(ValueError, match=name):
            NoiseAdaptation(**options)
    with pytest.raises(TypeError, match='noise_adaptation'):
        GaussianBP(noise_adaptation=0.9)


@pytest.mark.parametrize('model', [GaussianRange(sigma=0.7),
                                   StudentTRange(sigma=0.5, nu=4.0),
                                   NLOSRange()])
def test_the_range_closed_form_is_the_general_statistic(model, monkeypatch):
    # a range model's rank-one closed form against the general path
    # (score, Fisher information, pseudo-inverse by eigen-decomposition)
    # that every other model takes
    from tg_nebp.filters import noise_adaptation
    g = gen(3)
    mean, cov = _beliefs(g, 8)
    anchor = torch.zeros(8, dtype=torch.bool)
    anchor[0] = True
    edge_index = torch.tensor([[0, 1, 2, 3, 4, 5, 0], [1, 2, 3, 4, 5, 6, 7]])
    z = torch.rand(7, 1, generator=g, dtype=torch.float64) * 10
    belief = GaussianBelief(mean, torch.linalg.inv(cov))
    closed = NoiseAdaptation().statistics(model, belief, edge_index, z,
                                          anchor)
    monkeypatch.setattr(noise_adaptation, 'RangeModel', ())
    general = NoiseAdaptation().statistics(model, belief, edge_index, z,
                                           anchor)
    for a, b in zip(closed, general):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
