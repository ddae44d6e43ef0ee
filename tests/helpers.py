r"""Helpers shared by the tests (on the path through pytest's
:obj:`pythonpath` setting): generators, small networks, random snapshots and
stand-ins for the NEBP MLPs."""
import math
import os
import subprocess
import sys
from pathlib import Path

import torch

import tg_nebp
from tg_nebp.datasets import Scenario

PACKAGE_ROOT = str(Path(tg_nebp.__file__).resolve().parents[1])


def gen(seed):
    return torch.Generator().manual_seed(seed)


def tiny_scenario(steps=5):
    r"""Three agents between three anchors."""
    return Scenario(name='tiny', num_agents=3,
                    anchor_positions=((0.0, 0.0), (15.0, 0.0), (7.0, 12.0)),
                    agent_start_low=3.0, agent_start_high=10.0,
                    num_steps=steps)


def random_graph(generator, num_agents, num_anchors, num_particles,
                 edge_prob=0.5, spread=2.0, area=15.0, sigma=1.0,
                 dtype=torch.float64, into_anchor=False):
    r"""A random snapshot: agents first, then anchors (K copies of their
    position); edges ``j -> i`` with i an agent (and, if ``into_anchor``,
    also edges into anchors); ranges = true distance + noise, clamped at
    zero."""
    g = generator
    n = num_agents + num_anchors
    true_pos = area * torch.rand(n, 2, generator=g, dtype=torch.float64)
    particles = torch.randn(n, num_particles, 4, generator=g,
                            dtype=torch.float64)
    particles[..., :2] = true_pos.unsqueeze(1) + spread * particles[..., :2]
    particles[num_agents:] = torch.cat(
        [true_pos[num_agents:], torch.zeros(num_anchors, 2,
                                            dtype=torch.float64)],
        dim=1).unsqueeze(1)
    anchor = torch.arange(n) >= num_agents
    pairs = [(j, i) for i in range(n) for j in range(n)
             if i != j and (into_anchor or not bool(anchor[i]))]
    keep = torch.rand(len(pairs), generator=g) < edge_prob
    pairs = [p for p, k in zip(pairs, keep.tolist()) if k]
    edge_index = torch.tensor(pairs, dtype=torch.long).view(-1, 2).t()
    dist = (true_pos[edge_index[0]] - true_pos[edge_index[1]]).norm(dim=-1)
    noise = sigma * torch.randn(dist.shape, generator=g, dtype=torch.float64)
    edge_attr = (dist + noise).clamp_min(0.0).view(-1, 1)
    log_weights = torch.randn(n, num_particles, generator=g,
                              dtype=torch.float64) - math.log(num_particles)
    return (particles.to(dtype), log_weights.to(dtype), edge_index.contiguous(),
            edge_attr.to(dtype), anchor)


class Const(torch.nn.Module):
    r"""Replaces an MLP by a constant output of :obj:`width` columns."""
    def __init__(self, width, value):
        super().__init__()
        self.width, self.value = width, value

    def forward(self, x):
        return x.new_full((x.size(0), self.width), self.value)


class Shift(torch.nn.Module):
    r"""Wraps an MLP and adds a constant to its output (keeps its
    parameters in the graph)."""
    def __init__(self, module, offset):
        super().__init__()
        self.module, self.offset = module, offset

    def forward(self, x):
        return self.module(x) + self.offset


def mixed_k_checkpoint(path):
    r"""A checkpoint whose config says K = 8 and whose weights are sized for
    K = 16 (a foreign or tampered file)."""
    from tg_nebp import NEBP
    from tg_nebp.training import save_checkpoint
    save_checkpoint(path, NEBP(num_particles=8))
    state = torch.load(path, weights_only=True)
    state['model'] = NEBP(num_particles=16).state_dict()
    torch.save(state, path)
    return path


def torchrun(*args, timeout=120):
    r"""Runs :obj:`torchrun` with two processes on a free port, single
    threaded, importing this tg_nebp; returns its standard output."""
    path = [PACKAGE_ROOT] + os.environ.get('PYTHONPATH', '').split(os.pathsep)
    env = dict(os.environ, OMP_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join(filter(None, path)))
    done = subprocess.run(
        [sys.executable, '-m', 'torch.distributed.run', '--standalone',
         '--nproc_per_node=2', *map(str, args)], env=env,
        capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout
