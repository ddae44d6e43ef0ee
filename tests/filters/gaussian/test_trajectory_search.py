r"""The relocation with hindsight (TrajectorySearch) of a window tracker: an
agent whose prior puts it on the mirror of its track, where each step's
links are not decisive but the window's are, is found within the window
(where the per-step LinkSearch and no search leave it lost); an agent
whose links are symmetric about a line over the whole window is never
moved; the candidates' scores against plain float64 loops; the motion
role's transition log-likelihood and rigid moves against closed forms;
the refusals."""
import math

import numpy as np
import pytest
import torch

from tg_nebp.filters import (HYBRID_RECOMMENDED, FixedLagGaussianBP,
                             FixedLagGaussianNEBP, GaussianBP, HybridBP,
                             LinkSearch, TrackingSession, TrajectorySearch)
from tg_nebp.filters.gaussian.relocation import decisive_modes
from tg_nebp.filters.gaussian.trajectory_search import mirror_transforms
from tg_nebp.models import (ConstantVelocity, ConstantVelocityDrag,
                            UnicycleOdometry)

from helpers import mirror, randomize, stream_realization

#: The third anchor that decides the mirror over the window, not in one
#: step: its range differs by about 3 standard deviations between the
#: agent and its mirror (about 5 nats a step, under the margin of 10).
WEAK_THIRD = (20.0, 1.5)
LAG = 8


def moving_mirror(third=WEAK_THIRD):
    return mirror(third, steps=16, third_from=0, velocity=0.3)


def track(data, models, relocation):
    tracker = FixedLagGaussianBP.recommended(lag=LAG, relocation=relocation,
                                             **models)
    with torch.no_grad():
        return tracker(data)


def errors(out, data):
    return (out.mean[0, :, :2] - data.states[0, :, :2].double()).norm(dim=-1)


def test_the_window_finds_an_agent_that_no_single_step_can():
    data, models = moving_mirror()
    lost = errors(track(data, models, None), data)
    per_step = errors(track(data, models, LinkSearch()), data)
    found = errors(track(data, models, TrajectorySearch()), data)
    assert bool((lost > 8).all())
    # one step's links never beat the mirror by the margin
    assert bool((per_step > 8).all())
    # the window's do, within the window, and for good
    at = int((found < 1.0).nonzero()[0, 0])
    assert at < LAG
    assert bool((found[at:] < 1.0).all())
    # with the window's links kept, computed again where it moved: at the
    # relocation every step of its window is known as its links know it
    # (about 0.02 m^2 per axis here), not as the widened prior alone
    # (0.3 to 0.6 m^2 without them)
    tracker = FixedLagGaussianBP.recommended(
        lag=LAG, relocation=TrajectorySearch(), **models)
    with torch.no_grad():
        step = list(tracker.steps(data))[at]
    assert float(step.window_cov[0, :, :2, :2].diagonal(
        dim1=-2, dim2=-1).max()) < 0.1


def test_a_relocation_needs_one_decisive_mode():
    # two equally good modes far apart (a mirror): no decision; one that
    # beats the other by the margin: decided; directions the links leave
    # unmeasured: no decision
    curvature = torch.eye(2, dtype=torch.float64).expand(1, 2, 2)
    offset = torch.tensor([[[0.0, 0.0], [0.0, 10.0], [0.0, 0.5]]],
                          dtype=torch.float64)
    tied = torch.tensor([[-5.0, -5.0, -6.0]], dtype=torch.float64)
    ahead = torch.tensor([[-5.0, -20.0, -6.0]], dtype=torch.float64)
    assert not bool(decisive_modes(tied, offset, curvature, 10.0)[0])
    decided, distance = decisive_modes(ahead, offset, curvature, 10.0)
    assert bool(decided)
    assert torch.allclose(distance, torch.tensor([[0.0, 100.0, 0.25]],
                                                 dtype=torch.float64))
    flat = torch.diag(torch.tensor([1.0, 0.0], dtype=torch.float64))
    assert not bool(decisive_modes(ahead, offset, flat.unsqueeze(0),
                                   10.0)[0])


def test_an_agent_symmetric_over_the_whole_window_is_never_moved():
    data, models = moving_mirror(third=None)
    lost = track(data, models, None)
    searched = track(data, models, TrajectorySearch())
    assert float(errors(lost, data).min()) > 8
    assert torch.equal(searched.mean, lost.mean)
    assert torch.equal(searched.cov, lost.cov)


def test_a_live_session_relocates_as_the_offline_loop():
    data, models = moving_mirror()
    tracker = FixedLagGaussianBP.recommended(
        lag=LAG, relocation=TrajectorySearch(), **models)
    offline = tracker(data)
    outputs = stream_realization(TrackingSession(tracker), data)
    assert torch.equal(torch.stack([o.mean for o in outputs], 1),
                       offline.mean)


def test_hybrid_bp_over_the_window_reports_its_relocations():
    data, models = moving_mirror()
    window = FixedLagGaussianBP.recommended(
        lag=LAG, relocation=TrajectorySearch(), **models)
    hybrid = HybridBP(window, **HYBRID_RECOMMENDED)
    with torch.no_grad():
        out = hybrid(data, generator=torch.Generator().manual_seed(0))
    assert torch.equal(out.mean, window(data).mean)
    assert float(errors(out, data)[-1]) < 1.0


def test_scores_equal_plain_loops():
    # the window's score of every candidate: each link's Gaussian range
    # likelihood at the anchors (known sources) plus every transition's
    # density on the noise's subspace, by float64 loops
    data, models = moving_mirror()
    tracker = FixedLagGaussianBP.recommended(
        lag=LAG, relocation=TrajectorySearch(), **models)
    search = tracker.relocation
    seen = []
    original = search.search_window

    def spy(*args, **kwargs):
        result = original(*args, **kwargs)
        seen.append((args, result))
        return result

    search.search_window = spy
    with torch.no_grad():
        tracker(data)
    # the last search of the agent (it is searched every 'every' steps)
    args, result = [entry for entry in seen if bool(entry[1].searched[0])][-1]
    points = args[1]
    width = points.size(1)
    sigma = models['measurement'].sigma
    motion = models['motion']
    steps = [t for t, entry in enumerate(seen) if bool(entry[1].searched[0])]
    first = steps[-1] - width + 1
    for c in range(result.trajectories.size(1)):
        path = result.trajectories[0, c].double().numpy()
        total = 0.0
        for (j, i), z, t in zip(data.edge_index.t().tolist(),
                                data.edge_attr[:, 0].double().tolist(),
                                data.edge_time.tolist()):
            if i != 0 or not first <= t < first + width:
                continue
            anchor = data.states[j, 0, :2].double().numpy()
            d = float(np.linalg.norm(path[t - first, :2] - anchor))
            total += (-0.5 * ((z - d) / sigma)**2 -
                      math.log(sigma * math.sqrt(2 * math.pi)))
        q = motion.noise_covariance(torch.zeros(1, 4, dtype=torch.float64)
                                    )[0].numpy()
        values, vectors = np.linalg.eigh(q)
        for k in range(1, width):
            moved = motion.mean(torch.from_numpy(path[k - 1]).view(1, -1)
                                )[0].numpy()
            along = vectors.T @ (path[k] - moved)
            for value, a in zip(values, along):
                if value > 1e-9 * values.max():
                    total += -0.5 * (a * a / value +
                                     math.log(2 * math.pi * value))
        assert float(result.scores[0, c]) == pytest.approx(total, rel=1e-9,
                                                           abs=1e-8)


@pytest.mark.parametrize('model', [ConstantVelocity(sigma_a=0.2),
                                   ConstantVelocityDrag(sigma_a=0.2)])
def test_transition_log_likelihood_is_the_density_on_the_noise_subspace(
        model):
    g = torch.Generator().manual_seed(3)
    states = torch.randn(5, 4, generator=g, dtype=torch.float64)
    moved = model.sample(states, g)
    value = model.transition_log_likelihood(states, moved)
    for row in range(5):
        r = (moved[row] - model.mean(states[row:row + 1])[0]).numpy()
        q = model.noise_covariance(states[row:row + 1])[0].numpy()
        # the density of the acceleration a (r = W a): q = sigma^2 W W^T
        # has rank 2, and on its range r' Q^+ r = |a|^2 / sigma^2
        pinv = np.linalg.pinv(q, hermitian=True)
        eig = np.linalg.eigvalsh(q)
        kept = eig[eig > 1e-9 * eig.max()]
        reference = -0.5 * (r @ pinv @ r) - 0.5 * np.sum(
            np.log(2 * np.pi * kept))
        assert float(value[row]) == pytest.approx(reference, rel=1e-9)


def test_rigid_moves_carry_velocity_and_heading_along():
    angle = 0.7
    rotation = torch.tensor([[math.cos(angle), -math.sin(angle)],
                             [math.sin(angle), math.cos(angle)]],
                            dtype=torch.float64)
    reflection = torch.tensor([[1.0, 0.0], [0.0, -1.0]],
                              dtype=torch.float64)
    offset = torch.tensor([1.0, -2.0], dtype=torch.float64)
    states = torch.tensor([[1.0, 2.0, 0.5, -0.25]], dtype=torch.float64)
    cv = ConstantVelocity()
    moved = cv.rigidly_moved(states, rotation, offset)
    assert torch.allclose(moved[0, :2], rotation @ states[0, :2] + offset)
    assert torch.allclose(moved[0, 2:], rotation @ states[0, 2:])
    # a constant-velocity transition is as likely after any rigid move
    g = torch.Generator().manual_seed(1)
    path = cv.sample(states, g)
    before = cv.transition_log_likelihood(states, path)
    for turn in (rotation, reflection):
        after = cv.transition_log_likelihood(
            cv.rigidly_moved(states, turn, offset),
            cv.rigidly_moved(path, turn, offset))
        assert float(after) == pytest.approx(float(before), rel=1e-9)
    robot = UnicycleOdometry()
    pose = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    turned = robot.rigidly_moved(pose, rotation, offset)
    assert torch.allclose(turned[0, :2], rotation @ pose[0, :2] + offset)
    assert float(turned[0, 2]) == pytest.approx(3.0 + angle)
    mirrored = robot.rigidly_moved(pose, reflection, offset)
    assert float(mirrored[0, 2]) == pytest.approx(-3.0 + 2 * math.pi)


def test_the_mirror_is_across_the_neighbours_line():
    # neighbours on the line y = 1 (two agents' worth): each agent's
    # mirror is the reflection across it
    points = torch.tensor([[0.0, 1.0], [4.0, 1.0], [9.0, 1.0],
                           [-3.0, 1.0], [2.0, 1.0]], dtype=torch.float64)
    owner = torch.tensor([0, 0, 0, 1, 1])
    rotation, offset = mirror_transforms(points, owner, 2, 2)
    for agent in range(2):
        image = rotation[agent] @ torch.tensor([3.0, 6.0],
                                               dtype=torch.float64) + \
            offset[agent]
        assert torch.allclose(image, torch.tensor([3.0, -4.0],
                                                  dtype=torch.float64))


def test_refusals():
    with pytest.raises(ValueError, match="'relocation'.*has no window"):
        GaussianBP(relocation=TrajectorySearch())
    with pytest.raises(TypeError, match="'mirror'"):
        TrajectorySearch(mirror='yes')
    with pytest.raises(TypeError, match="'steps'"):
        TrajectorySearch(steps=1.5)
    assert TrajectorySearch() == TrajectorySearch()
    assert TrajectorySearch().settings()['search'] == 'trajectory'


def test_a_learned_window_relocates_too():
    # the Gaussian NEBP's window (random weights): its moved agent's
    # messages are computed again as Gaussian BP's, the correction's
    # iterations take over
    data, models = moving_mirror()
    tracker = randomize(FixedLagGaussianNEBP.recommended(lag=LAG, **models),
                        seed=2, scale=0.05).relocate_with(TrajectorySearch())
    with torch.no_grad():
        found = errors(tracker(data), data)
    at = int((found < 1.0).nonzero()[0, 0])
    assert at < LAG
    assert bool((found[at:] < 1.0).all())
