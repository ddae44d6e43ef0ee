r"""Tests of the :class:`tg_nebp.filters.NEBP` tracker: gradients, the shared
time loop (checked against :class:`ParticleBP` and against hand-chained
:class:`NEBPConv` calls), batching and its configuration."""
import math

import pytest
import torch
from torch_geometric.data import Batch

from tg_nebp.datasets import Scenario
from tg_nebp.filters import NEBP, ParticleBP
from tg_nebp.models import ConstantVelocityDrag
from tg_nebp.training import position_loss
from tg_nebp.utils import weighted_moments

from helpers import Const, Shift, gen, tiny_scenario


def small_realization(seed=0, steps=2):
    scenario = Scenario.load('paper_train').replace(num_steps=steps)
    return scenario.generate(gen(seed))


def keep_all(log_weights, num_samples, generator=None):
    r"""A deterministic 'resampler' that keeps every particle (the tracker
    still resets the weights to uniform)."""
    return torch.arange(num_samples).expand(log_weights.size(0), -1)


def sequence_loss(model, data, generator):
    total = 0.0
    for step in model.steps(data, generator):
        total = total + position_loss(step.mean, data.states, step.t,
                                      data.anchor)
    return total


# --------------------------------------------------------------------------
# 1. gradients
# --------------------------------------------------------------------------

@pytest.mark.parametrize('num_iterations', [1, 2])
def test_gradients_reach_every_parameter(num_iterations):
    data = small_realization(0, steps=2)
    torch.manual_seed(0)
    model = NEBP(num_particles=32, num_iterations=num_iterations,
                 message_dim=8, hidden_dim=16)
    mlps = ['g_e', 'g_s', 'g_v'] + (['g_n'] if num_iterations > 1 else [])
    assert (model.conv.g_n is not None) == (num_iterations > 1)
    loss = sequence_loss(model, data, gen(1))
    assert loss.requires_grad
    loss.backward()
    names = [name for name, _ in model.named_parameters()]
    for mlp in mlps:
        assert any(n.startswith(f'conv.{mlp}.') for n in names), mlp
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        assert bool(torch.isfinite(p.grad).all()), name
        assert bool((p.grad != 0).any()), name


def test_no_nan_gradient_when_g_v_is_negative_everywhere():
    data = small_realization(1, steps=2)
    torch.manual_seed(2)
    model = NEBP(num_particles=32, num_iterations=2, message_dim=8,
                 hidden_dim=16)
    model.conv.g_v = Shift(model.conv.g_v, -1e3)  # relu = 0: log g_v = -inf
    loss = sequence_loss(model, data, gen(3))
    assert bool(torch.isfinite(loss))
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        assert not bool(torch.isnan(p.grad).any()), name
        assert bool(torch.isfinite(p.grad).all()), name
        if '.g_v.' in name:
            assert bool((p.grad == 0).all()), name
        else:
            assert bool((p.grad != 0).any()), name


def test_resampling_cuts_the_gradient_between_steps():
    data = small_realization(2, steps=2)
    torch.manual_seed(4)
    model = NEBP(num_particles=16, message_dim=8, hidden_dim=16)
    steps = list(model.steps(data, gen(5)))
    assert not steps[1].particles.requires_grad
    # the second step's loss does not reach the first step's weights
    loss = position_loss(steps[1].mean, data.states, 1, data.anchor)
    grad = torch.autograd.grad(loss, steps[0].log_weights, allow_unused=True)
    assert grad[0] is None


# --------------------------------------------------------------------------
# 2. the time loop against independent references
# --------------------------------------------------------------------------

@pytest.mark.parametrize('num_iterations', [1, 2])
def test_identity_correction_tracks_like_particle_bp(num_iterations):
    r"""With g_s = 1, g_v = 0 on every edge, NEBP is classical BP: same
    draws (same generator), same beliefs at every step."""
    data = tiny_scenario(3).generate(gen(6))
    K = 32
    nebp = NEBP(num_particles=K, num_iterations=num_iterations,
                message_dim=8, hidden_dim=16, correct_anchor_edges=True,
                resampler=keep_all)
    nebp.conv.g_s = Const(1, 1e4)
    nebp.conv.g_v = Const(K, -1.0)
    bp = ParticleBP(num_particles=K, num_iterations=num_iterations,
                    resampler=keep_all)
    with torch.no_grad():
        ours = list(nebp.steps(data, gen(7)))
        ref = list(bp.steps(data, gen(7)))
    assert len(ours) == len(ref) == 3
    for a, b in zip(ours, ref):
        assert torch.equal(a.particles, b.particles)
        torch.testing.assert_close(a.log_weights, b.log_weights, atol=1e-4,
                                   rtol=1e-5)
        torch.testing.assert_close(a.mean, b.mean, atol=1e-4, rtol=1e-5)
        # BP did something: the beliefs are not uniform
        assert float(b.log_weights[~data.anchor].std()) > 0.1


def test_update_chains_two_conv_iterations():
    r""":meth:`NEBP.update` with T = 2 is conv -> normalize -> conv with
    the first iteration's normalized belief as sender and the node
    embedding g_n produced by the first iteration."""
    data = small_realization(3, steps=1)
    K = 16
    torch.manual_seed(8)
    model = NEBP(num_particles=K, num_iterations=2, message_dim=8,
                 hidden_dim=16)
    g = gen(9)
    particles = model.predict(model.sample_prior(data, g), data.anchor, g)
    lw = torch.randn(particles.shape[:2], generator=g)
    ei, ea = data.edges_by_step()[0]
    with torch.no_grad():
        got = model.update(particles, lw, ei, ea, data.anchor)
        conv = model.conv
        out1, emb1 = conv(particles, lw, ei, ea, data.anchor)
        sender = out1 - out1.logsumexp(-1, keepdim=True)
        out2, _ = conv(particles, lw, ei, ea, data.anchor,
                       sender_log_weights=sender, embedding=emb1)
        expected = out2 - out2.logsumexp(-1, keepdim=True)
        # the second iteration depends on the g_n embedding
        out_no_gn, _ = conv(particles, lw, ei, ea, data.anchor,
                            sender_log_weights=sender)
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(out_no_gn, out2, atol=1e-3)
    torch.testing.assert_close(got.exp().sum(-1),
                               torch.ones(got.size(0)), atol=1e-5, rtol=0)


def test_step_outputs_are_normalized_moments():
    data = small_realization(4, steps=2)
    torch.manual_seed(10)
    model = NEBP(num_particles=16, message_dim=8, hidden_dim=16)
    with torch.no_grad():
        for step in model.steps(data, gen(11)):
            sums = step.log_weights.double().exp().sum(-1)
            torch.testing.assert_close(sums, torch.ones_like(sums),
                                       atol=1e-5, rtol=0)
            w = step.log_weights.double().exp()
            mean = (w.unsqueeze(-1) * step.particles.double()).sum(1)
            torch.testing.assert_close(step.mean.double(), mean, atol=1e-4,
                                       rtol=1e-5)
            # anchors stay at their known position
            anchor = data.anchor
            torch.testing.assert_close(step.mean[anchor, :2],
                                       data.prior_mean[anchor, :2])


def test_same_seed_same_output_and_seed_matters():
    data = small_realization(5, steps=2)
    torch.manual_seed(12)
    model = NEBP(num_particles=16, message_dim=8, hidden_dim=16)
    with torch.no_grad():
        a = model(data, gen(13))
        b = model(data, gen(13))
        c = model(data, gen(14))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
    assert not torch.equal(a.mean, c.mean)


# --------------------------------------------------------------------------
# 3. batching
# --------------------------------------------------------------------------

class FixedPrior(NEBP):
    r"""NEBP whose prior particles are given (so that a batch and its graphs
    alone start from the same particles)."""
    fixed = None

    def sample_prior(self, data, generator=None):
        return self.fixed.clone()


@pytest.mark.parametrize('num_iterations', [1, 2])
def test_tracker_batch_equals_each_graph_alone(num_iterations):
    K = 16
    steps = 3
    big = small_realization(6, steps=steps)
    small = tiny_scenario(steps).generate(gen(7))
    batch = Batch.from_data_list([big, small])
    torch.manual_seed(15)
    # sigma_a = 0: the prediction is deterministic; keep_all: so is the
    # resampling, so batch and single graphs see the same particles
    model = FixedPrior(num_particles=K, num_iterations=num_iterations,
                       motion=ConstantVelocityDrag(sigma_a=0.0),
                       message_dim=8, hidden_dim=16, resampler=keep_all)
    priors = [ParticleBP(num_particles=K).sample_prior(d, gen(20 + b))
              for b, d in enumerate((big, small))]
    model.fixed = torch.cat(priors)
    with torch.no_grad():
        together = list(model.steps(batch, gen(30)))
        alone = []
        for b, d in enumerate((big, small)):
            model.fixed = priors[b]
            alone.append(list(model.steps(d, gen(31 + b))))
    ptr = batch.ptr.tolist()
    for t in range(steps):
        for b in range(2):
            part = slice(ptr[b], ptr[b + 1])
            one = alone[b][t]
            torch.testing.assert_close(together[t].particles[part],
                                       one.particles)
            torch.testing.assert_close(together[t].log_weights[part],
                                       one.log_weights, atol=1e-4, rtol=1e-5)
            torch.testing.assert_close(together[t].mean[part], one.mean,
                                       atol=1e-4, rtol=1e-5)
            agents = ~(big, small)[b].anchor
            assert float(one.log_weights[agents].std()) > 0.01


@pytest.mark.parametrize('num_iterations', [1, 2])
def test_per_graph_generators_make_a_batch_track_as_each_graph_alone(
        num_iterations):
    # real randomness (prior, motion noise, multinomial resampling): one
    # generator per graph gives each graph its stand-alone draws
    steps, K = 3, 16
    big = small_realization(8, steps=steps)
    small = tiny_scenario(steps).generate(gen(9))
    batch = Batch.from_data_list([big, small])
    torch.manual_seed(16)
    model = NEBP(num_particles=K, num_iterations=num_iterations,
                 message_dim=8, hidden_dim=16)
    with torch.no_grad():
        together = model(batch, [gen(40), gen(41)])
        alone = [model(big, gen(40)), model(small, gen(41))]
        shared = model(batch, gen(41))
    ptr = batch.ptr.tolist()
    for b in range(2):
        part = slice(ptr[b], ptr[b + 1])
        torch.testing.assert_close(together.mean[part], alone[b].mean,
                                   rtol=0, atol=1e-4)
        torch.testing.assert_close(together.cov[part], alone[b].cov,
                                   rtol=1e-4, atol=1e-4)
    # the check has teeth: a single generator draws otherwise for graph 2
    assert not torch.allclose(shared.mean[ptr[1]:], alone[1].mean,
                              atol=1e-2)
    with pytest.raises(ValueError, match="'generator' holds 3 generators"):
        model(batch, [gen(0)] * 3)


# --------------------------------------------------------------------------
# 4. configuration
# --------------------------------------------------------------------------

def test_config_round_trip():
    model = NEBP(num_particles=24, num_iterations=2, message_dim=6,
                 hidden_dim=10, correct_anchor_edges=True,
                 resampler='systematic',
                 motion=ConstantVelocityDrag(sigma_a=0.1, drag=0.02, dt=0.5))
    config = model.config()
    rebuilt = NEBP.from_config(config)
    assert rebuilt.config() == config
    assert rebuilt.num_particles == 24 and rebuilt.num_iterations == 2
    assert rebuilt.conv.correct_anchor_edges is True
    assert rebuilt.conv.g_n is not None
    assert rebuilt.motion.dt == 0.5 and rebuilt.motion.drag == 0.02
    assert {k: v.shape for k, v in rebuilt.state_dict().items()} == \
        {k: v.shape for k, v in model.state_dict().items()}


def test_custom_resampler_cannot_be_saved():
    model = NEBP(num_particles=8, resampler=keep_all)
    with pytest.raises(ValueError, match='resampler'):
        model.config()


def test_invalid_arguments():
    with pytest.raises(ValueError):
        NEBP(num_particles=0)
    with pytest.raises(ValueError):
        NEBP(num_particles=8, num_iterations=0)
    with pytest.raises(ValueError, match='resampler'):
        NEBP(num_particles=8, resampler='nope')


def test_prior_mean_must_be_float():
    data = small_realization(7, steps=1)
    data.prior_mean = data.prior_mean.round().long()
    with pytest.raises(ValueError):
        list(NEBP(num_particles=8).steps(data, gen(0)))


def test_weighted_moments_of_uniform_weights():
    g = gen(40)
    particles = torch.randn(3, 10, 4, generator=g, dtype=torch.float64)
    lw = torch.full((3, 10), -math.log(10), dtype=torch.float64)
    mean, cov = weighted_moments(particles, lw)
    torch.testing.assert_close(mean, particles.mean(1))
    centered = particles - particles.mean(1, keepdim=True)
    torch.testing.assert_close(cov, centered.transpose(1, 2) @ centered / 10)


def test_compiled_tracker_step_equals_eager_with_gradients():
    # the first step (before resampling, which would amplify rounding) of
    # NEBP(compile=True) and its gradients equal the eager tracker's
    data = small_realization(seed=5, steps=2)
    torch.manual_seed(5)
    eager = NEBP(32, message_dim=8, hidden_dim=16)
    compiled = NEBP(32, message_dim=8, hidden_dim=16, compile=True)
    compiled.load_state_dict(eager.state_dict())
    results = []
    for model in (eager, compiled):
        step = next(model.steps(data, gen(6)))
        position_loss(step.mean, data.states, step.t,
                      data.anchor).backward()
        results.append((step.mean, {n: p.grad.clone()
                                    for n, p in model.named_parameters()}))
    torch.testing.assert_close(results[1][0], results[0][0], atol=1e-4,
                               rtol=0)
    for name, grad in results[0][1].items():
        # float32 gradients summed over many particles: compare as vectors
        error = float((results[1][1][name] - grad).norm())
        assert float(grad.norm()) > 0 and error <= 1e-4 * float(
            grad.norm()), (name, error)


def test_two_iterations_with_int32_edges():
    # NEBP with two iterations crashed in PyG's scatter on int32 edges
    data = small_realization(seed=5)
    model = NEBP(num_particles=16, num_iterations=2, message_dim=4,
                 hidden_dim=8)
    expected = model(data, gen(1))
    data.edge_index = data.edge_index.int()
    out = model(data, gen(1))
    assert torch.equal(out.mean, expected.mean)


@pytest.mark.parametrize('model_dtype,data_dtype', [
    (torch.float32, torch.float64), (torch.float64, torch.float32)])
def test_data_and_model_of_different_dtypes(model_dtype, data_dtype):
    # NEBP returned log-weights in its parameters' dtype and the moments
    # failed on float64 data
    data = small_realization(seed=6)
    for key in ('prior_mean', 'prior_cov', 'edge_attr', 'states'):
        data[key] = data[key].to(data_dtype)
    model = NEBP(num_particles=16, message_dim=4, hidden_dim=8).to(
        model_dtype)
    out = model(data, gen(2))
    assert torch.isfinite(out.mean).all()


def test_sampled_nebp_trains_and_is_stored():
    data = small_realization(seed=7)
    model = NEBP(num_particles=16, message_dim=4, hidden_dim=8,
                 num_samples=4)
    loss = sequence_loss(model, data, gen(1))
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all()
               for p in model.parameters())
    rebuilt = NEBP.from_config(model.config())
    assert rebuilt.num_samples == 4 and rebuilt.conv.bp.num_samples == 4


# -- positions of any dimension ---------------------------------------------

# NEBP's means from a checkpoint of a model initialized with seed 0 (K =
# 200), on realization seed 3 of paper_test (4 steps, seed 1, one thread),
# as the code before positions of any dimension gave them: the sum over the
# first 100 nodes and node 5's state at the last step. The equivariant
# layer's float32 sums round by the CPU's kernels (its sum moved by 4e-5
# relative and node 5's velocity by 1e-4 m/s on another CPU and under
# another kernel dispatch, ATEN_CPU_CAPABILITY), so the sums are compared
# to 1e-4 relative and velocities to 1 mm/s; a change of the 2-D path
# moves them by far more
NEBP_BEFORE_3D = {
    'paper': (38986.010226692015, [25.900571823120117, 56.372344970703125,
                                   0.16250517964363098,
                                   -0.03925434499979019]),
    'equivariant': (39107.59330086998, [26.27747344970703, 56.40903854370117,
                                        0.31577423214912415,
                                        -0.017642734572291374]),
}


@pytest.mark.parametrize('variant', list(NEBP_BEFORE_3D))
def test_two_dimensional_nebp_is_unchanged(variant, tmp_path):
    from tg_nebp.training import nebp_from_checkpoint, save_checkpoint
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        data = Scenario.load('paper_test').replace(num_steps=4).generate(
            gen(3))
        torch.manual_seed(0)
        if variant == 'equivariant':  # after the reference run's paper
            NEBP(200, variant='paper')  # model and its reloaded copy
            NEBP(200, variant='paper')
        save_checkpoint(tmp_path / 'nebp.pt', NEBP(200, variant=variant))
        with torch.no_grad():
            mean = nebp_from_checkpoint(tmp_path / 'nebp.pt')(data,
                                                              gen(1)).mean
    finally:
        torch.set_num_threads(threads)
    total, state = NEBP_BEFORE_3D[variant]
    assert float(mean[:100].double().sum()) == pytest.approx(total,
                                                             rel=1e-4)
    torch.testing.assert_close(mean[5, 3], torch.tensor(state), rtol=1e-4,
                               atol=1e-3)


@pytest.mark.parametrize('variant', ['paper', 'equivariant'])
def test_three_dimensional_nebp_runs_and_keeps_its_dimension(variant):
    cube = Scenario(name='cube', num_agents=3,
                    anchor_positions=((0.0, 0.0, 0.0), (15.0, 0.0, 10.0),
                                      (0.0, 15.0, 10.0)),
                    agent_start_low=(3.0, 3.0, 2.0),
                    agent_start_high=(12.0, 12.0, 8.0), num_steps=2,
                    prior_var=(4.0, 4.0, 4.0, 0.01, 0.01, 0.01))
    data = cube.generate(gen(5))
    model = NEBP(16, 2, variant=variant, position_dim=3)
    out = model(data, gen(0))
    assert out.mean.shape == (6, 2, 6) and bool(torch.isfinite(
        out.mean).all())
    # the embedding holds a 6-entry mean and a 6 x 6 covariance
    assert model.conv.g_n.channel_list[-1] == 6 + 36
    loss = position_loss(out.mean[:, -1], data.states, 1, data.anchor)
    loss.backward()
    assert all(p.grad is not None for p in model.conv.g_e.parameters())
    rebuilt = NEBP.from_config(model.config())
    assert rebuilt.position_dim == 3
    with pytest.raises(ValueError, match=r'built for 3-D positions \(states '
                       r'of size 6\), but the realization holds states of '
                       r'size 4'):
        model(tiny_scenario(steps=1).generate(gen(1)), gen(0))


def test_nebp_refuses_a_robot_layout_by_name():
    from tg_nebp.models import GaussianRangeBearing, UnicycleOdometry
    with pytest.raises(ValueError, match=r"reads \[p, v\] states.*"
                       r"UnicycleOdometry.*GaussianNEBP"):
        NEBP(num_particles=8, motion=UnicycleOdometry(),
             measurement=GaussianRangeBearing())
