r"""The relocation of a lost agent with hindsight: a window tracker's agent
whose links over the whole window put its trajectory elsewhere (the
mirror of its track in its neighbours' geometry, another place on the
rings of its links) is moved there, trajectory and all, where no single
step's links could decide. A component of
:class:`~tg_nebp.filters.FixedLagGaussianBP` (its :obj:`relocation`), and
so of :class:`~tg_nebp.filters.HybridBP` over a window, whose particles
draw about the search's candidates."""
from typing import NamedTuple, Optional

import torch
from torch import Tensor

from tg_nebp.filters.gaussian.gaussian_bp import _inverse
from tg_nebp.filters.gaussian.relocation import (UNIQUE_DISTANCE,
                                                 LinkSearch, SearchResult,
                                                 damped_step,
                                                 decisive_modes, directions,
                                                 edges_into)
from tg_nebp.models import MotionModel, inputs
from tg_nebp.nn.conv.gaussian_bp_conv import Factors, GaussianBelief
from tg_nebp.nn.conv.hybrid_bp_conv import HybridBPConv, SourceBeliefs
from tg_nebp.utils import symmetrize

__all__ = ['TrajectorySearch', 'TrajectoryResult', 'WindowRelocation']

#: The largest variance that a relocation adds to a moved agent's
#: Gaussians along a direction its window's links hardly measure.
FREE_VARIANCE = 1e4


class TrajectoryResult(NamedTuple):
    r"""A window's search (:meth:`TrajectorySearch.search_window`): every
    agent's candidate trajectories :obj:`trajectories` :math:`(N, C, W,
    S)` over the window's steps (the first its window means), their
    :obj:`scores` :math:`(N, C)` (the log-likelihood of all its links over
    the window, the sources' extrinsic beliefs integrated out, plus that of
    its transitions), the agents :obj:`searched` :math:`(N)`, the agents
    :obj:`moved` :math:`(N)`, each agent's :obj:`best` candidate
    :math:`(N)` and the curvature :obj:`curvature` :math:`(N, D, D)` of its
    links over the window with respect to a translation of its best
    trajectory (what they alone know of where it is); the rigid moves that
    made the candidates from the window means, :obj:`rotation` :math:`(N,
    C, D, D)` and :obj:`offset` :math:`(N, C, D)`."""
    trajectories: Tensor
    scores: Tensor
    searched: Tensor
    moved: Tensor
    best: Tensor
    curvature: Tensor
    rotation: Tensor
    offset: Tensor


def mirror_transforms(points: Tensor, owner: Tensor, num: int, dim: int):
    r"""Every agent's reflection across the hyperplane that best fits the
    positions :obj:`points` :math:`(P, D)` of its neighbours (those of
    :obj:`owner` :math:`(P)`, the agent each belongs to, of :obj:`num`):
    the line through them in 2-D, the plane in 3-D, their mean on a line.
    Returns the rotations :math:`(N, D, D)` (:math:`\mathbf{I} - 2
    \mathbf{n} \mathbf{n}^\top`, :math:`\mathbf{n}` the normal: the
    direction of their least spread) and offsets :math:`(N, D)`
    (:math:`2 (\mathbf{n}^\top \mathbf{c}) \mathbf{n}`, :math:`\mathbf{c}`
    their mean)."""
    count = points.new_zeros(num).index_add(
        0, owner, torch.ones_like(owner, dtype=points.dtype)).clamp_min(1)
    center = points.new_zeros(num, dim).index_add(0, owner, points) / \
        count.view(-1, 1)
    spread = points - center[owner]
    scatter = points.new_zeros(num, dim, dim).index_add(
        0, owner, spread.unsqueeze(-1) * spread.unsqueeze(-2))
    normal = torch.linalg.eigh(scatter)[1][..., 0]  # the least spread
    eye = torch.eye(dim, dtype=points.dtype, device=points.device)
    rotation = eye - 2 * normal.unsqueeze(-1) * normal.unsqueeze(-2)
    offset = 2 * (normal * center).sum(-1, keepdim=True) * normal
    return rotation, offset


def spacetime(trajectories: Tensor) -> Tensor:
    r"""Candidate trajectories :math:`(N, C, W, S)` as the candidates of
    the window's space-time nodes :math:`(WN, C, S)` (node :math:`i` at
    step :math:`k` is row :math:`kN + i`)."""
    num, count, width, size = trajectories.shape
    return trajectories.permute(2, 0, 1, 3).reshape(width * num, count,
                                                    size)


class TrajectorySearch(LinkSearch):
    r"""The search of every agent's trajectory over a window tracker's
    window (:class:`~tg_nebp.filters.FixedLagGaussianBP`), and the
    relocation, with hindsight, of those whose links over the window
    decisively put it elsewhere: what :class:`~tg_nebp.filters.LinkSearch`
    does for one step's links, over all the window's.

    An agent's candidates are its window trajectory moved rigidly
    (:meth:`MotionModel.rigidly_moved
    <tg_nebp.models.MotionModel.rigidly_moved>`: positions
    :math:`\mathbf{p} \mapsto \mathbf{R} \mathbf{p} + \mathbf{b}`, the rest
    of the state carried along): translated onto the rings of up to
    :obj:`links` links of its newest step with links, in
    :obj:`directions` directions about each source, and, with
    :obj:`mirror`, reflected across the line (the plane in 3-D) that best
    fits the positions of every neighbour it had over the window. Each is
    translated by :obj:`steps` Gauss-Newton steps on all its links of the
    window (the target side of the measurement model's
    :meth:`~tg_nebp.models.MeasurementModel.linearize`, summed over the
    steps) and scored by the window's own likelihood: the messages of all
    its links at every step (:meth:`HybridBPConv.log_messages
    <tg_nebp.nn.conv.HybridBPConv.log_messages>`: the exact likelihood,
    the sources' extrinsic beliefs of that step integrated out) and its
    transitions (:meth:`MotionModel.transition_log_likelihood
    <tg_nebp.models.MotionModel.transition_log_likelihood>`), and so is the
    trajectory itself. An agent is relocated where its best candidate is
    another mode than its trajectory (farther than ``UNIQUE_DISTANCE`` (3)
    standard deviations of what the window's links know of a translation
    there) and beats it and every other mode by :obj:`margin` nats, with
    every direction measured: a mirror that the links leave open over the
    whole window (links symmetric about a line) is never taken.

    A relocated agent's whole window moves to the candidate: its
    linearization points, the Gaussian before the window and the prior of
    its first step (their covariances widened by the inverse of the
    window's link curvature there, what its links alone know of it), and
    its links keep their place in the window: their messages are computed
    again at the new trajectory (the window's hindsight stays, where
    :class:`~tg_nebp.filters.LinkSearch`'s relocation drops them; in a
    learned window, :class:`~tg_nebp.filters.FixedLagGaussianNEBP`, they
    are Gaussian BP's until the correction's next iterations reach them).
    An agent uses its own links and its neighbours' beliefs only, as
    :class:`~tg_nebp.filters.LinkSearch` does.

    Args:
        margin (float, optional): The nats by which the best candidate must
            beat the agent's trajectory and every other mode over the
            window. (default: :obj:`10.0`)
        directions (int, optional): Directions about each link's source.
            (default: :obj:`8`)
        links (int, optional): The links of the agent's newest step with
            links searched about, at most. (default: :obj:`4`)
        steps (int, optional): Gauss-Newton steps of every candidate's
            translation. (default: :obj:`3`)
        every (int, optional): Search each agent every :obj:`every` time
            steps (:meth:`~tg_nebp.filters.LinkSearch.due`).
            (default: :obj:`4`)
        mirror (bool, optional): Add the reflection of the trajectory
            across its neighbours' line (plane). (default: :obj:`True`)
    """
    #: Whether the search needs a window of steps, which only a window
    #: tracker has; this one does.
    needs_window = True

    def __init__(self, margin: float = 10.0, directions: int = 8,
                 links: int = 4, steps: int = 3, every: int = 4,
                 mirror: bool = True):
        super().__init__(margin, directions, links, steps, every)
        if not isinstance(mirror, bool):
            raise TypeError(f"'mirror' must be a bool, got {mirror!r}")
        self.mirror = mirror

    def settings(self) -> dict:
        return dict(super().settings(), mirror=self.mirror,
                    search='trajectory')

    def __repr__(self) -> str:
        return super().__repr__()[:-1] + f', mirror={self.mirror})'

    def search_window(self, conv: HybridBPConv, points: Tensor,
                      sources: SourceBeliefs, factors: Factors,
                      links: Tensor, link_attr: Tensor, start: Tensor,
                      motions, control: Optional[Tensor],
                      motion: MotionModel, due: Tensor
                      ) -> TrajectoryResult:
        r"""The candidate trajectories of the agents :obj:`due` :math:`(N)`
        and their scores, and the agents to relocate, from the window's
        means :obj:`points` :math:`(N, W, S)` and its space-time links
        (:obj:`links` :math:`(2, E)`, :obj:`link_attr`, their
        :obj:`factors` and :obj:`sources`, the
        :class:`~tg_nebp.nn.conv.SourceBeliefs` of :obj:`conv` over the
        window's space-time nodes, node :math:`i` at step :math:`k` being
        :math:`kN + i`); every agent's first window step :obj:`start`
        :math:`(N)`, the transitions into every window step
        :obj:`motions` (:math:`W` motion models) with the known inputs
        :obj:`control` :math:`(N, W, C)` (:obj:`None`: none), and the
        tracker's :obj:`motion` (its layout and rigid moves)."""
        num, width, size = points.shape
        dim = motion.layout(size).position_dim
        rows = num * width
        into, sourced, _ = edges_into(due.repeat(width), factors, sources)
        target = into.index[1]
        agent = target % num
        degree = torch.bincount(target, minlength=rows)
        searched = degree.view(width, num).sum(0).gt(0) & due
        none = torch.zeros_like(due)
        if not bool(searched.any()):
            eye = torch.eye(dim, dtype=points.dtype, device=points.device)
            return TrajectoryResult(points.unsqueeze(1),
                                    points.new_zeros(num, 1), none, none,
                                    torch.zeros_like(start),
                                    eye.expand(num, dim, dim),
                                    eye.expand(num, 1, dim, dim),
                                    points.new_zeros(num, 1, dim))
        pairs = conv.pairs(into)
        rotation, offset = self._transforms(
            conv, points, sourced, into, link_attr, pairs, degree, agent,
            dim)
        linearized = (sourced, into, links, link_attr, pairs)
        for _ in range(self.steps):
            grad, curv = self._window_linearization(
                conv, motion.rigidly_moved(
                    points.unsqueeze(1), rotation.unsqueeze(2),
                    offset.unsqueeze(2)), linearized, dim)
            step = damped_step(grad, curv)
            step[:, 0] = 0.0  # the trajectory itself is scored as it is
            offset = offset + step
        trajectories = motion.rigidly_moved(
            points.unsqueeze(1), rotation.unsqueeze(2), offset.unsqueeze(2))
        scores = self._scores(conv, linearized, target, start, motions,
                              control, trajectories)
        scores = torch.where(searched.view(-1, 1), scores, 0.0)
        best = scores.argmax(-1)
        _, curv = self._window_linearization(conv, trajectories,
                                             linearized, dim)
        curvature = curv.gather(1, best.view(-1, 1, 1, 1).expand(
            -1, 1, dim, dim)).squeeze(1)
        # the candidates' places: their mean positions over the window
        place = trajectories[..., :dim].mean(2)
        decisive, distance = decisive_modes(
            scores, place - place.gather(1, best.view(-1, 1, 1).expand(
                -1, 1, dim)), curvature, self.margin)
        moved = (searched & decisive & (distance[:, 0] >
                                        UNIQUE_DISTANCE**2) &
                 (scores.amax(-1) - scores[:, 0] > self.margin))
        return TrajectoryResult(trajectories, scores, searched, moved, best,
                                curvature, rotation, offset)

    def _transforms(self, conv, points, sourced, into, link_attr, pairs,
                    degree, agent, dim):
        # the candidates' rigid moves (N, C, D, D), (N, C, D): none (the
        # trajectory), translations onto the rings of the newest step with
        # links, the mirror across the neighbours' line (plane)
        num, width, _ = points.shape
        first = torch.cumsum(degree, 0) - degree
        # every agent's newest window step with links
        held = degree.view(width, num) > 0
        newest = (held * torch.arange(1, width + 1, device=points.device
                                      ).view(-1, 1)).amax(0).sub(1).clamp_min(0)
        row = newest * num + torch.arange(num, device=points.device)
        count = degree[row]
        links = max(min(self.links, int(count.max())), 1)
        k = torch.arange(links, device=points.device)
        edge = (first[row].view(-1, 1) + k).clamp(
            0, max(into.index.size(1) - 1, 0))
        has = k.view(1, -1) < count.view(-1, 1)
        ranges = conv.ranges(into, link_attr, pairs)
        spread = directions(self.directions, dim, points)
        centers = sourced.state[edge][..., :dim]
        ring = (centers.unsqueeze(2) + ranges[edge].view(num, links, 1, 1) *
                spread).flatten(1, 2)
        here = points.gather(1, newest.view(-1, 1, 1).expand(
            -1, 1, points.size(-1))).squeeze(1)[:, :dim]
        shift = torch.where(has.repeat_interleave(self.directions, 1)
                            .unsqueeze(-1), ring - here.unsqueeze(1), 0.0)
        eye = torch.eye(dim, dtype=points.dtype, device=points.device)
        offset = torch.cat([shift.new_zeros(num, 1, dim), shift], 1)
        rotation = eye.expand(num, offset.size(1), dim, dim)
        if self.mirror:
            turn, move = mirror_transforms(sourced.state[:, :dim], agent,
                                           num, dim)
            rotation = torch.cat([rotation, turn.unsqueeze(1)], 1)
            offset = torch.cat([offset, move.unsqueeze(1)], 1)
        return rotation, offset

    @staticmethod
    def _window_linearization(conv, trajectories, linearized, dim):
        # the gradient (N, C, D) and curvature (N, C, D, D) of every
        # candidate's links over the window with respect to a translation
        # of the whole trajectory: the sums of its steps' position blocks
        num, count, width, _ = trajectories.shape
        grad, curv = conv.target_linearization(spacetime(trajectories),
                                               *linearized)
        grad = grad[..., :dim].view(width, num, count, dim).sum(0)
        curv = curv[..., :dim, :dim].view(width, num, count, dim,
                                          dim).sum(0)
        return grad, curv

    def _scores(self, conv, linearized, target, start, motions, control,
                trajectories):
        # the window's log-likelihood (N, C) of every candidate trajectory
        # (N, C, W, S): its links' messages at every step and its
        # transitions
        num, count, width, _ = trajectories.shape
        links = trajectories.new_zeros(width * num, count).index_add(
            0, target, conv.log_messages(spacetime(trajectories),
                                         *linearized)).view(
                width, num, count).sum(0)
        return links + self._motion_scores(trajectories, start, motions,
                                           control)

    @staticmethod
    def _motion_scores(trajectories, start, motions, control):
        # the log-likelihood (N, C) of every candidate's transitions
        # between its window steps (those after the agent's first)
        num, count, width, _ = trajectories.shape
        total = trajectories.new_zeros(num, count)
        for k in range(1, width):
            given = None if control is None else control[:, k].unsqueeze(
                1).expand(-1, count, -1)
            step = motions[k].transition_log_likelihood(
                trajectories[:, :, k - 1], trajectories[:, :, k],
                **inputs(given))
            total = total + torch.where((start < k).view(-1, 1), step, 0.0)
        return total


class WindowRelocation:
    r"""The relocation with hindsight of
    :class:`~tg_nebp.filters.FixedLagGaussianBP`'s window (a part of the
    tracker, not a tracker of its own): its :class:`TrajectorySearch` run
    over the window after a step's iterations, and the moved agents'
    windows, priors and messages set where the search put them."""

    def _relocated_window(self, state, window, belief, messages, points,
                          anchor, graph_of, t, generator):
        # the window after the search of the agents due at time index t:
        # (state, window, belief, messages, covs, points) with every moved
        # agent's trajectory, Gaussian before the window and first prior
        # moved, its links' messages computed again there and the chains
        # solved (the state's settled forward pass is dropped: it runs
        # again at the next step), or None where nobody moved; and the
        # TrajectoryResult
        num, width, size = points.shape
        search, conv = self.relocation, self.link_conv
        sources = conv.sources(belief, window.factors, messages,
                               window.anchor)
        result = search.search_window(
            conv, points, sources, window.factors, window.links,
            window.link_attr, window.start, window.motions, window.control,
            self.motion, search.due(state.fresh, anchor, graph_of, t))
        moved = result.moved
        if not bool(moved.any()):
            return None, result
        dim = result.curvature.size(-1)
        rows = torch.arange(num, device=points.device)
        rotation = result.rotation[rows, result.best]
        offset = result.offset[rows, result.best]
        # what the window's links alone know of the agent at its new place
        # (at most the free variance along a direction they hardly
        # measure)
        values, vectors = torch.linalg.eigh(result.curvature)
        spread = (1 / values.clamp_min(1 / FREE_VARIANCE)).diag_embed()
        widening = points.new_zeros(num, size, size)
        widening[:, :dim, :dim] = symmetrize(
            vectors @ spread @ vectors.transpose(-1, -2))

        def moved_rigidly(states):
            return torch.where(moved.view(-1, 1), self.motion.rigidly_moved(
                states, rotation, offset), states)

        def widened(cov):
            return torch.where(moved.view(-1, 1, 1), cov + widening, cov)

        points = torch.where(moved.view(-1, 1, 1),
                             result.trajectories[rows, result.best], points)
        entry_cov = widened(state.cov)
        state = state._replace(
            mean=moved_rigidly(state.mean), cov=entry_cov,
            predicted=torch.where(moved.view(-1, 1, 1), entry_cov,
                                  state.predicted),
            entry_point=None if state.entry_point is None else
            moved_rigidly(state.entry_point))
        prior_cov = widened(window.prior_cov)
        prior_info = window.prior.info.clone()
        agents = moved & ~anchor
        prior_info[agents] = _inverse(prior_cov[agents])
        window = window._replace(
            prior=GaussianBelief(moved_rigidly(window.prior.mean),
                                 prior_info), prior_cov=prior_cov)
        # the moved agents' factors: their messages start again from the
        # new trajectory (twice: the second from beliefs that hold the
        # first's)
        chosen = moved.repeat(width)[window.factors.ends].any(1)
        fresh = chosen[window.factors.link]
        messages = type(messages)(*(
            torch.where(fresh.view((-1, ) + (1, ) * (m.dim() - 1)), 0.0, m)
            for m in messages))
        belief = GaussianBelief(points.transpose(0, 1).reshape(-1, size),
                                belief.info)
        solving = (~anchor).nonzero().view(-1)
        for _ in range(2):
            messages, _ = self._recomputed(window, belief, messages, chosen,
                                           fresh, generator)
            belief, covs = self.share(*self._solve(window, points, messages,
                                                   solving))
            points = belief.mean.view(width, num, size).transpose(0, 1)
            fresh = torch.zeros_like(fresh)
        return (state, window, belief, messages, covs, points), result

    def _newest_search(self, result: TrajectoryResult, solved, edge_index,
                       edge_attr, anchor) -> SearchResult:
        # the window's search as the newest step's SearchResult (what
        # hybrid BP draws its particles' modes from): every candidate
        # trajectory's newest state and its score over the window, the
        # sources and tempering of the newest step's message edges
        sources = self.link_conv.sources(solved.belief, solved.factors,
                                         solved.messages, anchor)
        return SearchResult(
            result.trajectories[:, :, -1], result.scores, result.searched,
            result.moved, sources, result.curvature,
            self.link_weights(solved, edge_index.long(), edge_attr.double(),
                              anchor))

