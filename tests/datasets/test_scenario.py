import dataclasses
import importlib.resources
import json
import math

import numpy as np
import pytest
import torch

from tg_nebp.data import Realization
from tg_nebp.data.validation import check_realization
from tg_nebp.datasets import Scenario
from tg_nebp.models import ConstantVelocityDrag, GaussianRange

from helpers import gen

PAPER_TRAIN_ANCHORS = ((10, 10), (50, 10), (10, 50), (50, 50), (30, 30))


def test_load_paper_scenarios_match_the_paper():
    train = Scenario.load('paper_train')
    assert train.num_agents == 25 and train.num_anchors == 5
    assert set(train.anchor_positions) == {
        (float(x), float(y)) for x, y in PAPER_TRAIN_ANCHORS}
    assert (train.agent_start_low, train.agent_start_high) == (15.0, 45.0)
    test = Scenario.load('paper_test')
    assert test.num_agents == 100 and test.num_anchors == 13
    grid = {(float(x), float(y)) for x in (10, 50, 90) for y in (10, 50, 90)}
    inner = {(float(x), float(y)) for x in (30, 70) for y in (30, 70)}
    assert set(test.anchor_positions) == grid | inner
    for s in (train, test):
        assert s.num_steps == 50 and s.sigma_v0 == 0.1
        assert s.measurement_model == GaussianRange(1.0, 20.0)
        assert s.motion_model == ConstantVelocityDrag(0.05, 0.06, 1.0)
        assert s.prior_var == (10.0, 10.0, 0.01, 0.01)


def test_load_from_json_path(tmp_path):
    fields = dict(name='custom', num_agents=2,
                  anchor_positions=[[0, 0], [5, 5]], agent_start_low=1,
                  agent_start_high=4, num_steps=3)
    path = tmp_path / 'custom.json'
    path.write_text(json.dumps(fields))
    s = Scenario.load(path)
    assert s.name == 'custom' and s.anchor_positions == ((0.0, 0.0),
                                                         (5.0, 5.0))
    assert s == Scenario.load(str(path))
    bad = tmp_path / 'bad.json'
    bad.write_text(json.dumps(dict(fields, colour='red')))
    with pytest.raises(ValueError, match='colour'):
        Scenario.load(bad)


def test_unknown_scenario_name():
    with pytest.raises(ValueError, match='unknown scenario'):
        Scenario.load('no_such_scenario')


def test_fingerprint_covers_every_generation_parameter():
    base = Scenario.load('paper_train')
    changes = dict(num_agents=24, anchor_positions=((0, 0), ),
                   agent_start_low=14.0, agent_start_high=46.0, num_steps=49,
                   sigma_v0=0.2, motion=ConstantVelocityDrag(dt=0.5).config(),
                   measurement=GaussianRange(max_range=19.0).config(),
                   prior_var=(9.0, 10.0, 0.01, 0.01), name='other')
    # a drive needs a motion model with inputs: robots_train's below
    assert set(changes) == {f.name for f in dataclasses.fields(Scenario)
                            } - {'description', 'drive'}
    prints = {base.fingerprint()}
    for key, value in changes.items():
        prints.add(base.replace(**{key: value}).fingerprint())
    assert len(prints) == len(changes) + 1
    robots = Scenario.load('robots_train')
    assert robots.replace(drive={**robots.drive, 'turn_back': 0.1}
                          ).fingerprint() != robots.fingerprint()
    # the fingerprints of the scenarios without a drive are those from
    # before drives existed (their datasets' file names)
    assert base.fingerprint() == '622693114a'
    assert Scenario.load('paper_test').fingerprint() == 'dea8836272'
    # the description is free text
    assert base.replace(description='x').fingerprint() == base.fingerprint()
    assert base.replace().fingerprint() == base.fingerprint()


@pytest.mark.parametrize('key,value', [
    ('name', ''), ('name', 'a/b'), ('name', 'a b'), ('name', '..'),
    ('name', '.hidden'), ('name', 'a\\b'), ('name', 'a\x00b'),
    ('num_agents', 0),
    ('num_steps', 0), ('anchor_positions', ((1.0, 2.0, 3.0, 4.0), )),
    ('agent_start_low', 50.0), ('prior_var', (1.0, 1.0, 1.0)),
    ('prior_var', (1.0, 1.0, 0.0, 1.0)), ('sigma_v0', -1.0),
    ('motion', {'name': 'constant-velocity-drag', 'params': {'drag': -1}}),
    ('motion', {'name': 'no-such-motion', 'params': {}}),
    ('measurement', {'name': 'gaussian', 'params': {'sigma': 0.0}}),
    ('measurement', {'name': 'gaussian'}),
])
def test_invalid_parameters_raise(key, value):
    match = key if not isinstance(value, dict) else (
        'drag|sigma|no-such-motion|configuration')
    with pytest.raises(ValueError, match=match):
        Scenario.load('paper_train').replace(**{key: value})


@pytest.fixture(scope='module')
def realization():
    scenario = Scenario.load('paper_train').replace(num_steps=8)
    return scenario, scenario.generate(torch.Generator().manual_seed(0))


def test_generate_layout(realization):
    scenario, data = realization
    assert isinstance(data, Realization)
    check_realization(data)
    n = scenario.num_agents + scenario.num_anchors
    assert data.num_nodes == n and data.num_time_steps == 8
    assert data.states.shape == (n, 8, 4)
    assert data.states.dtype == torch.float32
    assert data.anchor.tolist() == [False] * 25 + [True] * 5  # agents first
    anchors = torch.tensor(scenario.anchor_positions)
    # anchors are static at their positions, with zero velocity
    assert torch.equal(data.states[25:, :, :2],
                       anchors.view(5, 1, 2).expand(5, 8, 2))
    assert bool((data.states[25:, :, 2:] == 0).all())
    assert torch.equal(data.prior_mean[25:, :2], anchors)
    assert bool((data.prior_mean[25:, 2:] == 0).all())
    assert bool((data.prior_cov[25:] == 0).all())
    assert torch.equal(data.prior_cov[:25],
                       torch.diag(torch.tensor([10.0, 10.0, 0.01, 0.01]))
                       .expand(25, 4, 4))


def test_generate_edges_are_all_pairs_within_range(realization):
    scenario, data = realization
    pos = data.states[..., :2].double()
    for t in range(data.num_time_steps):
        mask = data.edge_time == t
        got = set(map(tuple, data.edge_index[:, mask].t().tolist()))
        expected = set()
        for i in range(data.num_nodes):
            if data.anchor[i]:
                continue
            for j in range(data.num_nodes):
                if j != i and float((pos[j, t] - pos[i, t]).norm()) <= 20.0:
                    expected.add((j, i))
        # float32 storage may move a pair by ~1e-5 m across the boundary
        near = {(j, i) for j, i in got ^ expected
                if abs(float((pos[j, t] - pos[i, t]).norm()) - 20) > 1e-4}
        assert not near
        assert len(got) > 100


def test_generate_follows_the_motion_model():
    scenario = Scenario.load('paper_train').replace(num_steps=40)
    data = scenario.generate(torch.Generator().manual_seed(1))
    x = data.states[:25].double()
    v, v_next = x[:, :-1, 2:], x[:, 1:, 2:]
    motion = scenario.motion_model
    c = motion.drag
    # v' = v - c v|v| + a, p' = p + v + (a - c v|v|) / 2 (dt = 1)
    a = v_next - v + c * v * v.abs()
    pos_pred = x[:, :-1, :2] + v + 0.5 * (a - c * v * v.abs())
    assert (pos_pred - x[:, 1:, :2]).abs().max() < 1e-4
    a = a.reshape(-1, 2).numpy()
    n = a.shape[0]
    sigma = motion.sigma_a
    assert np.all(np.abs(a.mean(0)) < 5 * sigma / math.sqrt(n))
    assert np.all(np.abs(a.std(0) - sigma) < 5 * sigma / math.sqrt(2 * n))
    # agents start uniformly in [15, 45]^2: after one step within the box
    # up to a few velocity standard deviations
    p0 = x[:, 0, :2]
    assert bool(((p0 > 14.0) & (p0 < 46.0)).all())


def test_generate_is_deterministic_in_the_generator():
    scenario = Scenario.load('paper_train').replace(num_steps=3)
    a = scenario.generate(torch.Generator().manual_seed(5))
    b = scenario.generate(torch.Generator().manual_seed(5))
    c = scenario.generate(torch.Generator().manual_seed(6))
    for key in ('states', 'edge_index', 'edge_attr', 'edge_time',
                'prior_mean'):
        assert torch.equal(a[key], b[key])
    assert not torch.equal(a.states, c.states)


def test_generate_without_anchors_and_single_agent():
    s = Scenario(name='solo', num_agents=1, anchor_positions=(),
                 agent_start_low=0.0, agent_start_high=1.0, num_steps=4)
    data = s.generate(torch.Generator().manual_seed(0))
    assert data.num_nodes == 1 and data.edge_index.shape == (2, 0)
    assert data.edge_attr.shape == (0, 1)
    assert data.num_time_steps == 4 and len(data.edges_by_step()) == 4


@pytest.mark.parametrize('name,num_agents', [('paper_test', 900),
                                             ('paper_test', 250),
                                             ('paper_train', 100)])
def test_grown_keeps_the_density(name, num_agents):
    base = Scenario.load(name)
    grown = base.grown(num_agents)
    scale = math.sqrt(num_agents / base.num_agents)
    side = base.agent_start_low + base.agent_start_high
    assert grown.num_agents == num_agents
    agent_square = grown.agent_start_high - grown.agent_start_low
    base_square = base.agent_start_high - base.agent_start_low
    assert math.isclose(num_agents / agent_square**2,
                        base.num_agents / base_square**2)
    # the anchors: the base layout tiled, all inside the grown area
    anchors = torch.tensor(grown.anchor_positions)
    assert bool((anchors >= 0).all() and (anchors <= side * scale).all())
    assert len(set(grown.anchor_positions)) == grown.num_anchors
    for x, y in grown.anchor_positions:
        assert (x % side, y % side) in set(base.anchor_positions)
    expected = base.num_anchors * scale**2  # same density up to the border
    assert abs(grown.num_anchors - expected) <= 0.5 * expected
    # every other generation parameter is kept, and growing is a no-op at I
    assert grown.motion == base.motion
    assert grown.measurement == base.measurement
    same = base.grown(base.num_agents)
    assert same.replace(name=base.name, description=base.description) == base


def test_grown_rejects_no_agents():
    with pytest.raises(ValueError, match="'num_agents'"):
        Scenario.load('paper_test').grown(0)


@pytest.mark.parametrize('key,value', [
    ('num_agents', 2.5), ('num_agents', '3'), ('num_agents', True),
    ('num_steps', 1.0), ('sigma_v0', '1.0'), ('sigma_v0', None),
    ('prior_var', 10.0), ('prior_var', (1.0, '1', 1.0, 1.0)),
    ('anchor_positions', 5.0), ('anchor_positions', ((0.0, 'x'), )),
    ('name', 7), ('description', 3),
])
def test_wrong_types_name_the_field(key, value):
    with pytest.raises(TypeError, match=f"'{key}' must be"):
        Scenario.load('paper_train').replace(**{key: value})


@pytest.mark.parametrize('change,message', [
    (dict(num_agents=None), r"lacks the fields \['num_agents'\]"),
    (dict(num_agents=2.5), r"'num_agents' must be an integer, got 2.5"),
    (dict(prior_var=10.0), r"'prior_var' must be a list of numbers"),
    (dict(name='..'), r"'name' must be a plain file name"),
    (dict(num_steps=0), r"'num_steps' must be at least 1"),
])
def test_bad_json_scenario_names_the_file_and_field(tmp_path, change,
                                                     message):
    fields = json.loads((importlib.resources.files('tg_nebp.datasets') /
                         'scenarios' / 'paper_test.json').read_text())
    fields.update(change)
    fields = {k: v for k, v in fields.items() if v is not None}
    path = tmp_path / 'bad.json'
    path.write_text(json.dumps(fields))
    with pytest.raises(ValueError, match=rf"scenario '.*bad.json'.*{message}"):
        Scenario.load(path)


def test_missing_or_malformed_json_scenario_names_the_file(tmp_path):
    with pytest.raises(ValueError, match=r"scenario file '.*none.json' does "
                       r"not exist"):
        Scenario.load(tmp_path / 'none.json')
    broken = tmp_path / 'broken.json'
    broken.write_text('{"name": ')
    with pytest.raises(ValueError, match=r"'.*broken.json' is not a valid "
                       r"JSON file"):
        Scenario.load(broken)
    listed = tmp_path / 'list.json'
    listed.write_text('[1, 2]')
    with pytest.raises(ValueError, match='must be a JSON object'):
        Scenario.load(listed)


@pytest.mark.parametrize('name', ['paper_train_nlos', 'paper_test_nlos'])
def test_nlos_scenarios_are_the_paper_networks_with_nlos_links(name):
    nlos = Scenario.load(name)
    clean = Scenario.load(name.replace('_nlos', ''))
    assert nlos.replace(name=clean.name, description=clean.description,
                        measurement=clean.measurement) == clean
    model = nlos.measurement_model
    assert (model.p_nlos, model.bias_mean, model.sigma) == (0.2, 3.0, 1.0)
    data = nlos.replace(num_steps=2).generate(torch.Generator().manual_seed(0))
    check_realization(data, model.features)
    flags = data.edge_attr[:, 1]
    assert set(flags.unique().tolist()) == {0.0, 1.0}
    # one state per pair: both directions of a pair carry the same flag
    state = {}
    for (j, i), flag in zip(data.edge_index.t().tolist(), flags.tolist()):
        assert state.setdefault((min(i, j), max(i, j)), flag) == flag


@pytest.mark.parametrize('split', ['train', 'test'])
def test_sparse_and_wide_prior_scenarios_change_one_thing(split):
    # the regimes of the learned correction: the paper's networks with a
    # 12 m range (fewer links) or a 10 m prior standard deviation
    clean = Scenario.load(f'paper_{split}')
    sparse = Scenario.load(f'paper_{split}_sparse')
    wide = Scenario.load(f'paper_{split}_wide_prior')
    assert sparse.measurement_model.max_range == 12.0
    assert sparse.replace(name=clean.name, description=clean.description,
                          measurement=clean.measurement) == clean
    assert tuple(wide.prior_var) == (100.0, 100.0, 0.01, 0.01)
    assert wide.replace(name=clean.name, description=clean.description,
                        prior_var=clean.prior_var) == clean
    gen = torch.Generator().manual_seed(0)
    short = [s.replace(num_steps=2).generate(gen) for s in (clean, sparse)]
    check_realization(short[1])
    # fewer links than the paper's 20 m at the same positions (same seed)
    assert short[1].edge_index.size(1) < 0.6 * short[0].edge_index.size(1)


# -- 3-D scenarios -----------------------------------------------------------

def test_three_dimensional_scenario_pair():
    test, train = Scenario.load('box3d_test'), Scenario.load('box3d_train')
    assert (test.position_dim, train.position_dim) == (3, 3)
    assert (test.num_agents, test.num_anchors) == (100, 13)
    heights = {p[2] for p in test.anchor_positions}
    assert heights == {0.0, 20.0}
    data = test.replace(num_steps=2).generate(torch.Generator().manual_seed(0))
    check_realization(data)
    assert data.states.shape == (113, 2, 6) and data.prior_mean.shape == (
        113, 6)
    low, high = test.start_box()
    start = data.prior_mean  # within the prior's spread of the box
    assert low.tolist() == [10.0, 10.0, 2.0]
    assert high.tolist() == [90.0, 90.0, 18.0]
    # ranges are 3-D distances plus noise; every pair within range measured
    states = data.states[:, 0].double()
    first = data.edge_time == 0
    src, dst = data.edge_index[:, first]
    distances = (states[src, :3] - states[dst, :3]).norm(dim=-1)
    assert float(distances.max()) <= 20.0 + 1e-4
    noise = data.edge_attr[first, 0].double() - distances
    assert abs(float(noise.mean())) < 0.1 and 0.9 < float(noise.std()) < 1.1
    pairs = torch.cdist(states[:, :3], states[:, :3]) <= 20.0
    pairs.fill_diagonal_(False)
    pairs[:, 100:] = False  # anchors never receive
    assert int(pairs.sum()) == int(first.sum())
    assert bool(torch.isfinite(start).all())


@pytest.mark.parametrize('change,message', [
    (dict(anchor_positions=((0.0, 0.0, 0.0), (1.0, 1.0))),
     'every anchor alike'),
    (dict(anchor_positions=((0.0, 0.0, 0.0, 0.0), )), r'\[x, y, z\]'),
    (dict(prior_var=(1.0, 1.0, 0.1, 0.1)), "'prior_var' must hold 6"),
    (dict(agent_start_low=(1.0, 1.0)), 'one value per axis'),
    (dict(agent_start_low=(1.0, 1.0, 5.0), agent_start_high=(5.0, 5.0, 4.0)),
     'below .* on every axis'),
    (dict(agent_start_low='low'), "'agent_start_low' must be a number"),
])
def test_three_dimensional_fields_are_checked(change, message):
    with pytest.raises((TypeError, ValueError), match=message):
        Scenario.load('box3d_test').replace(**change)


def test_three_dimensional_network_grows_on_the_horizontal_plane():
    grown = Scenario.load('box3d_test').grown(400)
    assert grown.position_dim == 3
    assert {p[2] for p in grown.anchor_positions} == {0.0, 20.0}
    assert grown.agent_start_low == (20.0, 20.0, 2.0)
    assert grown.agent_start_high == (180.0, 180.0, 18.0)
    assert grown.num_anchors > 4 * 13 - 13


def test_a_realization_that_cannot_fit_is_refused_before_any_work():
    scenario = Scenario.load('paper_test')
    needed = scenario.realization_bytes()
    # states alone: 113 nodes x 50 steps x 4 entries in float64 and float32
    assert needed >= 113 * 50 * 4 * 12
    scenario.check_memory(free=needed)
    with pytest.raises(ValueError, match="needs at least .* GiB.*lower "
                       "'num_agents' or 'num_steps'"):
        scenario.check_memory(free=needed - 1)
    with pytest.raises(ValueError, match='1000000000 agents'):
        scenario.replace(num_agents=10**9).generate(torch.Generator())


@pytest.mark.parametrize('changes, message', [
    (dict(sigma_v0=1e300), "'sigma_v0' .* or 'prior_var'"),
    (dict(prior_var=[1e300] * 4), "'sigma_v0' .* or 'prior_var'"),
    (dict(motion=ConstantVelocityDrag(drag=1e300)),
     r'the motion model ConstantVelocityDrag\(.*drag=1e\+300.*\) drives '
     r'the states beyond .* by step 1'),
])
def test_a_generator_that_leaves_float32_blames_its_parameters(changes,
                                                               message):
    scenario = Scenario.load('paper_test').replace(num_agents=5, **changes)
    with pytest.raises(ValueError, match=message):
        scenario.generate(torch.Generator().manual_seed(0))


def test_robots_scenario_generates_odometry_and_bearings():
    scenario = Scenario.load('robots_test').replace(num_steps=15)
    data = scenario.generate(gen(0))
    count = scenario.num_agents
    assert data.states.shape == (data.num_nodes, 15, 3)
    assert data.control.shape == (data.num_nodes, 15, 2)
    assert int(data.position_dim) == 2
    assert bool(torch.isnan(data.control[count:]).all())
    assert not bool(torch.isnan(data.control[:count]).any())
    assert data.edge_attr.size(1) == 2
    heading = data.states[..., 2]
    assert bool(((heading > -math.pi) & (heading <= math.pi)).all())
    # the recorded odometry is the true move plus the model's noise: the
    # driven distance per step within the drive's speeds, give or take
    moved = (data.states[:count, 1:, :2] - data.states[:count, :-1, :2]
             ).norm(dim=-1)
    drive = scenario.drive
    assert float(moved.min()) > drive['speed_low'] * 0.8
    assert float(moved.max()) < drive['speed_high'] * 1.01
    odometry = data.control[:count, 1:, 0]
    assert float((odometry - moved).abs().mean()) < 0.05
    # the same seed, the same realization
    again = scenario.generate(gen(0))
    torch.testing.assert_close(again.control, data.control, rtol=0, atol=0,
                               equal_nan=True)
    assert torch.equal(again.edge_attr, data.edge_attr)


@pytest.mark.parametrize('change,match', [
    (dict(drive=None), "needs a 'drive'"),
    (dict(drive={'speed_low': 0.1}), "'drive' must map"),
    (dict(drive={'speed_low': 0.3, 'speed_high': 0.1, 'turn_sigma': 0.1,
                 'turn_correlation': 0.5, 'turn_back': 0.2}),
     'speed_low <= speed_high'),
    (dict(prior_var=(1.0, 1.0, 1.0, 1.0)), "'prior_var' must hold 3"),
])
def test_robots_scenario_errors(change, match):
    with pytest.raises(ValueError, match=match):
        Scenario.load('robots_test').replace(**change)


def test_a_drive_needs_inputs():
    robots = Scenario.load('robots_test')
    with pytest.raises(ValueError, match="'drive' is for a motion model"):
        Scenario.load('paper_test').replace(drive=robots.drive)
