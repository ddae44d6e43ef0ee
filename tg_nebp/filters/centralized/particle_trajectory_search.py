r"""The escape of the whole sequence's smoother from the basin its start put
it in: every agent's trajectory searched over the whole sequence by a
conditional particle filter, its neighbours held at the solution, and
moved where a candidate's optimum beats its own. A component of
:class:`~tg_nebp.filters.CentralizedSmoother` with :obj:`lag=None` (its
:obj:`search`)."""
from typing import List, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number, check_positive_int
from tg_nebp.filters.particle.resampling import (RESAMPLERS,
                                                 effective_sample_size)
from tg_nebp.gaussian import block_diagonal, marginal_blocks
from tg_nebp.models import inputs

__all__ = ['ParticleTrajectorySearch', 'EscapeSweep']


class EscapeSweep(NamedTuple):
    r"""One sweep of the search (:meth:`ParticleTrajectorySearch.sweep`):
    every agent's cost :obj:`cost` :math:`(A)` (its share of the whole
    sequence's negative log-posterior: its prior, transitions and links,
    its neighbours held), the cost :obj:`candidate_cost` :math:`(A, C)` of
    each candidate's optimum (:math:`+\infty` where an agent has fewer
    candidates), those optima :obj:`candidates` :math:`(C, T, A, S)`, and
    the agents :obj:`moved` :math:`(A)`, each to its best candidate
    :obj:`best` :math:`(A)`."""
    cost: Tensor
    candidate_cost: Tensor
    candidates: Tensor
    moved: Tensor
    best: Tensor


class ParticleTrajectorySearch:
    r"""The search, with the whole sequence's hindsight, of every agent's
    trajectory for a better basin of the smoother's cost than the one its
    start put it in (a filter's lost agent, a drift along a direction its
    few links do not measure): a block move of the Gauss-Newton smoother
    (:class:`~tg_nebp.filters.CentralizedSmoother` with :obj:`lag=None`),
    one agent at a time, its neighbours held at the solution.

    Each sweep, for every agent :math:`a` at once:

    1. a conditional particle filter over its own state (`"Particle Markov
       chain Monte Carlo methods"
       <https://doi.org/10.1111/j.1467-9868.2009.00736.x>`_, Andrieu,
       Doucet and Holenstein, JRSS B 2010): :obj:`num_particles` particles
       drawn from the prior of its first step, moved by the motion model's
       :meth:`~tg_nebp.models.MotionModel.sample`, weighted by the
       measurement model's likelihood of its links to its neighbours'
       solution (anchors at their known states) and resampled
       (:obj:`resampler`) where the effective sample size falls below
       half; particle 0 is its current trajectory, never resampled away;
    2. every final particle's lineage scored by its log-posterior,

       .. math::
           \log p(\mathbf{x}_0) + \sum_k \log p(\mathbf{x}_k \,|\,
           \mathbf{x}_{k-1}) + \sum_k \sum_{j \sim a} \log p\big(
           z^{(k)}_{ja} \,\big|\, \mathbf{x}_k, \hat{\mathbf{x}}^{(k)}_j
           \big)

       (:meth:`~tg_nebp.models.MotionModel.transition_log_likelihood`,
       the measurement model's
       :meth:`~tg_nebp.models.MeasurementModel.log_likelihood`): the
       :obj:`candidates` best lineages that lie farther than
       :obj:`separation` metres from the current trajectory, and from each
       other, at some step are its candidates;
    3. each candidate is taken to its optimum by the smoother's own
       Gauss-Newton iterations (at most :obj:`refine_iterations`) on the
       agent's trajectory alone, the neighbours held;
    4. the agent moves to its best optimum where that costs less than its
       trajectory by :obj:`margin` nats. Agents that share a link at some
       step do not move in the same sweep (the one that gains most does):
       each gain is measured with the other held.

    The whole sequence's Gauss-Newton iterations then start from the moved
    solution, and the sweeps repeat, at most :obj:`sweeps` times, until
    no agent moves. Each move lowers the whole sequence's cost by its gain
    and the iterations only descend, so the smoother's cost never rises.

    A lost agent whose trajectory is wrong only together with its
    neighbours' (a group that ranged only to each other) is not moved: one
    agent at a time, its neighbours held, cannot see that basin.

    Args:
        num_particles (int, optional): Particles of each agent's filter
            (:math:`P`, the current trajectory's included).
            (default: :obj:`500`)
        candidates (int, optional): Candidates per agent (:math:`C`).
            (default: :obj:`2`)
        separation (float, optional): The metres at some step by which a
            candidate lies off the current trajectory and off every better
            candidate. (default: :obj:`2.0`)
        margin (float, optional): The nats by which a candidate's optimum
            must beat the agent's trajectory. (default: :obj:`10.0`)
        sweeps (int, optional): Sweeps at most. (default: :obj:`3`)
        refine_iterations (int, optional): Gauss-Newton iterations of the
            candidates' optima (stopping early at the smoother's
            tolerance). (default: :obj:`20`)
        resampler (str, optional): A resampler by name,
            :obj:`"systematic"`, :obj:`"multinomial"`,
            :obj:`"stratified"` or :obj:`"residual"` (the registry
            ``RESAMPLERS`` of the particle methods). (default:
            :obj:`"systematic"`)
    """
    def __init__(self, num_particles: int = 500, candidates: int = 2,
                 separation: float = 2.0, margin: float = 10.0,
                 sweeps: int = 3, refine_iterations: int = 20,
                 resampler: str = 'systematic'):
        self.num_particles = check_positive_int(num_particles,
                                                'num_particles')
        if self.num_particles < 2:
            raise ValueError(f"'num_particles' must be at least 2 (the "
                             f"current trajectory and a draw), got "
                             f"{num_particles}")
        self.candidates = check_positive_int(candidates, 'candidates')
        self.separation = check_number(separation, 'separation')
        self.margin = check_number(margin, 'margin')
        self.sweeps = check_positive_int(sweeps, 'sweeps')
        self.refine_iterations = check_positive_int(refine_iterations,
                                                    'refine_iterations')
        if resampler not in RESAMPLERS:
            raise ValueError(f"'resampler' must be one of "
                             f"{sorted(RESAMPLERS)}, got {resampler!r}")
        self.resampler = resampler

    def escaped(self, smoother, base, slots: List, solved: Tuple,
                generator: Optional[torch.Generator] = None) -> Tuple:
        r"""The smoother's whole-sequence solution :obj:`solved` (as its
        Gauss-Newton iterations return it: per step the agents' states
        :math:`(A, S)`, the optimum of its start's basin, and the
        forward-backward pass there) after the sweeps, in the same
        form."""
        for _ in range(self.sweeps):
            points = solved[0]
            result = self.sweep(smoother, base, slots, points, generator)
            if not bool(result.moved.any()):
                break
            agents = torch.arange(points[0].size(0),
                                  device=points[0].device)
            start = [torch.where(result.moved.view(-1, 1), result.candidates[
                result.best, k, agents], here)
                for k, here in enumerate(points)]
            solved = smoother._solve(base, slots, start)
        return solved

    def sweep(self, smoother, base, slots: List, points: List[Tensor],
              generator: Optional[torch.Generator] = None) -> EscapeSweep:
        r"""One sweep over the solution :obj:`points`: every agent's
        candidates, their optima and costs, and the agents that move."""
        held = [held_slot(slot, here) for slot, here in zip(slots, points)]
        cost = agent_costs(smoother, base, held, points)
        lineages = self.lineages(smoother, base, slots, points, generator)
        count = points[0].size(0)
        # the held problem of the agents with a candidate alone (the others
        # keep their trajectories): independent agents, so its optimum
        # is theirs
        searched = torch.stack([exists for _, exists in lineages]).any(0)
        if not bool(searched.any()):
            return EscapeSweep(cost, cost.new_full(
                (count, len(lineages)), float('inf')), torch.stack(
                [torch.stack(points)] * len(lineages)), searched,
                torch.zeros_like(searched, dtype=torch.long))
        index = searched.nonzero().flatten()
        mine_base, mine = restricted(base, held, searched)
        optima, costs = [], []
        for candidate, exists in lineages:
            start = [torch.where(exists.view(-1, 1), state, here)[index]
                     for state, here in zip(candidate.unbind(0), points)]
            optimum = smoother._solve(mine_base, mine, start,
                                      self.refine_iterations)[0]
            optima.append(torch.stack([here.index_copy(0, index, state)
                                       for here, state in
                                       zip(points, optimum)]))
            costs.append(torch.where(exists, cost.index_copy(
                0, index, agent_costs(smoother, mine_base, mine, optimum)),
                float('inf')))
        candidate_cost = torch.stack(costs, 1)
        best_cost, best = candidate_cost.min(1)
        moved = _unlinked_movers(cost - best_cost, self.margin, slots)
        return EscapeSweep(cost, candidate_cost, torch.stack(optima), moved,
                           best)

    def lineages(self, smoother, base, slots: List, points: List[Tensor],
                 generator: Optional[torch.Generator] = None):
        r"""Every agent's candidates from its conditional particle filter:
        per candidate the trajectories :math:`(T, A, S)` and whether each
        agent has one :math:`(A)`."""
        count, size = points[0].shape
        num = self.num_particles
        mean, cov, _ = smoother._predicted(base, slots[0].control)
        blocks = marginal_blocks(cov, size)
        draws = torch.randn((count, num, size), dtype=mean.dtype,
                            device=mean.device, generator=generator)
        particles = mean.unsqueeze(1) + (torch.linalg.cholesky(
            blocks).unsqueeze(1) @ draws.unsqueeze(-1)).squeeze(-1)
        particles[:, 0] = points[0]
        offset = (particles - mean.unsqueeze(1)).unsqueeze(-1)
        score = -0.5 * (offset * torch.linalg.solve(
            blocks.unsqueeze(1), offset)).sum((-1, -2))
        log_weights = torch.zeros_like(score)
        history, ancestry = [], []
        every = torch.arange(num, device=mean.device).expand(count, num)
        for k, slot in enumerate(slots):
            if k > 0:
                given = inputs(None if slot.control is None else
                               slot.control.unsqueeze(1).expand(
                                   -1, num, -1))
                moved = smoother.motion.sample(particles, generator=generator,
                                               **given)
                moved[:, 0] = points[k]
                score = score + smoother.motion.transition_log_likelihood(
                    particles, moved, **given)
                particles = moved
            links = link_log_likelihoods(smoother, slot, points[k],
                                         particles)
            score = score + links
            log_weights = log_weights + links
            history.append(particles)
            ancestors = every.clone()
            low = effective_sample_size(log_weights) < num / 2
            if k + 1 < len(slots) and bool(low.any()):
                drawn = RESAMPLERS[self.resampler](log_weights[low],
                                                   generator=generator)
                drawn[:, 0] = 0  # the current trajectory stays
                ancestors[low] = drawn
                log_weights = torch.where(low.view(-1, 1), 0.0, log_weights)
            ancestry.append(ancestors)
            particles = particles.gather(
                1, ancestors.unsqueeze(-1).expand(-1, -1, size))
            score = score.gather(1, ancestors)
        # every final particle's lineage (T, A, P, S), back through its
        # ancestors
        index = every
        paths = [history[-1]]
        for k in range(len(slots) - 2, -1, -1):
            index = ancestry[k].gather(1, index)
            paths.insert(0, history[k].gather(
                1, index.unsqueeze(-1).expand(-1, -1, size)))
        paths = torch.stack(paths)
        return self._chosen(smoother, paths, score, points)

    def _chosen(self, smoother, paths: Tensor, score: Tensor,
                points: List[Tensor]):
        # the best lineages (by score) farther than 'separation' at some
        # step from the current trajectory and from each better one
        dim = smoother.measurement.position_dim(paths.size(-1))
        position = paths[..., :dim]  # (T, A, P, D)
        order = score.argsort(1, descending=True)

        def apart_from(trajectory: Tensor) -> Tensor:
            # (A, P): the lineages farther than 'separation' from it at
            # some step
            return (position - trajectory[..., :dim].unsqueeze(2)).norm(
                dim=-1).amax(0) > self.separation

        apart = apart_from(torch.stack(points))
        agents = torch.arange(score.size(0), device=score.device)
        chosen = []
        for _ in range(self.candidates):
            ranked = apart.gather(1, order)
            exists = ranked.any(1)
            pick = order.gather(1, ranked.to(torch.uint8).argmax(
                1, keepdim=True)).squeeze(1)
            path = paths[:, agents, pick]  # (T, A, S)
            chosen.append((path, exists))
            apart = apart & apart_from(path)
        return chosen

    def settings(self) -> dict:
        return dict(search='particle-trajectory',
                    num_particles=self.num_particles,
                    candidates=self.candidates, separation=self.separation,
                    margin=self.margin, sweeps=self.sweeps,
                    refine_iterations=self.refine_iterations,
                    resampler=self.resampler)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(num_particles='
                f'{self.num_particles}, candidates={self.candidates}, '
                f'separation={self.separation}, margin={self.margin}, '
                f'sweeps={self.sweeps})')

    def __eq__(self, other) -> bool:
        return isinstance(other, ParticleTrajectorySearch) and \
            self.settings() == other.settings()


def held_slot(slot, state: Tensor):
    r"""A step's links (a smoother's slot) with every link between two
    agents made two, one per end, the other end held at its state in
    :obj:`state` :math:`(A, S)` (index :math:`-1`, its state known): the
    links of every agent's own problem, its neighbours held."""
    both = slot.sender >= 0
    held = torch.full_like(slot.sender[both], -1)
    return type(slot)(
        torch.cat([slot.z, slot.z[both]]),
        torch.cat([torch.where(both, -1, slot.sender), slot.sender[both]]),
        torch.cat([slot.receiver, held]),
        torch.cat([torch.where(both.view(-1, 1),
                               state[slot.sender.clamp_min(0)], slot.known),
                   state[slot.receiver[both]]]),
        slot.control)


def restricted(base, held: List, keep: Tensor):
    r"""The held problem (slots of :func:`held_slot`, the Gaussian before
    it :obj:`base`, independent across agents) of the agents :obj:`keep`
    :math:`(A)` alone: their prior, and their links, renumbered."""
    index = keep.nonzero().flatten()
    size = base.mean.size(1)
    number = torch.full_like(keep, -1, dtype=torch.long)
    number[index] = torch.arange(index.numel(), device=keep.device)
    out_base = type(base)(base.mean[index], block_diagonal(
        marginal_blocks(base.cov, size)[index]), base.point[index])
    out = []
    for slot in held:
        owner = torch.where(slot.receiver >= 0, slot.receiver, slot.sender)
        links = keep[owner]
        out.append(type(slot)(
            slot.z[links],
            torch.where(slot.sender[links] >= 0,
                        number[slot.sender[links].clamp_min(0)], -1),
            torch.where(slot.receiver[links] >= 0,
                        number[slot.receiver[links].clamp_min(0)], -1),
            slot.known[links],
            None if slot.control is None else slot.control[index]))
    return out_base, out


def agent_costs(smoother, base, held: List, points: List[Tensor]) -> Tensor:
    r"""Every agent's cost :math:`(A)` in the held problem (slots of
    :func:`held_slot`): its share of the whole sequence's negative
    log-posterior, as the smoother's :meth:`_window_cost` counts it (the
    prior of its first step, the driving noise of its transitions, its
    links' log-likelihood), the whole sequence's prior being independent
    across agents. The sum over agents is the held problem's cost."""
    count, size = points[0].shape
    prior, cov, _ = smoother._predicted(base, held[0].control)
    blocks = marginal_blocks(cov, size)
    offset = (points[0] - prior).unsqueeze(-1)
    cost = 0.5 * (offset * torch.linalg.solve(blocks, offset)).sum((-1, -2))
    factors = smoother._noise_factors(held, points)
    for noise in smoother._noises(held, points, factors):
        cost = cost + 0.5 * noise.square().sum(-1)
    for slot, state in zip(held, points):
        ends = smoother._ends(state, slot.sender, slot.receiver, slot.known)
        log_lik = smoother.measurement.log_likelihood(
            slot.z, ends[0].unsqueeze(1), ends[1].unsqueeze(1)).view(-1)
        owner = torch.where(slot.receiver >= 0, slot.receiver, slot.sender)
        cost = cost.index_add(0, owner, -log_lik)
    return cost


def link_log_likelihoods(smoother, slot, state: Tensor,
                         particles: Tensor) -> Tensor:
    r"""The log-likelihood :math:`(A, P)` of every agent's links of a step
    at each of its particles :obj:`particles` :math:`(A, P, S)`, the other
    end at its state in :obj:`state` :math:`(A, S)` (an anchor's known)."""
    out = particles.new_zeros(particles.shape[:2])
    sender = torch.where((slot.sender >= 0).view(-1, 1),
                         state[slot.sender.clamp_min(0)], slot.known)
    out.index_add_(0, slot.receiver, smoother.measurement.log_likelihood(
        slot.z, sender.unsqueeze(1), particles[slot.receiver]))
    agent = slot.sender >= 0
    out.index_add_(0, slot.sender[agent], smoother.measurement.log_likelihood(
        slot.z[agent], particles[slot.sender[agent]],
        state[slot.receiver[agent]].unsqueeze(1)))
    return out


def linked_agents(slots: List, count: int, device) -> Tensor:
    r"""Which of :obj:`count` agents share a link at some step of
    :obj:`slots` (a smoother's steps; :math:`-1`, an anchor or a held end,
    links no agent): a symmetric :math:`(A, A)` boolean matrix."""
    linked = torch.zeros(count, count, dtype=torch.bool, device=device)
    for slot in slots:
        both = (slot.sender >= 0) & (slot.receiver >= 0)
        linked[slot.sender[both], slot.receiver[both]] = True
    return linked | linked.T


def connected_groups(linked: Tensor, members: Tensor) -> List[Tensor]:
    r"""The :obj:`members` (a boolean mask :math:`(A)`) split into groups
    connected by :obj:`linked` (a symmetric boolean :math:`(A, A)`, as
    :func:`linked_agents` gives; two members in one group are joined by a
    path of members): the index tensors of their agents, ascending, the
    largest group first (the one of the lowest agent among equal sizes)."""
    count = members.numel()
    # every member reaches itself and its linked members
    reach = (linked | torch.eye(count, dtype=torch.bool,
                                device=members.device)) & \
        members.view(-1, 1) & members.view(1, -1)
    # connected components by closure: each member reaches what its
    # reachable members reach, until nothing is added
    while True:
        wider = (reach.to(torch.float64) @ reach.to(torch.float64)) > 0
        if torch.equal(wider, reach):
            break
        reach = wider
    groups, seen = [], torch.zeros_like(members)
    for agent in members.nonzero().flatten().tolist():
        if not bool(seen[agent]):
            groups.append(reach[agent].nonzero().flatten())
            seen = seen | reach[agent]
    return sorted(groups, key=lambda group: (-group.numel(),
                                             int(group[0])))


def _unlinked_movers(gain: Tensor, margin: float, slots: List) -> Tensor:
    # the agents whose gain beats the margin, best first, skipping any that
    # shares a link at some step with one already taken
    count = gain.numel()
    linked = linked_agents(slots, count, gain.device)
    moved = torch.zeros(count, dtype=torch.bool, device=gain.device)
    for agent in gain.argsort(descending=True).tolist():
        if not float(gain[agent]) > margin:
            break
        if not bool((linked[agent] & moved).any()):
            moved[agent] = True
    return moved
