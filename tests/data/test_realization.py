import numpy as np
import pytest
import torch
from torch_geometric.data import Batch
from torch_geometric.loader import DataLoader

from tg_nebp.data import Realization, num_steps_of
from tg_nebp.datasets import Scenario

T = 5


def small_scenario():
    return Scenario(name='tiny', num_agents=3,
                    anchor_positions=((0.0, 0.0), (10.0, 0.0)),
                    agent_start_low=0.0, agent_start_high=10.0, num_steps=T)


@pytest.fixture(scope='module')
def pair():
    a = Scenario.load('paper_train').replace(num_steps=T).generate(
        torch.Generator().manual_seed(0))
    b = small_scenario().generate(torch.Generator().manual_seed(1))
    return a, b


def edge_set(edge_index, edge_attr):
    return sorted(zip(edge_index[0].tolist(), edge_index[1].tolist(),
                      edge_attr[:, 0].tolist()))


def test_snapshot_single(pair):
    data = pair[0]
    assert data.num_time_steps == T
    for t in range(T):
        snap = data.snapshot(t)
        mask = [int(data.edge_time[e]) == t for e in range(data.num_edges)]
        mask = torch.tensor(mask)
        assert int(mask.sum()) > 0
        assert torch.equal(snap.edge_index, data.edge_index[:, mask])
        assert torch.equal(snap.edge_attr, data.edge_attr[mask])
        assert torch.equal(snap.anchor, data.anchor)
        assert torch.equal(snap.pos, data.states[:, t, :2])
        assert snap.num_nodes == data.num_nodes
        assert getattr(snap, 'batch', None) is None
    assert sum(data.snapshot(t).num_edges for t in range(T)) == data.num_edges


@pytest.mark.parametrize('t', [-1, T, T + 3])
def test_snapshot_out_of_range(pair, t):
    with pytest.raises(ValueError, match="'t'"):
        pair[0].snapshot(t)


@pytest.mark.parametrize('t', [1.5, 1.0, True, '1', torch.tensor(1.0),
                               torch.tensor([0, 1])])
def test_snapshot_needs_an_integer_time_index(pair, t):
    # 1.5 gave an IndexError, or silently no edges without states
    for data in (pair[0].clone(), pair[1].clone()):
        del data.states
        with pytest.raises(TypeError, match="'t' must be an integer"):
            data.snapshot(t)


def test_snapshot_takes_numpy_and_tensor_integers(pair):
    expected = pair[0].snapshot(1)
    for t in (np.int64(1), torch.tensor(1), torch.tensor([1])):
        assert torch.equal(pair[0].snapshot(t).edge_index,
                           expected.edge_index)


def test_snapshot_without_states(pair):
    data = pair[1].clone()
    del data.states
    snap = data.snapshot(0)
    assert getattr(snap, 'pos', None) is None


def loader_batch(pair):
    loader = DataLoader(list(pair), batch_size=2, shuffle=False)
    batch = next(iter(loader))
    assert isinstance(batch, Realization)
    return batch


def test_batch_snapshot_matches_graphs_with_offsets(pair):
    a, b = pair
    batch = loader_batch(pair)
    assert batch.num_nodes == a.num_nodes + b.num_nodes
    assert batch.num_time_steps == T
    offset = a.num_nodes
    for t in range(T):
        snap = batch.snapshot(t)
        # against a manual mask on the batch
        mask = batch.edge_time == t
        assert torch.equal(snap.edge_index, batch.edge_index[:, mask])
        assert torch.equal(snap.edge_attr, batch.edge_attr[mask])
        # against the graphs' own snapshots, shifted by the node offsets
        sa, sb = a.snapshot(t), b.snapshot(t)
        expected = edge_set(sa.edge_index, sa.edge_attr) + edge_set(
            sb.edge_index + offset, sb.edge_attr)
        assert edge_set(snap.edge_index, snap.edge_attr) == sorted(expected)
        # edges never cross graphs
        src_graph = snap.batch[snap.edge_index[0]]
        assert torch.equal(src_graph, snap.batch[snap.edge_index[1]])
        assert torch.equal(snap.batch, torch.cat([
            torch.zeros(a.num_nodes, dtype=torch.long),
            torch.ones(b.num_nodes, dtype=torch.long)]))
        assert snap.ptr.tolist() == [0, a.num_nodes, a.num_nodes + b.num_nodes]
        assert torch.equal(snap.pos, torch.cat([sa.pos, sb.pos]))
        assert torch.equal(snap.anchor, torch.cat([a.anchor, b.anchor]))


def check_edges_by_step(data):
    steps = data.edges_by_step()
    assert len(steps) == T
    for t, (edge_index, edge_attr) in enumerate(steps):
        snap = data.snapshot(t)
        assert edge_index.size(1) == edge_attr.size(0) == snap.num_edges
        # sorted by receiver
        assert bool((edge_index[1, 1:] >= edge_index[1, :-1]).all())
        # the same edges (with their ranges) as the snapshot
        assert edge_set(edge_index, edge_attr) == edge_set(
            snap.edge_index, snap.edge_attr)


def test_edges_by_step_single(pair):
    check_edges_by_step(pair[0])
    check_edges_by_step(pair[1])


def test_edges_by_step_batch(pair):
    check_edges_by_step(loader_batch(pair))


def test_edges_by_step_shuffled_and_empty_steps():
    # edges stored out of time order, one time step without edges
    data = Realization(
        edge_index=torch.tensor([[1, 0, 2, 0, 2], [0, 2, 0, 1, 1]]),
        edge_attr=torch.arange(5, dtype=torch.float).view(-1, 1),
        edge_time=torch.tensor([2, 0, 2, 2, 0]),
        anchor=torch.zeros(3, dtype=torch.bool),
        prior_mean=torch.zeros(3, 4), prior_cov=torch.zeros(3, 4, 4),
        num_steps=4, num_nodes=3)
    steps = data.edges_by_step()
    assert len(steps) == 4
    assert steps[0][0].tolist() == [[2, 0], [1, 2]]
    assert steps[0][1][:, 0].tolist() == [4.0, 1.0]
    assert steps[1][0].shape == (2, 0) and steps[3][0].shape == (2, 0)
    assert steps[2][0].tolist() == [[1, 2, 0], [0, 0, 1]]
    assert steps[2][1][:, 0].tolist() == [0.0, 2.0, 3.0]


def test_batch_num_steps_mismatch_raises(pair):
    a = pair[0].clone()
    other = small_scenario().replace(num_steps=T + 1).generate(
        torch.Generator().manual_seed(2))
    del a.states, other.states  # [N, T, 4] would not concatenate
    batch = Batch.from_data_list([a, other])
    assert batch.num_steps.tolist() == [T, T + 1]
    with pytest.raises(ValueError, match='num_steps'):
        batch.snapshot(0)
    with pytest.raises(ValueError, match='num_steps'):
        batch.edges_by_step()
    with pytest.raises(ValueError, match='num_steps'):
        num_steps_of(batch)


def test_generated_loaded_and_sliced_realizations_batch_together(tmp_path):
    from torch_geometric.loader import DataLoader

    from tg_nebp import CooperativeLocalizationDataset, Scenario
    scenario = Scenario.load('paper_train').replace(num_steps=3)
    single = CooperativeLocalizationDataset(str(tmp_path), scenario, 1, 0,
                                            log=False)
    several = CooperativeLocalizationDataset(str(tmp_path), scenario, 2, 1,
                                             log=False)
    generated = scenario.generate(torch.Generator().manual_seed(5))
    batch = next(iter(DataLoader([single[0], generated, several[1]],
                                 batch_size=3)))
    assert batch.num_steps.tolist() == [3, 3, 3]
    assert batch.num_nodes == 3 * 30
    assert batch.snapshot(2).edge_index.size(1) == sum(
        int((r.edge_time == 2).sum()) for r in (single[0], generated,
                                                several[1]))
