r"""The relocation of lost agents (LinkSearch) in every Gaussian tracker:
an agent locked on the mirror position of two anchors, when a third one
contradicts it, is relocated at once by Gaussian BP, fixed-lag Gaussian BP
(rejoining its window) and the Gaussian NEBP, where the same trackers
without it stay lost; the search's candidates, settings and refusals."""

import pytest
import torch
from scipy.stats import chi2

from tg_nebp.filters import (FixedLagGaussianBP, GaussianBP, GaussianNEBP,
                             LinkSearch, TrackingSession)
from tg_nebp.filters.gaussian.relocation import directions

from helpers import mirror, randomize, stream_realization


def trackers(models):
    return {
        'gbp': lambda relocation: GaussianBP.recommended(
            relocation=relocation, **models),
        'lag3': lambda relocation: FixedLagGaussianBP.recommended(
            lag=3, relocation=relocation, **models),
        'gnebp': lambda relocation: randomize(GaussianNEBP.recommended(
            **models), seed=2, scale=0.05).relocate_with(relocation)}


@pytest.mark.parametrize('name', ['gbp', 'lag3', 'gnebp'])
def test_every_gaussian_tracker_relocates_a_lost_agent(name):
    data, models = mirror((-4.0, 4.0))
    truth = data.states[0, 0, :2].double()
    make = trackers(models)[name]
    with torch.no_grad():
        lost = make(None)(data)
        found = make(LinkSearch())(data)
    errors = (found.mean[0, :, :2] - truth).norm(dim=-1)
    assert float((lost.mean[0, -1, :2] - truth).norm()) > 5
    assert bool((errors[:3] > 8).all())  # two anchors cannot tell
    # the third anchor decides at the agent's first search after it (the
    # agent is searched every 'every' steps), and for good
    search = LinkSearch()
    at = int((errors < 1.0).nonzero()[0, 0])
    assert 3 <= at < 3 + search.every
    assert bool((errors[at:] < 1.0).all())
    for t in range(at, data.num_steps):
        error = found.mean[0, t, :2] - truth
        nees = error @ torch.linalg.solve(found.cov[0, t, :2, :2], error)
        assert float(nees) < chi2.ppf(0.99, 2)


def test_a_live_session_relocates_as_the_offline_loop():
    data, models = mirror()
    tracker = FixedLagGaussianBP.recommended(lag=3,
                                             relocation=LinkSearch(), **models)
    offline = tracker(data)
    outputs = stream_realization(TrackingSession(tracker), data)
    assert torch.equal(torch.stack([o.mean for o in outputs], 1),
                       offline.mean)


def test_the_search_is_its_settings():
    search = LinkSearch(margin=8.0, directions=6)
    tracker = GaussianBP(relocation=search)
    assert tracker.settings()['relocation'] == dict(
        margin=8.0, directions=6, links=4, steps=2, every=4)
    assert 'relocation' not in GaussianBP().settings()
    assert search == LinkSearch(margin=8.0, directions=6)
    assert 'LinkSearch(margin=8.0' in repr(tracker)
    for options, match in ((dict(margin=0.0), "'margin'"),
                           (dict(directions=0), "'directions'"),
                           (dict(links=0), "'links'"),
                           (dict(steps=-1), "'steps' must be at least 0"),
                           (dict(every=0), "'every'")):
        with pytest.raises(ValueError, match=match):
            LinkSearch(**options)
    # a count of another type named (a raw TypeError of 'steps + 1' was
    # raised, and True taken as 1)
    for steps in ('2', None, True, 1.5):
        with pytest.raises(TypeError, match="'steps' must be an integer"):
            LinkSearch(steps=steps)
    assert LinkSearch(steps=0).steps == 0
    with pytest.raises(TypeError, match="'relocation'"):
        GaussianBP(relocation='search')


@pytest.mark.parametrize('dim', [1, 2, 3])
def test_the_directions_are_unit_vectors_spread_evenly(dim):
    out = directions(12, dim, torch.zeros((), dtype=torch.float64))
    assert out.shape == (12, dim)
    torch.testing.assert_close(out.norm(dim=-1), torch.ones(
        12, dtype=torch.float64))
    # evenly spread: they cancel out (a lattice on the sphere nearly)
    assert float(out.sum(0).norm()) < (1e-9 if dim < 3 else 0.5)
    with pytest.raises(ValueError, match='1 to 3 dimensions'):
        directions(4, 4, out)


def test_the_search_weighs_the_links_as_the_correction_does():
    # a correction that discounts every link to its lowest weight (0.02)
    # is not moved by the third anchor: its search raises every link's
    # likelihood to that power, which leaves the decisive margin out of
    # reach; the same tracker searching the untempered likelihood is
    data, models = mirror((-4.0, 4.0))
    truth = data.states[0, 0, :2].double()

    class Untempered(GaussianNEBP):
        def link_weights(self, solved, edge_index, edge_attr, anchor):
            return None

    errors = {}
    for kind in (GaussianNEBP, Untempered):
        tracker = kind.recommended(**models)
        with torch.no_grad():
            tracker.conv.weight_head.weight.zero_()
            tracker.conv.weight_head.bias.fill_(-1e3)
        tracker.relocate_with(LinkSearch())
        with torch.no_grad():
            out = tracker(data)
        errors[kind] = (out.mean[0, -1, :2] - truth).norm()
    assert float(errors[GaussianNEBP]) > 5
    assert float(errors[Untempered]) < 1
