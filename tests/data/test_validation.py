r"""Tests of the validation layer (:mod:`tg_nebp.data.validation`) through
its two main entry points: :class:`~tg_nebp.nn.conv.ParticleBPConv` with
:obj:`validate=True`, and a :class:`~tg_nebp.data.Realization` given to
:func:`~tg_nebp.data.check_realization` or to
:class:`~tg_nebp.filters.ParticleBP`. Every bad input must raise a
:class:`ValueError` that names the field and the offending index."""
import math
import re

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch_geometric import EdgeIndex
from torch_geometric.data import Batch

from tg_nebp.data import Realization, check_realization
from tg_nebp.data.validation import check_positive_int
from tg_nebp.datasets import Scenario
from tg_nebp.filters import ParticleBP
from tg_nebp.nn.conv import ParticleBPConv

from helpers import NonNegativeRange

# --------------------------------------------------------------------------
# the convolution
# --------------------------------------------------------------------------

N, K = 5, 4  # nodes 0..3 agents, node 4 an anchor


def conv_inputs():
    g = torch.Generator().manual_seed(0)
    particles = 5.0 * torch.randn(N, K, 4, generator=g)
    particles[4] = torch.tensor([1.0, 2.0, 0.0, 0.0])
    log_weights = torch.full((N, K), -math.log(K))
    edge_index = torch.tensor([[1, 2, 4, 0, 3, 4, 2],
                               [0, 0, 0, 1, 1, 2, 3]])
    edge_attr = torch.tensor([[1.0], [2.0], [3.0], [4.0], [5.0], [6.0],
                              [7.0]])
    anchor = torch.tensor([False, False, False, False, True])
    return dict(particles=particles, log_weights=log_weights,
                edge_index=edge_index, edge_attr=edge_attr,
                sender_log_weights=None, anchor=anchor)


def run_conv(inputs, validate=True):
    # a likelihood that needs non-negative ranges: they are refused
    return ParticleBPConv(NonNegativeRange())(
        inputs['particles'], inputs['log_weights'], inputs['edge_index'],
        inputs['edge_attr'], inputs['sender_log_weights'], inputs['anchor'],
        validate=validate)


def test_valid_conv_inputs_pass():
    inputs = conv_inputs()
    out, msg = run_conv(inputs)
    assert bool(torch.isfinite(out).all()) and msg.shape == (7, K)
    # an agent that heard something changed, the anchor did not
    assert not torch.equal(out[0], inputs['log_weights'][0])
    assert torch.equal(out[4], inputs['log_weights'][4])


def _set(key, fn):
    def corrupt(inputs):
        inputs[key] = fn(inputs[key])
    return corrupt


def _at(index, value):
    def fn(t):
        t = t.clone()
        t[index] = value
        return t
    return fn


CONV_CORRUPTIONS = [
    ('range_nan', _set('edge_attr', _at((3, 0), math.nan)),
     r"'edge_attr\[3\]' = nan is not finite"),
    ('range_inf', _set('edge_attr', _at((5, 0), math.inf)),
     r"'edge_attr\[5\]' = inf is not finite"),
    ('range_minus_inf', _set('edge_attr', _at((0, 0), -math.inf)),
     r"'edge_attr\[0\]' = -inf is not finite"),
    ('range_negative', _set('edge_attr', _at((6, 0), -0.5)),
     r"'edge_attr\[6\]' = -0.5 is a negative range"),
    ('range_flat', _set('edge_attr', lambda t: t.view(-1)),
     r"'edge_attr' must have shape \[7, F\] with the link features "
     r"\('range',\) first, got \(7,\)"),
    ('range_no_column', _set('edge_attr', lambda t: t[:, :0]),
     r"'edge_attr' must have shape \[7, F\].*got \(7, 0\)"),
    ('range_one_too_many', _set('edge_attr',
                                lambda t: torch.cat([t, t[:1]])),
     r"'edge_attr' must have shape \[7, F\].*got \(8, 1\)"),
    ('second_feature_nan', _set('edge_attr', lambda t: torch.cat(
        [t, torch.zeros_like(t).index_fill_(0, torch.tensor([5]), math.nan)],
        1)), r"'edge_attr\[5, 1\]' = nan is not finite"),
    ('range_integer', _set('edge_attr', lambda t: t.long()),
     r"'edge_attr' must be a floating point tensor"),
    ('index_too_large', _set('edge_index', _at((1, 4), N)),
     r"'edge_index\[1, 4\]' = 5 is out of range for 5 nodes"),
    ('index_negative', _set('edge_index', _at((0, 2), -1)),
     r"'edge_index\[0, 2\]' = -1 is out of range for 5 nodes"),
    ('self_loop', _set('edge_index', _at((0, 3), 1)),
     r"'edge_index\[:, 3\]' is a self-loop on node 1"),
    ('index_float', _set('edge_index', lambda t: t.float()),
     r"'edge_index' must be an integer tensor"),
    ('index_three_rows', _set('edge_index',
                              lambda t: torch.cat([t, t[:1]])),
     r"'edge_index' must have shape \[2, E\], got \(3, 7\)"),
    ('weights_wrong_K', _set('log_weights', lambda t: t[:, :-1]),
     r"'log_weights' must have shape \[5, 4\].*\(K = 4\), got \[5, 3\]"),
    ('weights_wrong_N', _set('log_weights', lambda t: t[:-1]),
     r"'log_weights' must have shape \[5, 4\].*got \[4, 4\]"),
    ('sender_wrong_K', lambda i: i.update(
        sender_log_weights=torch.zeros(N, K + 2)),
     r"'sender_log_weights' must have shape \[5, 4\].*got \[5, 6\]"),
    ('particles_wrong_K', _set('particles', lambda t: t[:, :-2]),
     r"'log_weights' must have shape \[5, 2\].*\(K = 2\), got \[5, 4\]"),
    ('particles_state_1', _set('particles', lambda t: t[..., :1]),
     r"'particles' must hold a position, then a velocity.*state size 1"),
    ('particles_2d', _set('particles', lambda t: t[..., 0]),
     r"'particles' must have shape \[N, K, D\], got \(5, 4\)"),
    ('particles_no_K', _set('particles', lambda t: t[:, :0]),
     r"'particles' holds K = 0 particles"),
    ('particle_nan', _set('particles', _at((2, 1, 0), math.nan)),
     r"'particles\[2\]' holds a non-finite value"),
    ('particle_inf', _set('particles', _at((3, 0, 3), math.inf)),
     r"'particles\[3\]' holds a non-finite value"),
    ('weight_nan', _set('log_weights', _at((1, 2), math.nan)),
     r"'log_weights\[1\]' holds NaN or \+inf"),
    ('weight_plus_inf', _set('log_weights', _at((3, 0), math.inf)),
     r"'log_weights\[3\]' holds NaN or \+inf"),
    ('sender_nan', lambda i: i.update(
        sender_log_weights=_at((2, 3), math.nan)(torch.zeros(N, K))),
     r"'sender_log_weights\[2\]' holds NaN or \+inf"),
    ('anchor_long', _set('anchor', lambda t: t.long()),
     r"'anchor' must be a bool tensor of shape \[5\], got torch.int64"),
    ('anchor_uint8', _set('anchor', lambda t: t.to(torch.uint8)),
     r"'anchor' must be a bool tensor of shape \[5\], got torch.uint8"),
    ('anchor_short', _set('anchor', lambda t: t[:-1]),
     r"'anchor' must be a bool tensor of shape \[5\].*\[4\]"),
    ('weights_zero_row', _set('log_weights', _at(2, -math.inf)),
     r"'log_weights\[2\]' is -inf for every particle"),
    ('sender_zero_row', lambda i: i.update(
        sender_log_weights=_at(3, -math.inf)(torch.zeros(N, K))),
     r"'sender_log_weights\[3\]' is -inf for every particle"),
    ('range_too_large', _set('edge_attr', _at((4, 0), 1e30)),
     r"'edge_attr\[4\]' = 1e\+30 is too large a range \(at most 4.61e\+18"),
    ('particle_too_large', _set('particles', _at((1, 2, 0), -1e20)),
     r"'particles\[1\]' holds a value beyond 4.61e\+18"),
    ('velocity_too_large', _set('particles', _at((2, 0, 3), 1e20)),
     r"'particles\[2\]' holds a value beyond 4.61e\+18"),
    ('log_weight_too_large', _set('log_weights', _at((1, 1), -2e38)),
     r"'log_weights\[1\]' holds a finite value beyond 4.61e\+18"),
    ('false_col_order_claim', _set('edge_index', lambda t: EdgeIndex(
        t[:, [0, 3, 1]], sparse_size=(N, N), sort_order='col')),
     r"'edge_index' claims sort_order='col' but 'edge_index\[1, 2\]' = 0 "
     r"follows 1"),
    ('false_row_order_claim', _set('edge_index', lambda t: EdgeIndex(
        t, sparse_size=(N, N), sort_order='row')),
     r"'edge_index' claims sort_order='row' but 'edge_index\[0, 3\]' = 0 "
     r"follows 4"),
    ('edge_index_sparse_size', _set('edge_index', lambda t: EdgeIndex(
        t, sparse_size=(N + 1, N + 1))),
     r"'edge_index' has sparse size \(6, 6\) but the graph has 5 nodes"),
    ('empty_graph', lambda i: i.update(
        particles=torch.zeros(0, K, 4), log_weights=torch.zeros(0, K),
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        edge_attr=torch.zeros(0, 1), anchor=None),
     r"'num_nodes' must be positive, got 0 \(empty graph\)"),
]


@pytest.mark.parametrize('name,corrupt,message', CONV_CORRUPTIONS,
                         ids=[c[0] for c in CONV_CORRUPTIONS])
def test_conv_rejects(name, corrupt, message):
    inputs = conv_inputs()
    corrupt(inputs)
    with pytest.raises(ValueError, match=message):
        run_conv(inputs)


def test_conv_minus_inf_log_weight_is_valid():
    inputs = conv_inputs()
    inputs['log_weights'][0, 1] = -math.inf
    out, _ = run_conv(inputs)
    assert float(out[0, 1]) == -math.inf
    assert not bool(torch.isnan(out).any())


def test_conv_validate_false_skips_the_checks():
    inputs = conv_inputs()
    inputs['edge_attr'][0, 0] = math.nan  # edge 1 -> 0
    out, _ = run_conv(inputs, validate=False)
    # garbage in, garbage out: only the receiver of that edge is NaN
    assert bool(torch.isnan(out[0]).all())
    assert not bool(torch.isnan(out[1:]).any())


# --------------------------------------------------------------------------
# realizations
# --------------------------------------------------------------------------


@pytest.fixture(scope='module')
def generated():
    scenario = Scenario.load('paper_train').replace(num_steps=3)
    return scenario.generate(torch.Generator().manual_seed(0))


@pytest.fixture
def realization(generated):
    return generated.clone()


def small_realization():
    r"""3 agents (0, 1, 2) and 2 anchors (3, 4), T = 2 steps, by hand."""
    prior_cov = torch.diag(torch.tensor([10.0, 10.0, 0.01, 0.01]))
    prior_cov = prior_cov.repeat(5, 1, 1)
    prior_cov[3:] = 0.0
    return Realization(
        states=torch.arange(5 * 2 * 4, dtype=torch.float).view(5, 2, 4),
        edge_index=torch.tensor([[3, 1, 4, 0, 3, 2],
                                 [0, 0, 1, 1, 2, 1]]),
        edge_attr=torch.tensor([[1.0], [2.0], [3.0], [1.5], [2.5], [0.5]]),
        edge_time=torch.tensor([0, 0, 0, 1, 1, 1]),
        anchor=torch.tensor([False, False, False, True, True]),
        prior_mean=torch.tensor([[1.0, 1.0, 0.0, 0.0], [5.0, 5.0, 0.1, 0.0],
                                 [2.0, 8.0, 0.0, 0.1], [0.0, 0.0, 0.0, 0.0],
                                 [10.0, 0.0, 0.0, 0.0]]),
        prior_cov=prior_cov, num_steps=2, num_nodes=5)


def check_both(data, message):
    r"""Both entry points reject :obj:`data` with :obj:`message`."""
    with pytest.raises(ValueError, match=message):
        check_realization(data)
    # a likelihood defined for negative ranges takes them
    if 'negative range' in message:
        check_realization(data, negative_ranges=True)
    with pytest.raises(ValueError, match=message):
        ParticleBP(num_particles=8, measurement=NonNegativeRange())(
            data, torch.Generator().manual_seed(0))


def test_valid_realizations_pass(realization):
    for data in (realization, small_realization()):
        check_realization(data)
        out = ParticleBP(num_particles=16)(data,
                                           torch.Generator().manual_seed(1))
        assert out.mean.shape == (data.num_nodes, data.num_time_steps, 4)
        assert bool(torch.isfinite(out.mean).all())
        anchor = data.anchor
        # anchors are tracked at their known position
        torch.testing.assert_close(
            out.mean[anchor], data.prior_mean[anchor].unsqueeze(1).expand(
                -1, data.num_time_steps, -1))


def test_generated_realization_is_what_the_checks_assume(realization):
    r"""Guards the corruption tests below: the fixture has anchors that
    never receive and agents that do."""
    anchor = realization.anchor
    assert bool(anchor.any()) and not bool(anchor.all())
    assert not bool(anchor[realization.edge_index[1]].any())
    assert realization.edge_index.size(1) > 100


@pytest.mark.parametrize('value,what', [
    (math.nan, r'nan is not finite'),
    (math.inf, r'inf is not finite'),
    (-math.inf, r'-inf is not finite'),
    (-1.0, r'-1.0 is a negative range'),
])
def test_realization_bad_range(realization, value, what):
    e = realization.edge_index.size(1) // 2 + 7
    realization.edge_attr[e, 0] = value
    check_both(realization, rf"'edge_attr\[{e}\]' = {what}")


def test_realization_range_wrong_shape(realization):
    E = realization.edge_attr.size(0)
    realization.edge_attr = realization.edge_attr.view(-1)
    check_both(realization, rf"'edge_attr' must have shape \[{E}, F\]")


def test_realization_edge_index_out_of_range(realization):
    n = realization.num_nodes
    realization.edge_index[0, 11] = n + 3
    check_both(realization,
               rf"'edge_index\[0, 11\]' = {n + 3} is out of range for {n} "
               rf"nodes")


def test_realization_self_loop(realization):
    receiver = int(realization.edge_index[1, 20])
    realization.edge_index[0, 20] = receiver
    check_both(realization, rf"'edge_index\[:, 20\]' is a self-loop on node "
               rf"{receiver}")


def test_realization_edge_into_anchor(realization):
    a = int(realization.anchor.nonzero()[0, 0])
    e = int((realization.edge_index[0] != a).nonzero()[5, 0])
    realization.edge_index[1, e] = a
    check_both(realization, rf"'edge_index\[:, {e}\]' ends at anchor {a}")


@pytest.mark.parametrize('offset', [0, 1, 5])
def test_realization_edge_time_too_large(realization, offset):
    T = realization.num_time_steps
    realization.edge_time[9] = T + offset
    check_both(realization,
               rf"'edge_time\[9\]' = {T + offset} is outside \[0, {T}\)")


def test_realization_edge_time_negative(realization):
    realization.edge_time[4] = -1
    check_both(realization, r"'edge_time\[4\]' = -1 is outside \[0, 3\)")


def test_realization_edge_time_wrong_shape(realization):
    realization.edge_time = realization.edge_time[:-1]
    check_both(realization, r"'edge_time' must have shape")


def test_realization_edge_time_float(realization):
    realization.edge_time = realization.edge_time.float()
    check_both(realization, r"'edge_time' must be an integer tensor")


def test_realization_non_psd_prior(realization):
    realization.prior_cov[6, 2, 2] = -0.5
    check_both(realization,
               r"'prior_cov\[6\]' is not positive semi-definite "
               r"\(smallest eigenvalue -0.5\)")


def test_realization_non_psd_prior_with_positive_diagonal(realization):
    # diag(2, 2) with off-diagonal 3: eigenvalues 5 and -1
    realization.prior_cov[2, :2, :2] = torch.tensor([[2.0, 3.0], [3.0, 2.0]])
    check_both(realization, r"'prior_cov\[2\]' is not positive "
               r"semi-definite \(smallest eigenvalue -1\)")


def test_realization_asymmetric_prior(realization):
    realization.prior_cov[3, 0, 1] = 1.0
    check_both(realization, r"'prior_cov\[3\]' is not symmetric")


def test_realization_nan_prior_cov(realization):
    realization.prior_cov[8, 1, 1] = math.nan
    check_both(realization, r"'prior_cov\[8\]' is not finite")


def test_realization_prior_cov_wrong_shape(realization):
    realization.prior_cov = realization.prior_cov[:, :3, :3]
    check_both(realization, r"'prior_cov' must have shape \[30, 4, 4\]")


def test_realization_anchor_without_position(realization):
    a = int(realization.anchor.nonzero()[2, 0])
    realization.prior_mean[a] = math.nan
    check_both(realization,
               rf"'prior_mean\[{a}\]': anchor without a known position")


def test_realization_agent_nan_prior_mean(realization):
    realization.prior_mean[4, 1] = math.nan
    check_both(realization, r"'prior_mean\[4\]': non-finite prior mean")


def test_realization_prior_mean_wrong_state_size(realization):
    realization.prior_mean = realization.prior_mean[:, :3]
    check_both(realization,
               r"'prior_mean' must have shape \[30, 4\] or \[30, 6\]")


def test_realization_integer_prior_mean(realization):
    realization.prior_mean = realization.prior_mean.long()
    check_both(realization, r"'prior_mean' must be a floating point tensor")


def test_realization_states_wrong_state_size(realization):
    realization.states = torch.cat([realization.states,
                                    realization.states[..., :1]], dim=-1)
    check_both(realization, r"'states' must have shape \[30, 3, 4\], got "
               r"\[30, 3, 5\]")


def test_realization_states_of_an_agent_without_truth(realization):
    # an agent's whole row NaN: tracked without ground truth, accepted; a
    # NaN within a row, an infinity or an anchor without truth refused
    from tg_nebp.data import check_realization, scored_of
    agent = int((~realization.anchor).nonzero()[0, 0])
    realization.states[agent] = math.nan
    check_realization(realization, ('range', ))
    assert not bool(scored_of(realization)[agent])
    assert int(scored_of(realization).sum()) == \
        int((~realization.anchor).sum()) - 1
    realization.states[agent, 0, 0] = 1.0
    check_both(realization, rf"'states\[{agent}\]' holds a non-finite")
    realization.states[agent] = math.inf
    check_both(realization, rf"'states\[{agent}\]' holds a non-finite")
    realization.states[agent] = 0.0
    a = int(realization.anchor.nonzero()[0, 0])
    realization.states[a] = math.nan
    check_both(realization, rf"'states\[{a}\]' holds a non-finite")


def test_realization_states_wrong_steps(realization):
    realization.states = realization.states[:, :2]
    check_both(realization, r"'states' must have shape \[30, 3, 4\]")


@pytest.mark.parametrize('dtype', [torch.long, torch.uint8, torch.float])
def test_realization_anchor_wrong_dtype(realization, dtype):
    realization.anchor = realization.anchor.to(dtype)
    check_both(realization, rf"'anchor' must be a bool tensor of shape "
               rf"\[30\], got {re.escape(str(dtype))}")


def test_realization_anchor_wrong_shape(realization):
    realization.anchor = realization.anchor[:-1]
    check_both(realization, r"'anchor' must be a bool tensor of shape \[30\]")


def test_realization_all_anchors():
    data = small_realization()
    data.anchor = torch.ones(5, dtype=torch.bool)
    check_both(data, r"'anchor': the graph has no agent to localize")


def test_realization_empty_graph():
    data = Realization(
        states=torch.zeros(0, 2, 4),
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        edge_attr=torch.zeros(0, 1), edge_time=torch.zeros(0,
                                                           dtype=torch.long),
        anchor=torch.zeros(0, dtype=torch.bool), prior_mean=torch.zeros(0, 4),
        prior_cov=torch.zeros(0, 4, 4), num_steps=2, num_nodes=0)
    check_both(data, r"'num_nodes' must be positive, got 0 \(empty graph\)")


@pytest.mark.parametrize('key', ['edge_index', 'edge_attr', 'edge_time',
                                 'anchor', 'prior_mean', 'prior_cov',
                                 'num_steps'])
def test_realization_missing_field(key):
    data = small_realization()
    delattr(data, key)
    check_both(data, rf"realization is missing the field '{key}'")


def test_small_realization_corruptions_by_hand():
    data = small_realization()
    check_realization(data)
    data.edge_index[1, 2] = 4  # edge 4 -> 4
    check_both(data, r"'edge_index\[:, 2\]' is a self-loop on node 4")
    data = small_realization()
    data.edge_index[1, 4] = 3  # edge 3 -> 3 is caught as a self-loop first
    check_both(data, r"'edge_index\[:, 4\]' is a self-loop on node 3")
    data = small_realization()
    data.edge_index[1, 4] = 4  # edge 3 -> anchor 4
    check_both(data, r"'edge_index\[:, 4\]' ends at anchor 4")


def test_batched_realization_names_the_global_index(generated):
    first, second = generated.clone(), generated.clone()
    E, n = first.edge_index.size(1), first.num_nodes
    second.edge_attr[3, 0] = -2.0
    batch = Batch.from_data_list([first, second])
    check_both(batch, rf"'edge_attr\[{E + 3}\]' = -2.0 is a negative range")

    second = generated.clone()
    a = int(second.anchor.nonzero()[0, 0])
    second.prior_mean[a] = math.nan
    batch = Batch.from_data_list([first, second])
    check_both(batch, rf"'prior_mean\[{n + a}\]': anchor without a known "
               rf"position")


def test_batched_realization_with_unequal_steps(generated):
    other = Scenario.load('paper_train').replace(num_steps=2).generate(
        torch.Generator().manual_seed(1))
    first = generated.clone()
    del first.states, other.states  # [N, T, 4] does not collate across T
    batch = Batch.from_data_list([first, other])
    check_both(batch, r"'num_steps' must be equal across a batch, got "
               r"\[3, 2\]")


# --------------------------------------------------------------------------
# property-based: one random corruption, named by its index
# --------------------------------------------------------------------------

BAD_RANGES = st.sampled_from([math.nan, math.inf, -math.inf, -1e-3, -7.0])


@settings(max_examples=30, deadline=None, derandomize=True)
@given(fraction=st.floats(0.0, 1.0, exclude_max=True), value=BAD_RANGES)
def test_property_bad_range_is_named(generated, fraction, value):
    data = generated.clone()
    E = data.edge_attr.size(0)
    e = int(fraction * E)
    data.edge_attr[e, 0] = value
    with pytest.raises(ValueError) as info:
        check_realization(data)
    assert re.search(rf"'edge_attr\[{e}\]' = ", str(info.value))


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.data())
def test_property_conv_corruption_is_named(data):
    n = data.draw(st.integers(2, 8), label='nodes')
    k = data.draw(st.integers(1, 5), label='K')
    pairs = [(j, i) for i in range(n) for j in range(n) if i != j]
    edges = data.draw(st.lists(st.sampled_from(pairs), min_size=1,
                               max_size=15), label='edges')
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1)))
    particles = 10.0 * torch.randn(n, k, 4, generator=g)
    log_weights = torch.randn(n, k, generator=g)
    edge_index = torch.tensor(edges).t().contiguous()
    edge_attr = 20.0 * torch.rand(len(edges), 1, generator=g)
    conv = ParticleBPConv()
    kind = data.draw(st.sampled_from(['range', 'weight', 'particle']),
                     label='kind')
    if kind == 'range':
        e = data.draw(st.integers(0, len(edges) - 1), label='edge')
        edge_attr[e, 0] = data.draw(BAD_RANGES, label='value')
        message = rf"'edge_attr\[{e}\]' = "
    elif kind == 'weight':
        i = data.draw(st.integers(0, n - 1), label='node')
        log_weights[i, data.draw(st.integers(0, k - 1))] = data.draw(
            st.sampled_from([math.nan, math.inf]), label='value')
        message = rf"'log_weights\[{i}\]' holds NaN or \+inf"
    else:
        i = data.draw(st.integers(0, n - 1), label='node')
        particles[i, data.draw(st.integers(0, k - 1)),
                  data.draw(st.integers(0, 3))] = data.draw(
            st.sampled_from([math.nan, math.inf, -math.inf]), label='value')
        message = rf"'particles\[{i}\]' holds a non-finite value"
    with pytest.raises(ValueError, match=message):
        conv(particles, log_weights, edge_index, edge_attr)


def test_first_of_several_offending_indices_is_named(realization):
    realization.edge_attr[40, 0] = math.nan
    realization.edge_attr[17, 0] = -3.0  # negative, but checked after NaNs
    realization.edge_attr[90, 0] = math.inf
    check_both(realization, r"'edge_attr\[40\]' = nan is not finite")
    realization.edge_attr[40, 0] = 1.0
    check_both(realization, r"'edge_attr\[90\]' = inf is not finite")
    realization.edge_attr[90, 0] = 1.0
    realization.edge_attr[60, 0] = -1.0
    check_both(realization, r"'edge_attr\[17\]' = -3.0 is a negative range")
    inputs = conv_inputs()
    inputs['log_weights'][3, 0] = math.nan
    inputs['log_weights'][1, 2] = math.inf
    with pytest.raises(ValueError, match=r"'log_weights\[1\]'"):
        run_conv(inputs)


def test_realization_without_steps(realization):
    realization.num_steps = 0
    realization.edge_time = realization.edge_time[:0]
    realization.edge_index = realization.edge_index[:, :0]
    realization.edge_attr = realization.edge_attr[:0]
    realization.states = realization.states[:, :0]
    check_both(realization, r"'num_steps' must be at least 1, got 0")


def test_realization_fractional_steps(realization):
    realization.num_steps = torch.tensor([2.5])
    check_both(realization, r"'num_steps' must be an integer, got \[2.5\]")


def test_realization_range_too_large(realization):
    # the probe: NaN estimates, then an internal resampler error
    realization.edge_attr[11, 0] = 1e30
    check_both(realization, r"'edge_attr\[11\]' = 1e\+30 is too large")


def test_realization_prior_mean_too_large(realization):
    realization.prior_mean[2, 1] = 1e25
    check_both(realization, r"'prior_mean\[2\]' holds a position beyond")


@pytest.mark.parametrize('dtype, variance', [(torch.float64, 1.7e308),
                                             (torch.float32, 3e38),
                                             (torch.float64, 1e15)])
def test_realization_prior_variance_too_large(realization, dtype, variance):
    # a finite variance near the largest float passed, then overflowed
    # the symmetrization (Gaussian BP's raw LinAlgError, the window's
    # Cholesky error, the bound's NaN)
    realization.prior_mean = realization.prior_mean.to(dtype)
    realization.prior_cov = realization.prior_cov.to(dtype)
    realization.prior_cov[2, 1, 1] = variance
    check_both(realization, r"'prior_cov\[2\]' holds an entry beyond 1e\+14")


def test_the_largest_prior_variance_is_tracked_finitely():
    # at the bound, every Gaussian tracker and the bound stay finite and
    # the agents are found by their links
    from tg_nebp.bounds import PosteriorCRB
    from tg_nebp.data.validation import MAX_PRIOR_VARIANCE
    from tg_nebp.filters import (CentralizedIEKF, FixedLagGaussianBP,
                                 GaussianBP)
    from helpers import gen, tiny_scenario
    data = tiny_scenario(steps=6).generate(gen(0))
    agents = ~data.anchor
    data.prior_cov = data.prior_cov.clone()
    data.prior_cov[agents] = torch.eye(4, dtype=data.prior_cov.dtype) * \
        MAX_PRIOR_VARIANCE
    check_realization(data)
    for tracker in (GaussianBP.recommended(),
                    FixedLagGaussianBP.recommended(lag=3),
                    CentralizedIEKF()):
        out = tracker(data)
        assert bool(out.cov.isfinite().all())
        error = (out.mean[agents, -1, :2] - data.states[agents, -1, :2])
        assert float(error.norm(dim=-1).max()) < 3.0
    assert bool(PosteriorCRB()(data).isfinite().all())


@pytest.mark.parametrize('value,error', [
    (2.5, TypeError), ('8', TypeError), (True, TypeError), (0, ValueError),
    (-3, ValueError)])
def test_check_positive_int(value, error):
    with pytest.raises(error, match="'num_particles' must be"):
        check_positive_int(value, 'num_particles')
    assert check_positive_int(np.int64(7), 'num_particles') == 7


# -- a singular prior: particles carry it, the Gaussian methods need the
# motion model's noise to reach it --------------------------------------

@pytest.mark.parametrize('entries', [[2, 3], [0, 1, 2, 3]])
def test_a_singular_agent_prior_is_used_or_refused_by_name(entries):
    # a velocity known at the start (zero variance) is filled by the
    # motion's noise at the first prediction: used. A whole state known
    # is not (the noise of a constant-velocity model has rank D): refused,
    # naming the field and the node, by every Gaussian method
    from tg_nebp.bounds import PosteriorCRB
    from tg_nebp.filters import CentralizedIEKF, GaussianBP
    data = small_realization()
    agent = int((~data.anchor).nonzero()[1, 0])
    data.prior_cov[agent, entries, entries] = 0.0
    check_realization(data)  # a valid covariance, positive semi-definite
    out = ParticleBP(num_particles=16)(data, torch.Generator().manual_seed(1))
    assert bool(torch.isfinite(out.mean).all())
    for method, what in ((GaussianBP(), 'Gaussian BP'),
                         (CentralizedIEKF(), 'the centralized IEKF'),
                         (PosteriorCRB(), 'the posterior CRB')):
        if len(entries) == 2:
            out = method(data)
            cov = out if isinstance(out, torch.Tensor) else out.cov
            assert bool(torch.isfinite(cov).all()), what
            continue
        with pytest.raises(ValueError, match=re.escape(
                f"'prior_cov[{agent}]' of agent {agent} is singular") +
                f'.*{what} needs a positive predicted variance'):
            method(data)


def _robots(steps=4):
    scenario = Scenario.load('robots_train').replace(num_steps=steps)
    return scenario, scenario.generate(torch.Generator().manual_seed(0))


@pytest.mark.parametrize('edit,match', [
    (lambda d: setattr(d, 'control', d.control[:, :, :1]),
     r"'control' must have shape \[11, 4, 2\]"),
    (lambda d: setattr(d, 'control', d.control.long()),
     "'control' must be a floating point"),
    (lambda d: d.control.__setitem__((2, 3, 0), math.inf),
     r"'control\[2, 3\]' holds an infinite value"),
    (lambda d: d.control.__setitem__((1, 2, 1), math.nan),
     r"'control\[1, 2\]' is partly NaN"),
    (lambda d: setattr(d, 'position_dim', 4),
     "'position_dim' must be 2 or 3"),
])
def test_bad_control_and_layout_are_named(edit, match):
    from tg_nebp.filters import GaussianBP
    scenario, data = _robots()
    edit(data)
    with pytest.raises(ValueError, match=match):
        GaussianBP(motion=scenario.motion_model,
                   measurement=scenario.measurement_model).check(data)


def test_control_for_a_model_without_inputs_is_refused():
    from tg_nebp.filters import GaussianBP
    from tg_nebp.models import ConstantVelocity
    _, data = _robots()
    # a robot's states are not a constant-velocity model's
    with pytest.raises(ValueError, match='positions have 2 entries'):
        GaussianBP(motion=ConstantVelocity()).check(data)
    scenario = Scenario.load('paper_train').replace(num_steps=3)
    paper = scenario.generate(torch.Generator().manual_seed(0))
    paper.control = torch.zeros(paper.num_nodes, 3, 2)
    with pytest.raises(ValueError, match='takes none'):
        GaussianBP().check(paper)
    # without a declared layout a state is [p, v]
    del data.position_dim
    with pytest.raises(ValueError, match=r"shape \[11, 4\] or \[11, 6\]"):
        check_realization(data)


@pytest.mark.parametrize('method', ['gbp', 'iekf', 'bp'])
def test_a_motion_layout_outside_the_state_is_named_before_any_step(method):
    # a user's robot model whose layout names angle index 5 of a state of
    # 3 entries: refused by name where the model meets the data, not an
    # IndexError inside a step
    from tg_nebp.filters import CentralizedIEKF, GaussianBP, ParticleBP
    from tg_nebp.models import GaussianRange, StateLayout, UnicycleOdometry

    class Misnumbered(UnicycleOdometry):
        def layout(self, size):
            return StateLayout(size, 2, (5, ))

    _, data = _robots()
    # a range model (a range-bearing one refuses the layout itself)
    models = dict(motion=Misnumbered(), measurement=GaussianRange())
    tracker = {'gbp': GaussianBP, 'iekf': CentralizedIEKF,
               'bp': lambda **m: ParticleBP(num_particles=20, **m)}[method](
        **models)
    with pytest.raises(ValueError, match=r"names angle index 5 of a state "
                       r"of size 3 \(its entries are 0 to 2\)"):
        tracker(data)


def test_a_tracker_told_to_ignore_inputs_runs_data_that_has_them():
    from tg_nebp.filters import CentralizedIEKF, GaussianBP
    scenario = Scenario.load('paper_train').replace(num_steps=3)
    paper = scenario.generate(torch.Generator().manual_seed(0))
    plain = GaussianBP()(paper)
    paper.control = torch.zeros(paper.num_nodes, 3, 2)
    for tracker in (GaussianBP(), CentralizedIEKF()):
        tracker.use_control = False
        tracker(paper)
    blind = GaussianBP()
    blind.use_control = False
    assert torch.equal(blind(paper).mean, plain.mean)
