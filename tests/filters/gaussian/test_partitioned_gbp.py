r"""Gaussian BP and fixed-lag Gaussian BP with one network's agents spread
over the ranks of a :obj:`torchrun` job (gloo): every rank's agents get
what one process gives them, bit for bit, with 2 and 4 ranks. Run as a
script by :obj:`torchrun`, this file is the worker."""
import sys
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from torch_geometric.data import Batch

from tg_nebp.filters import (FixedLagGaussianBP, GaussianBP, LinkSearch,
                             NoiseAdaptation, PartitionedFixedLagGaussianBP,
                             PartitionedGaussianBP, Smoothed, partition,
                             strips)
from tg_nebp.models import GaussianRange

from helpers import gen, tiny_scenario, torchrun


def network():
    # 60 agents on the tiny scenario's area grown at its density: links
    # cross every strip border
    scenario = tiny_scenario(steps=5).grown(60)
    return scenario, scenario.generate(gen(4))


#: A tolerance that takes many iterations
OPTIONS = dict(num_iterations=40, tolerance=1e-4)
#: The window of the fixed-lag runs, and the runs: name, wrapper, options
#: (the residual schedule's, and a window whose oldest step is settled)
LAG = 3
WINDOWED = (('lag', lambda tracker: tracker, {}),
            ('smoothed', Smoothed, {}),
            ('residual', lambda tracker: tracker, dict(schedule='residual')),
            ('settled', Smoothed, dict(iterated=2)))


def adapting(scenario) -> dict:
    # the options of the noise adaptation's runs
    sigma = scenario.measurement_model.sigma / 3
    return dict(measurement=GaussianRange(sigma=sigma),
                noise_adaptation=NoiseAdaptation())


def tracked(path: Path, rank: int) -> None:
    scenario, data = network()
    owner = strips(data, dist.get_world_size())
    part, plan = partition(data, owner, rank, dist.get_world_size())
    tracker = PartitionedGaussianBP.recommended(
        plan=plan, motion=scenario.motion_model,
        measurement=scenario.measurement_model, **OPTIONS)
    out = tracker(part)
    # the noise adaptation, of a model whose noise is 3 times too small
    # (every agent's scale above 1): an owned agent's scale sums all its
    # links in the order one process sums them
    adapted = PartitionedGaussianBP.recommended(
        plan=plan, motion=scenario.motion_model, **adapting(scenario),
        **OPTIONS)(part)
    # the stop is decided over all ranks: each sees the largest move of
    # any (here every rank's own move is its number)
    moves = tracker.largest_moves(torch.tensor([float(rank)]),
                                  torch.zeros(1, dtype=torch.long), 1)
    # with a window: its filtered and its smoothed estimates, and the
    # residual schedule's
    windowed = {}
    for name, wrap, options in WINDOWED:
        smoother = wrap(PartitionedFixedLagGaussianBP.recommended(
            plan=plan, lag=LAG, motion=scenario.motion_model,
            measurement=scenario.measurement_model, **options, **OPTIONS))
        tracked = smoother(part)
        windowed[name] = (tracked.mean[plan.owned], tracked.cov[plan.owned])
    torch.save(dict(nodes=plan.nodes[plan.owned], moves=moves,
                    halo=int((~plan.owned).sum()),
                    mean=out.mean[plan.owned], cov=out.cov[plan.owned],
                    adapted=(adapted.mean[plan.owned],
                             adapted.cov[plan.owned]),
                    windowed=windowed),
               path / f'rank{rank}.pt')


@pytest.mark.parametrize('ranks', [2, 4])
def test_ranks_track_their_agents_as_one_process(tmp_path, ranks):
    torchrun(__file__, tmp_path, processes=ranks, timeout=120)
    scenario, data = network()
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    expected = GaussianBP.recommended(**models, **OPTIONS)(data)
    adapted = GaussianBP.recommended(motion=scenario.motion_model,
                                     **adapting(scenario), **OPTIONS)(data)
    windowed = {name: wrap(FixedLagGaussianBP.recommended(
        lag=LAG, **options, **models, **OPTIONS))(data)
        for name, wrap, options in WINDOWED}
    seen = []
    for rank in range(ranks):
        part = torch.load(tmp_path / f'rank{rank}.pt')
        assert part['halo'] > 0  # the borders are crossed
        assert part['moves'].tolist() == [ranks - 1.0]
        nodes = part['nodes']
        # bit for bit on every CPU path, for the reason a batch is each
        # graph alone (see assert_batch_equals_alone): a rank runs the same
        # operations on its nodes' rows, every node's messages summed in
        # the same order as in one process
        assert torch.equal(part['mean'], expected.mean[nodes])
        assert torch.equal(part['cov'], expected.cov[nodes])
        assert torch.equal(part['adapted'][0], adapted.mean[nodes])
        assert torch.equal(part['adapted'][1], adapted.cov[nodes])
        for name, (mean, cov) in part['windowed'].items():
            assert torch.equal(mean, windowed[name].mean[nodes]), name
            assert torch.equal(cov, windowed[name].cov[nodes]), name
        seen.append(nodes)
    # every node is owned once
    assert torch.equal(torch.cat(seen).sort().values,
                       torch.arange(data.num_nodes))


def test_a_relocation_is_refused_where_partitioned():
    # a rank would search halo agents whose links it sees in part, stagger
    # the searches by its own indices and keep its relocations: the ranks
    # no longer tracked as one process (6.8e-5 m apart on 2 ranks)
    scenario, data = network()
    owner = strips(data, 2)
    part, plan = partition(data, owner, 0, 2)
    for make in (PartitionedGaussianBP, PartitionedFixedLagGaussianBP):
        options = dict(lag=LAG) if make is PartitionedFixedLagGaussianBP \
            else {}
        with pytest.raises(ValueError, match="'relocation' is not "
                           "available to a partitioned tracker"):
            make.recommended(plan=plan, relocation=LinkSearch(), **options)
        tracker = make.recommended(plan=plan, **options)
        with pytest.raises(ValueError, match="'relocation' is not"):
            tracker.relocate_with(LinkSearch())


def test_a_rank_without_an_agent_is_refused_up_front():
    # 4 ranks on a network of 3 agents, or strips that leave a rank only
    # anchors: every rank gets the same error, naming the idle ranks,
    # before any collective
    data = tiny_scenario(steps=2).generate(gen(1))  # 3 agents, 3 anchors
    for ranks in (4, 6):
        owner = strips(data, ranks)
        for rank in range(ranks):
            with pytest.raises(ValueError, match=rf"ranks \[.*\] of {ranks} "
                               rf"own no agent \(the network has 6 nodes, "
                               rf"3 of them agents\)"):
                partition(data, owner, rank, ranks)
    with pytest.raises(ValueError, match=r"must lie in 0-1 \(2 ranks\)"):
        partition(data, strips(data, 3), 0, 2)
    part, plan = partition(data, torch.tensor([0, 1, 2, 0, 1, 2]), 1, 3)
    assert int(plan.owned.sum()) == 2


def test_partition_keeps_the_order_and_plans_both_sides():
    _, data = network()
    owner = strips(data, 3)
    parts = [partition(data, owner, rank) for rank in range(3)]
    for rank, (part, plan) in enumerate(parts):
        assert torch.equal(plan.nodes, plan.nodes.sort().values)
        # every link of an owned node, and only those
        mine = owner == rank
        src, dst = data.edge_index
        assert part.edge_index.size(1) == int((mine[src] | mine[dst]).sum())
        for other in range(3):
            if other == rank:
                continue
            # what one side sends is what the other receives, row by row
            sent = plan.nodes[plan.send[other]]
            received = parts[other][1].nodes[parts[other][1].receive[rank]]
            assert torch.equal(sent, received)


def test_a_partition_carries_the_robots_inputs_and_layout():
    # a rank's part of a robots network: its nodes' odometry and the
    # layout, so its Gaussian BP predicts as the whole network's does
    from tg_nebp.datasets import Scenario
    scenario = Scenario.load('robots_train').replace(num_steps=3)
    data = scenario.generate(gen(0))
    owner = strips(data, 2)
    for rank in range(2):
        part, plan = partition(data, owner, rank)
        torch.testing.assert_close(part.control, data.control[plan.nodes],
                                   rtol=0, atol=0, equal_nan=True)
        assert int(part.position_dim) == 2
        GaussianBP(motion=scenario.motion_model,
                   measurement=scenario.measurement_model).check(part)


def test_a_batch_is_refused():
    _, data = network()
    part, plan = partition(data, strips(data, 2), 0)
    tracker = PartitionedGaussianBP(plan)
    with pytest.raises(ValueError, match='one network, not a batch'):
        tracker(Batch.from_data_list([part]))


if __name__ == '__main__':  # the worker of torchrun
    dist.init_process_group('gloo')
    try:
        tracked(Path(sys.argv[1]), dist.get_rank())
    finally:
        dist.destroy_process_group()
