r"""Helpers shared by the tests (on the path through pytest's
:obj:`pythonpath` setting): generators, small networks, random snapshots,
stand-ins for the NEBP MLPs and randomized learned corrections."""
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

import tg_nebp
from tg_nebp.datasets import Scenario
from tg_nebp.filters import StepOutput, Tracker
from tg_nebp.models import GaussianRange

PACKAGE_ROOT = str(Path(tg_nebp.__file__).resolve().parents[1])


def gen(seed):
    return torch.Generator().manual_seed(seed)


def tiny_scenario(steps=5):
    r"""Three agents between three anchors."""
    return Scenario(name='tiny', num_agents=3,
                    anchor_positions=((0.0, 0.0), (15.0, 0.0), (7.0, 12.0)),
                    agent_start_low=3.0, agent_start_high=10.0,
                    num_steps=steps)


def assert_symmetric_positive_definite(cov, atol=0.0):
    r"""Covariances :math:`(*, S, S)` symmetric (to :obj:`atol`) with every
    eigenvalue above zero."""
    torch.testing.assert_close(cov, cov.transpose(-1, -2), rtol=0,
                               atol=atol)
    assert bool((torch.linalg.eigvalsh(cov) > 0).all())


def assert_batch_equals_alone(method, fields=('mean', 'cov'), rtol=1e-10,
                              atol=1e-12):
    r"""A deterministic :obj:`method` (a tracker, or the bound) on a batch
    of two tiny graphs of different sizes gives, field by field of its
    output (or the output itself with :obj:`fields` :obj:`None`), each
    graph's result alone, concatenated.

    With :obj:`rtol` = :obj:`atol` = 0 (the Gaussian trackers, whose
    documentation promises it) this is bit for bit on every CPU kernel
    path, not one CPU's luck: each graph's rows go through the same
    operations in the same order in a batch as alone (elementwise
    arithmetic, which IEEE rounding gives the same wherever an element sits
    in a tensor, and reductions over one node's own entries; no sum runs
    across graphs, and converged graphs leave the iterations with the
    others renumbered in order). Checked under both the AVX2 and the
    generic kernels (:obj:`ATEN_CPU_CAPABILITY=default`)."""
    from torch_geometric.data import Batch
    scenario = tiny_scenario(steps=4)
    small = scenario.generate(gen(1))
    large = scenario.replace(num_agents=5).generate(gen(2))
    alone = [method(d) for d in (small, large)]
    batched = method(Batch.from_data_list([small, large]))
    for field in fields or (None, ):
        def pick(out):
            return out if field is None else getattr(out, field)
        torch.testing.assert_close(pick(batched),
                                   torch.cat([pick(a) for a in alone]),
                                   rtol=rtol, atol=atol)


def assert_same_minimum(mean, cov, ref_mean, ref_cov, scale=100.0):
    r"""Two converged iterative solves of one nonlinear least-squares
    problem (:obj:`mean` :math:`(*, S)` and :obj:`cov` :math:`(*, S, S)`
    against the reference :obj:`ref_mean` and :obj:`ref_cov`, e.g. the
    batch :class:`~tg_nebp.filters.CentralizedSmoother`'s) found the same
    minimum, to the precision that the minimum is defined by.

    The batch smoother stops when a Gauss-Newton step no longer decreases
    the cost :math:`f`, and :math:`f` is resolved only to about
    :math:`\epsilon |f|` (:math:`\epsilon` the dtype's machine epsilon).
    Near the minimum :math:`f(\mathbf{x}^* + \mathbf{d}) - f(\mathbf{x}^*)
    \approx \mathbf{d}^\top \mathbf{H} \mathbf{d} / 2`, so any
    :math:`\mathbf{d}` with :math:`\mathbf{d}^\top \mathbf{H} \mathbf{d}
    \lesssim 2 \epsilon |f|` is a minimum as good as any other; by
    Cauchy-Schwarz, :math:`|d_i| \le \sqrt{S_{ii}} \sqrt{\mathbf{d}^\top
    \mathbf{H} \mathbf{d}}` with :math:`\mathbf{S} = \mathbf{H}^{-1}` the
    posterior covariance, so each state is located only to about
    :math:`\sqrt{2 \epsilon |f|}` of its posterior standard deviation
    :math:`\sqrt{S_{ii}}`, whichever CPU kernels ran (the vectorized
    paths round the cost differently, and two solves that stop at
    different iterates are both right). The means are compared in units of
    the reference's posterior standard deviations with the tolerance
    :math:`C \sqrt{\epsilon}`, :obj:`scale` :math:`C = 100` covering
    :math:`\sqrt{2 |f|}` for costs up to 5,000 (the tests' are below 500:
    about :math:`1.5 \cdot 10^{-6}` standard deviations in float64, where
    the solves differ by up to :math:`1.2 \cdot 10^{-7}`). The
    covariance is the inverse Hessian at the point reached, so it moves by
    its derivative times that displacement: relative to
    :math:`\sqrt{S_{ii} S_{jj}}` (a correlation's units) by the same order
    where the Jacobians change over more than a standard deviation, and
    it is compared so. A solve that misses the minimum is off by far more
    (the incremental smoother on the robots: a motion Jacobian off by
    :math:`10^{-6}` relative, :math:`10^{-5}` standard deviations; one
    round of relinearization every 5 steps, 0.16)."""
    tol = scale * math.sqrt(torch.finfo(ref_mean.dtype).eps)
    std = ref_cov.diagonal(dim1=-2, dim2=-1).sqrt()
    torch.testing.assert_close(
        (mean - ref_mean) / std, torch.zeros_like(std), rtol=0, atol=tol,
        msg=lambda m: 'means in posterior standard deviations: ' + m)
    torch.testing.assert_close(
        (cov - ref_cov) / (std.unsqueeze(-1) * std.unsqueeze(-2)),
        torch.zeros_like(ref_cov), rtol=0, atol=tol,
        msg=lambda m: 'covariances in correlation units: ' + m)


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


def torchrun(*args, timeout=120, check=True, processes=2):
    r"""Runs :obj:`torchrun` with :obj:`processes` processes on a free
    port, single threaded, importing this tg_nebp; returns its standard
    output (with :obj:`check`, which asserts success), or else the
    completed process."""
    # (and these helpers, for a worker in a subfolder of the tests)
    path = [PACKAGE_ROOT, os.path.dirname(os.path.abspath(__file__))] + \
        os.environ.get('PYTHONPATH', '').split(os.pathsep)
    env = dict(os.environ, OMP_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join(filter(None, path)))
    done = subprocess.run(
        [sys.executable, '-m', 'torch.distributed.run', '--standalone',
         f'--nproc_per_node={processes}', *map(str, args)], env=env,
        capture_output=True, text=True, timeout=timeout)
    if not check:
        return done
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout


def linear_offset_model():
    r"""A measurement model that is linear in the states with Gaussian
    noise, for the tests that compare against a Kalman filter: agent
    :math:`i` measures the displacement :math:`\mathbf{p}_j -
    \mathbf{p}_i` of its neighbour plus a constant offset (validation wants
    a non-negative first link feature) plus :math:`\mathcal{N}(\mathbf{0},
    \sigma^2 \mathbf{I})`. Its Fisher information is the closed form
    :math:`\mathbf{H}^\top \mathbf{H} / \sigma^2`. Registered once per
    test session."""
    from tg_nebp.models import MODELS
    if 'test-linear-offset' in MODELS['measurement']:
        return MODELS['measurement']['test-linear-offset']
    from tg_nebp.models import GaussianRange, MeasurementModel

    class LinearOffset(MeasurementModel, name='test-linear-offset'):
        features = ('offset_dx', 'offset_dy')
        generated_features = features
        state_entries = (0, 1)
        OFFSET = 1000.0

        def __init__(self, sigma=0.5, max_range=20.0):
            self.sigma, self.max_range = sigma, max_range

        def params(self):
            return dict(sigma=self.sigma, max_range=self.max_range)

        def log_likelihood(self, z, sender, receiver):
            residual = (z[:, None, :2] - self.OFFSET -
                        (sender[..., :2] - receiver[..., :2]))
            return (-0.5 * residual.square().sum(-1) / self.sigma**2 -
                    2 * math.log(self.sigma * math.sqrt(2 * math.pi)))

        def connect(self, pos, receiver):
            return GaussianRange(max_range=self.max_range).connect(
                pos, receiver)

        def sample_features(self, states_j, states_i, link_state,
                            edge_index, generator=None):
            noise = torch.randn(states_j.shape[:-1] + (2, ),
                                dtype=states_j.dtype, generator=generator)
            return (states_j[:, :2] - states_i[:, :2] + self.OFFSET +
                    self.sigma * noise)

        def fisher_information(self, z, sender, receiver, generator=None):
            dim = sender.size(-1)
            h = torch.zeros(2, 2 * dim, dtype=sender.dtype)
            h[:, :2] = torch.eye(2)
            h[:, dim:dim + 2] = -torch.eye(2)
            return (h.t() @ h / self.sigma**2).expand(sender.size(0), -1, -1)

    return LinearOffset


def linear_kalman_filter(data, motion, measurement, inflation=1.0,
                         marginal=False, record=None):
    r"""The Kalman filter of a realization with a linear motion model and
    :func:`linear_offset_model`'s measurements, written independently of
    the library: one joint state over the agents, float64 numpy, one
    vector measurement at a time in a plain loop, Joseph-form updates; the
    covariance multiplied by :obj:`inflation` before every prediction but
    the first, in every generalized eigen-direction of (the step's
    prediction, the covariance) no further than that prediction (scipy's
    generalized eigh; one agent: Gaussian BP's bounded inflation). A
    realization's known inputs (:obj:`control`) enter as
    :math:`\mathbf{F} \mathbf{x} + f(\mathbf{0}, \mathbf{u})` (the model
    is linear). With :obj:`marginal`, the cross-agent covariances are
    dropped after every step (what a filter of marginals keeps). Returns
    the agents' means :math:`(A, T, S)`, their marginal covariances
    :math:`(A, T, S, S)` and the agents' node indices. Every step's joint
    prediction and update (:obj:`x_pred`, :obj:`P_pred`, :obj:`x`,
    :obj:`P`) and the joint transition :obj:`F` are appended to the list
    :obj:`record` as a dict, if given (for
    :func:`linear_rts_smoother`)."""
    import numpy as np
    anchor = data.anchor.numpy()
    agents = np.flatnonzero(~anchor)
    index = {int(n): a for a, n in enumerate(agents)}
    size = data.prior_mean.size(1)
    count = len(agents)
    # the linear transition's matrices, read off the model at one state
    zero = torch.zeros(1, size, dtype=torch.float64)
    F = motion.jacobian(zero)[0].numpy()
    Q = motion.noise_covariance(zero)[0].numpy()
    x = data.prior_mean.double().numpy()[agents].reshape(-1)
    P = np.zeros((count * size, count * size))
    for a, n in enumerate(agents):
        P[a * size:(a + 1) * size, a * size:(a + 1) * size] = \
            data.prior_cov.double().numpy()[n]
    known = data.prior_mean.double().numpy()
    means, covs = [], []
    sigma2 = measurement.sigma**2
    for t in range(int(data.num_steps)):
        if t > 0 and inflation != 1.0:
            import scipy.linalg
            lam, V = scipy.linalg.eigh(predicted, P)
            Vinv = np.linalg.inv(V)
            P = Vinv.T @ np.diag(np.minimum(inflation, np.maximum(lam, 1.0))
                                 ) @ Vinv
        Fj = np.kron(np.eye(count), F)
        x = Fj @ x
        control = getattr(data, 'control', None)
        if control is not None:  # the inputs' move, f(0, u)
            x = x + motion.mean(torch.zeros(count, size, dtype=torch.float64),
                                control=control[agents, t].double()
                                ).numpy().reshape(-1)
        P = Fj @ P @ Fj.T + np.kron(np.eye(count), Q)
        predicted = P
        x_pred = x.copy()
        for e in np.flatnonzero(data.edge_time.numpy() == t):
            j, i = (int(v) for v in data.edge_index[:, e])
            z = data.edge_attr[e, :2].double().numpy() - measurement.OFFSET
            H = np.zeros((2, count * size))
            H[:, index[i] * size:index[i] * size + 2] = -np.eye(2)
            constant = np.zeros(2)
            if anchor[j]:
                constant = known[j, :2]
            else:
                H[:, index[j] * size:index[j] * size + 2] = np.eye(2)
            S = H @ P @ H.T + sigma2 * np.eye(2)
            K = P @ H.T @ np.linalg.inv(S)
            x = x + K @ (z - H @ x - constant)
            A = np.eye(count * size) - K @ H
            P = A @ P @ A.T + sigma2 * K @ K.T
        if marginal:
            P = np.kron(np.eye(count), np.ones((size, size))) * P
        if record is not None:
            record.append(dict(x_pred=x_pred, P_pred=predicted, x=x.copy(),
                               P=P.copy(), F=Fj))
        means.append(x.reshape(count, size).copy())
        covs.append(np.stack([P[a * size:(a + 1) * size,
                                a * size:(a + 1) * size]
                              for a in range(count)]))
    return (np.stack(means, 1), np.stack(covs, 1), agents)


def tree_realization(steps=4):
    r"""Two agents each measured by its own anchor at every step, measuring
    each other at step 1 only (:func:`linear_scenario`'s linear Gaussian
    links): the space-time graph is a tree (the two time chains joined by
    one factor), where Gaussian BP is exact. Returns the scenario and the
    realization."""
    scenario = linear_scenario(steps=steps, num_agents=2)
    data = scenario.generate(gen(6))
    own = {0: 2, 1: 3}
    edges, attrs, times = [], [], []
    for t in range(steps):
        links = [(own[0], 0), (own[1], 1)] + ([(1, 0), (0, 1)] if t == 1
                                              else [])
        for j, i in sorted(links, key=lambda link: link[1]):
            noise = 0.5 * torch.randn(2, dtype=torch.float64,
                                      generator=gen(100 * t + 10 * j + i))
            attrs.append(data.states[j, t, :2] - data.states[i, t, :2] +
                         scenario.measurement_model.OFFSET + noise)
            edges.append((j, i))
            times.append(t)
    out = data.clone()
    out.edge_index = torch.tensor(edges).t()
    out.edge_attr = torch.stack(attrs)
    out.edge_time = torch.tensor(times)
    return scenario, out


def linear_rts_smoother(data, motion, measurement, lag=None):
    r"""The Rauch-Tung-Striebel smoother of the same problem as
    :func:`linear_kalman_filter`, written independently of the library:
    the filter's joints, then for every step :math:`t` a backward pass
    from step :math:`t + L - 1` (the sequence's last at most; from its
    last with :obj:`lag=None`), :math:`\mathbf{G} = \mathbf{P}_k
    \mathbf{F}^\top (\mathbf{P}^-_{k+1})^{-1}`, in numpy. Returns the
    agents' smoothed means :math:`(A, T, S)`, marginal covariances
    :math:`(A, T, S, S)` and node indices."""
    import numpy as np
    record = []
    _, _, agents = linear_kalman_filter(data, motion, measurement,
                                        record=record)
    size = data.prior_mean.size(1)
    count = len(agents)
    steps = len(record)
    means, covs = [], []
    for t in range(steps):
        last = steps - 1 if lag is None else min(t + lag - 1, steps - 1)
        x, P = record[last]['x'], record[last]['P']
        for k in range(last - 1, t - 1, -1):
            ahead = record[k + 1]
            G = record[k]['P'] @ ahead['F'].T @ np.linalg.inv(ahead['P_pred'])
            x = record[k]['x'] + G @ (x - ahead['x_pred'])
            P = record[k]['P'] + G @ (P - ahead['P_pred']) @ G.T
        means.append(x.reshape(count, size))
        covs.append(np.stack([P[a * size:(a + 1) * size,
                                a * size:(a + 1) * size]
                              for a in range(count)]))
    return np.stack(means, 1), np.stack(covs, 1), agents


def assert_kalman_filter_and_smoother(smoother, data, motion, measurement,
                                      lag=None):
    r"""A smoother on a linear-Gaussian realization: its filtered steps are
    :func:`linear_kalman_filter`'s and its smoothed ones
    (:class:`~tg_nebp.filters.Smoothed`, every step once, in order) are
    :func:`linear_rts_smoother`'s at :obj:`lag`, means and covariances;
    the anchors' smoothed covariances are zero."""
    import numpy as np
    from tg_nebp.filters import Smoothed
    means, covs, agents = linear_kalman_filter(data, motion, measurement)
    out = smoother(data)
    np.testing.assert_allclose(out.mean[agents].numpy(), means, rtol=1e-9,
                               atol=1e-9)
    np.testing.assert_allclose(out.cov[agents].numpy(), covs, rtol=1e-9,
                               atol=1e-12)
    means, covs, _ = linear_rts_smoother(data, motion, measurement, lag)
    steps = list(Smoothed(smoother).steps(data))
    assert [s.t for s in steps] == list(range(out.mean.size(1)))
    mean = torch.stack([s.mean for s in steps], 1)
    cov = torch.stack([s.cov for s in steps], 1)
    np.testing.assert_allclose(mean[agents].numpy(), means, rtol=1e-9,
                               atol=1e-9)
    np.testing.assert_allclose(cov[agents].numpy(), covs, rtol=1e-9,
                               atol=1e-12)
    assert cov[data.anchor].abs().max() == 0


def linear_scenario(steps=4, num_agents=4, sigma=0.5):
    r"""A small network of :func:`linear_offset_model` measurements and
    linear (drag-free) motion."""
    from tg_nebp.models import ConstantVelocity
    return Scenario(name='linear', num_agents=num_agents,
                    anchor_positions=((0.0, 0.0), (12.0, 0.0)),
                    agent_start_low=2.0, agent_start_high=10.0,
                    num_steps=steps, motion=ConstantVelocity(0.1),
                    measurement=linear_offset_model()(sigma))


def simulate_robots(motion, measurement, true_control, anchors, start,
                    prior_var, seed=0):
    r"""A realization of robots moved by :obj:`motion`'s own draws with
    the true inputs :obj:`true_control` :math:`(A, T, C)` from the true
    states :obj:`start` :math:`(A, S)`, measured by :obj:`measurement`
    (links by its :meth:`connect_states`) to the anchors at
    :obj:`anchors` :math:`(M, D)` and each other; the inputs recorded are
    the true ones, the prior centred on the
    truth with the variances :obj:`prior_var` :math:`(S)`."""
    from tg_nebp.data import Realization
    from tg_nebp.models import resolve_models
    motion, measurement = resolve_models(motion, measurement)
    g = gen(seed)
    count, steps, _ = true_control.shape
    size = start.size(1)
    anchor_states = torch.cat([anchors, anchors.new_zeros(
        anchors.size(0), size - anchors.size(1))], 1).double()
    anchor = torch.arange(count + anchors.size(0)) >= count
    state = start.double()
    states, edge_index, edge_attr, edge_time = [], [], [], []
    # the links' own state (NLOS or not), for the models that have one
    links = measurement.sample_links(count + anchors.size(0), g)
    for t in range(steps):
        if t:
            links = measurement.step_links(links, g)
        state = motion.sample(state, g, control=true_control[:, t].double())
        # the truth stored with its angles wrapped, as a report is
        every = motion.layout(size).wrap(torch.cat([state, anchor_states]))
        edges = measurement.connect_states(every, ~anchor)
        states.append(every)
        edge_index.append(edges)
        edge_attr.append(measurement.sample_features(
            every[edges[0]], every[edges[1]], links, edges, g))
        edge_time.append(torch.full((edges.size(1), ), t))
    prior_cov = torch.diag_embed(torch.tensor(prior_var).double().expand(
        count + anchors.size(0), size)).clone()
    prior_cov[anchor] = 0
    return Realization(
        states=torch.stack(states, 1),
        control=torch.cat([true_control.double(), true_control.new_full(
            (anchors.size(0), ) + true_control.shape[1:],
            math.nan).double()]),
        position_dim=anchors.size(1),
        edge_index=torch.cat(edge_index, 1),
        edge_attr=torch.cat(edge_attr).double(),
        edge_time=torch.cat(edge_time), anchor=anchor,
        prior_mean=torch.cat([start.double(), anchor_states]),
        prior_cov=prior_cov, num_steps=steps,
        num_nodes=count + anchors.size(0))


class GeneralRange(GaussianRange):
    r"""The Gaussian range through the general (matrix) messages: a range
    model with its own :meth:`linearize` is not sent rank-one messages."""
    def linearize(self, *args):
        return super().linearize(*args)


def anchor_links_only(data):
    r"""The realization without its links between agents."""
    keep = data.anchor[data.edge_index[0]]
    out = data.clone()
    out.edge_index = data.edge_index[:, keep]
    out.edge_attr = data.edge_attr[keep]
    out.edge_time = data.edge_time[keep]
    return out


def embed_in_3d(data, height_var=4.0):
    r"""A 2-D realization as a 3-D one at height zero: states [x, y, 0, v_x,
    v_y, 0], the prior's height (variance :obj:`height_var`) and vertical
    velocity independent of the rest."""
    from tg_nebp.data import Realization

    def lift(x):  # [..., 4] -> [..., 6]
        out = x.new_zeros(x.shape[:-1] + (6, ))
        out[..., [0, 1, 3, 4]] = x
        return out

    cov = data.prior_cov.new_zeros(data.num_nodes, 6, 6)
    keep = torch.tensor([0, 1, 3, 4])
    cov[:, keep.view(-1, 1), keep] = data.prior_cov
    agents = ~data.anchor
    cov[agents, 2, 2] = height_var
    cov[agents, 5, 5] = 0.01
    return Realization(states=lift(data.states), edge_index=data.edge_index,
                       edge_attr=data.edge_attr, edge_time=data.edge_time,
                       anchor=data.anchor, prior_mean=lift(data.prior_mean),
                       prior_cov=cov, num_steps=int(data.num_steps),
                       num_nodes=data.num_nodes)


def randomize(module, seed=0, scale=1.0):
    r"""Every parameter of :obj:`module` drawn at random (the output layers
    included, so the correction is far from the identity)."""
    g = gen(seed)
    with torch.no_grad():
        for parameter in module.parameters():
            parameter.copy_(scale * torch.randn(parameter.shape, generator=g,
                                                dtype=parameter.dtype))
    return module


def first_step(data, motion):
    r"""The predicted prior of the first step (a Gaussian belief) and its
    links, as the Gaussian BP tracker hands them to its conv."""
    from tg_nebp.filters import GaussianBP
    from tg_nebp.nn.conv import GaussianBelief
    tracker = GaussianBP(motion=motion)
    mean, cov = tracker.predict(data.prior_mean.double(),
                                data.prior_cov.double(), data.anchor)
    info = torch.zeros_like(cov)
    agents = ~data.anchor
    info[agents] = torch.linalg.inv(cov[agents])
    edge_index, edge_attr = next(iter(data.edges_by_step()))
    return GaussianBelief(mean, info), edge_index, edge_attr.double()


def live_trackers():
    r"""A tracker of every kind by name, built the same way in every
    process (the learned ones with fixed random weights), for the live
    session tests: Gaussian BP plain, recommended and with the noise
    adaptation, the IEKF joint and
    marginal, particle BP plain and recommended (M-sample messages,
    regularized), NEBP, the Gaussian NEBP, fixed-lag Gaussian BP (a
    window of 3 steps, and one of 4 whose 2 oldest are settled), the
    Gaussian NEBP in a window of 3, hybrid BP (over Gaussian BP and over
    that window) and the incremental smoother (relinearizing every other
    step)."""
    from tg_nebp.filters import (NEBP, CentralizedIEKF, FixedLagGaussianBP,
                                 FixedLagGaussianNEBP, GaussianBP,
                                 GaussianNEBP, HybridBP,
                                 IncrementalSmoother, NoiseAdaptation,
                                 ParticleBP)
    return {
        'gbp': lambda: GaussianBP(),
        'gbp-recommended': lambda: GaussianBP.recommended(),
        'gbp-adapted': lambda: GaussianBP.recommended(
            noise_adaptation=NoiseAdaptation()),
        'gbp-lag3': lambda: FixedLagGaussianBP.recommended(lag=3),
        'gbp-lag4-settled': lambda: FixedLagGaussianBP.recommended(
            lag=4, iterated=2),
        'iekf': lambda: CentralizedIEKF(),
        'iekf-marginal': lambda: CentralizedIEKF(marginal=True),
        'bp': lambda: ParticleBP(num_particles=40),
        'bp-recommended': lambda: ParticleBP.recommended(num_particles=40),
        'nebp': lambda: randomize(NEBP(num_particles=16, message_dim=8,
                                       hidden_dim=8), seed=4, scale=0.1),
        'gnebp': lambda: randomize(GaussianNEBP.recommended(hidden_dim=8),
                                   seed=5, scale=0.1),
        'gnebp-lag3': lambda: randomize(FixedLagGaussianNEBP.recommended(
            lag=3, hidden_dim=8), seed=5, scale=0.1),
        'hybrid': lambda: HybridBP.recommended(num_particles=20),
        'hybrid-lag3': lambda: HybridBP.recommended(lag=3, num_particles=20),
        'iekf-incremental': lambda: IncrementalSmoother(relinearize_skip=2),
    }


def stream_realization(session, data, steps=None, start=0, dt=None,
                       order=None, leave_links=()):
    r"""Feeds the time steps :obj:`start` to :obj:`steps` of a single
    realization to a live session (nodes named 'n<index>', those of
    :obj:`order`, every node by default, joined at the first step fed if
    the session holds none; links of nodes not in the session, and of the
    nodes in :obj:`leave_links`, are left out), returning the outputs."""
    from tg_nebp.filters import AgentPrior, AnchorAt
    join = {}
    if not session.ids:
        for i in range(data.num_nodes) if order is None else order:
            if bool(data.anchor[i]):
                join[f'n{i}'] = AnchorAt(data.prior_mean[i, :2].tolist())
            else:
                join[f'n{i}'] = AgentPrior(data.prior_mean[i].tolist(),
                                           data.prior_cov[i].tolist())
    outputs = []
    for t, (edge_index, edge_attr) in enumerate(data.edges_by_step()):
        if t < start or (steps is not None and t >= steps):
            continue
        present = set(session.ids) | set(join)
        links, ranges = [], []
        for (j, i), z in zip(edge_index.t().tolist(), edge_attr[:, 0]):
            if {f'n{j}', f'n{i}'} <= present and not (
                    {j, i} & set(leave_links)):
                links.append((f'n{j}', f'n{i}'))
                ranges.append(float(z))
        outputs.append(session.update(links, ranges, dt=dt, join=join))
        join = {}
    return outputs


# a small UTIAS MRCLAM sequence, written in its format
MRCLAM_HEADER = '# UTIAS\n# produced by\n# Format:\n# columns\n'
MRCLAM_T0 = 1000.0
# robot r drives at v_r along x with turn rate w_r from heading h_r
MRCLAM_SPEED = [0.1, 0.2, 0.05, 0.0, 0.15]
MRCLAM_TURN = [0.0, 0.1, -0.2, 0.0, 0.3]
MRCLAM_HEADING = [0.0, 3.0, -3.0, 1.0, 2.0]


def write_mrclam(folder: Path, measurements=None):
    r"""A small MRCLAM sequence in the dataset's format in :obj:`folder`:
    five robots driving at constant speeds and turn rates for 30 s, two
    landmarks, the measurements :obj:`measurements` (robot -> rows; by
    default :data:`MRCLAM_MEASUREMENTS`)."""
    measurements = MRCLAM_MEASUREMENTS if measurements is None else \
        measurements
    folder.mkdir(parents=True, exist_ok=True)

    def table(name, rows):
        (folder / name).write_text(MRCLAM_HEADER + ''.join(
            ' \t '.join(f'{v}' for v in row) + '\n' for row in rows))

    # robots 1-5, landmarks 6 and 7; barcode 99 is nobody's
    table('Barcodes.dat', [(s, 10 + s) for s in range(1, 8)])
    table('Landmark_Groundtruth.dat', [(6, 1.0, 2.0, 0.0, 0.0),
                                       (7, -3.0, 4.0, 0.0, 0.0)])
    for r in range(5):
        times = MRCLAM_T0 + np.arange(0.0, 30.0, 0.01)
        heading = MRCLAM_HEADING[r] + MRCLAM_TURN[r] * (times - MRCLAM_T0)
        wrapped = math.pi - np.mod(math.pi - heading, 2 * math.pi)
        table(f'Robot{r + 1}_Groundtruth.dat', [
            (t, r + MRCLAM_SPEED[r] * (t - MRCLAM_T0), 0.5 * r, h)
            for t, h in zip(times, wrapped)])
        # odometry from 1 s on, every 0.02 s
        table(f'Robot{r + 1}_Odometry.dat', [
            (t, MRCLAM_SPEED[r], MRCLAM_TURN[r])
            for t in MRCLAM_T0 + 1.0 + np.arange(0.0, 28.0, 0.02)])
        table(f'Robot{r + 1}_Measurement.dat', measurements.get(r + 1, []))


MRCLAM_MEASUREMENTS = {
    # robot 1 sees landmark 6 twice in step 0 (the latest stays), once
    # exactly at the end of step 0, robot 2 in step 1, and barcode 99
    1: [(MRCLAM_T0 + 1.1, 16, 1.5, 0.1), (MRCLAM_T0 + 1.3, 16, 1.6, 0.2),
        (MRCLAM_T0 + 1.5, 16, 1.7, 0.3), (MRCLAM_T0 + 1.7, 12, 2.0, -0.1),
        (MRCLAM_T0 + 1.8, 99, 3.0, 0.0)],
    # robot 3 sees landmark 7 before the start (outside) and in step 2
    3: [(MRCLAM_T0 + 0.5, 17, 4.0, 0.0), (MRCLAM_T0 + 2.4, 17, 4.1, -0.3)],
}


def _non_negative_range():
    from tg_nebp.models import GaussianRange

    class NonNegativeRange(GaussianRange, name='test-non-negative-range'):
        r"""The Gaussian likelihood, declared to need ranges of at least
        zero: what the checks refuse negative ranges for."""
        negative_ranges = False

    return NonNegativeRange


NonNegativeRange = _non_negative_range()


def loads_after_bit_flips(path, load, count, seed):
    r"""The file at :obj:`path` with one bit flipped at each of
    :obj:`count` places drawn with :obj:`seed`, one at a time, read by
    :obj:`load`: the number refused (a :class:`ValueError`) and the
    :obj:`(place, loaded)` of the others. The file is restored after."""
    original = path.read_bytes()
    places = torch.randint(0, 8 * len(original), (count, ),
                           generator=gen(seed)).tolist()
    refused, loaded = 0, []
    try:
        for place in places:
            flipped = bytearray(original)
            flipped[place // 8] ^= 1 << (place % 8)
            path.write_bytes(bytes(flipped))
            try:
                loaded.append((place, load(path)))
            except ValueError:
                refused += 1
    finally:
        path.write_bytes(original)
    return refused, loaded


class Given(Tracker):
    r"""A tracker whose estimates are the given states :math:`(N, T, S)`,
    with zero covariances: a start of the whole sequence's smoother in a
    chosen basin."""
    def __init__(self, states, **models):
        super().__init__(**models)
        self.states = states

    def steps(self, data, generator=None):
        for t, state in enumerate(self.states.unbind(1)):
            yield StepOutput(t, state, state.new_zeros(
                state.shape + state.shape[-1:]))


def mirror(third=(15.0, 3.0), prior_y=-5.0, steps=8, prior_sd=0.5,
           third_from=3, velocity=0.0):
    r"""A lost agent's realization, for the relocation tests: one agent
    at (5, 5), still (or moving along x at 'velocity' m/s), measured by
    anchors at (0, 0) and (10, 0) (its mirror across their line, (5, -5),
    fits them as well) and from step 'third_from' on by an anchor at
    'third' (None: never); its prior at (5, 'prior_y') with 'prior_sd'
    per axis. Returns the realization and the models (constant velocity,
    Gaussian ranges of 0.3 m)."""
    truth = torch.tensor([5.0, 5.0, velocity, 0.0])
    anchors = torch.tensor([[0.0, 0.0], [10.0, 0.0],
                            list(third or (0.0, 0.0))])
    states = torch.zeros(4, steps, 4)
    states[0] = truth
    states[0, :, 0] = 5.0 + velocity * torch.arange(steps)
    states[1:, :, :2] = anchors.unsqueeze(1)
    g = gen(1)
    edges, ranges, times = [], [], []
    for t in range(steps):
        for a in range(3 if t >= third_from and third else 2):
            distance = (anchors[a] - states[0, t, :2]).norm()
            edges.append((a + 1, 0))
            ranges.append(float(distance + 0.3 * torch.randn(
                (), generator=g, dtype=torch.float64)))
            times.append(t)
    prior_mean = torch.zeros(4, 4)
    prior_mean[0] = torch.tensor([5.0, prior_y, velocity, 0.0])
    prior_mean[1:, :2] = anchors
    prior_cov = torch.zeros(4, 4, 4)
    prior_cov[0] = torch.diag(torch.tensor([prior_sd**2, prior_sd**2,
                                            0.01, 0.01]))
    from tg_nebp.data import Realization
    data = Realization(
        states=states, edge_index=torch.tensor(edges).t(),
        edge_attr=torch.tensor(ranges).view(-1, 1),
        edge_time=torch.tensor(times),
        anchor=torch.tensor([False, True, True, True]),
        prior_mean=prior_mean, prior_cov=prior_cov, num_steps=steps,
        num_nodes=4)
    from tg_nebp.models import ConstantVelocity, GaussianRange
    return data, dict(motion=ConstantVelocity(sigma_a=0.05),
                      measurement=GaussianRange(sigma=0.3))


def bounded_inflation_by_loops(cov, predicted, kappa):
    r"""An independent reference of
    :func:`~tg_nebp.gaussian.bounded_inflation`, one node at a time, in
    float64."""
    # with cov = L L^T, the eigenvalues lambda of L^-1 P L^-T tell how much
    # each direction's variance the links took away; each is inflated by
    # min(kappa, max(lambda, 1)). A covariance without a Cholesky factor, or
    # one whose factor's diagonal spans more than half the digits of its
    # dtype, is scaled by kappa as it is (an anchor's zero stays zero)
    out = cov.double().clone()
    for i in range(cov.size(0)):
        c, p = cov[i].double(), predicted[i].double()
        lower, failed = torch.linalg.cholesky_ex(c)
        diagonal = lower.diagonal().abs()
        if failed or diagonal.min() <= diagonal.max() * \
                torch.finfo(cov.dtype).eps**0.25:
            out[i] = kappa * c
            continue
        inv = torch.linalg.inv(lower)
        values, vectors = torch.linalg.eigh(inv @ p @ inv.T)
        factor = torch.clamp(torch.clamp(values, min=1.0), max=kappa)
        root = lower @ vectors
        out[i] = root @ torch.diag(factor) @ root.T
    return out


def link_slots(links):
    r"""A whole-sequence smoother's steps (its ``_Slot``s) from each step's
    links, a list of ``(sender, receiver)`` agent indices (-1 for an
    anchor or a held end), with unit ranges and no inputs: for the tests
    of the components that read only which agents link."""
    from tg_nebp.filters.centralized.centralized_smoother import _Slot
    return [_Slot(torch.ones(len(step), 1),
                  torch.tensor([s for s, _ in step]),
                  torch.tensor([r for _, r in step]),
                  torch.zeros(len(step), 4), None) for step in links]


def assert_each_graph(mean, expected, graphs, atol):
    r"""Each of the :obj:`graphs` equal graphs of a batch's estimates
    :obj:`mean` is :obj:`expected` (one graph's) within :obj:`atol`."""
    count = expected.size(0)
    for graph in range(graphs):
        torch.testing.assert_close(mean[graph * count:(graph + 1) * count],
                                   expected, rtol=0, atol=atol)


def ranged_realization(states, step_links, count, prior_cov, loose=None,
                       sigma=0.3):
    r"""A realization of the true :obj:`states` :math:`(N, T, 4)` (the
    first :obj:`count` nodes agents, the rest anchors) whose links are the
    same ``(sender, receiver)`` pairs :obj:`step_links` at every step,
    each measured with Gaussian noise of :obj:`sigma` (drawn from
    ``gen(1)`` in link order, step by step); the prior at the first
    step's truth with the y of the first :obj:`loose` agents (all by
    default) on 0 and covariances :obj:`prior_cov` :math:`(N, 4, 4)`."""
    from tg_nebp.data import Realization
    num, steps = states.shape[:2]
    g = gen(1)
    edges, ranges, times = [], [], []
    for t in range(steps):
        for sender, receiver in step_links:
            edges.append((sender, receiver))
            ranges.append(float((states[sender, t, :2] - states[
                receiver, t, :2]).norm() + sigma * torch.randn(
                (), generator=g, dtype=torch.float64)))
            times.append(t)
    prior_mean = states[:, 0].clone()
    prior_mean[:count if loose is None else loose, 1] = 0.0
    return Realization(
        states=states, edge_index=torch.tensor(edges).t(),
        edge_attr=torch.tensor(ranges).view(-1, 1),
        edge_time=torch.tensor(times),
        anchor=torch.arange(num) >= count, prior_mean=prior_mean,
        prior_cov=prior_cov, num_steps=steps, num_nodes=num)
