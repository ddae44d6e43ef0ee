r"""The chains of fixed-lag Gaussian BP's window: every agent's states over
the window solved exactly given the links' messages (a forward filter and
an RTS backward pass), and the settled steps of a long window
(:class:`WindowChains`, a part of
:class:`~tg_nebp.filters.FixedLagGaussianBP`)."""
from typing import List, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.filters.gaussian.gaussian_bp import _inverse
from tg_nebp.filters.gaussian.window_state import Window, WindowState
from tg_nebp.gaussian import (bounded_inflation, rts_backward,
                              rts_backward_chain)
from tg_nebp.models import inputs
from tg_nebp.nn.conv.gaussian_bp_conv import GaussianBelief, as_factor_messages
from tg_nebp.utils import symmetrize

__all__ = ['WindowChains']


class SolvedWindow(NamedTuple):
    # the window's beliefs (space-time rows, slot-major) and covariances
    # (N, W, S, S)
    belief: GaussianBelief
    cov: Tensor


class Chains(NamedTuple):
    # the forward pass of agents' time chains: their first window steps,
    # priors there (belief, covariance), every filtered step (mean,
    # covariance), the prediction into every step after the first that
    # the pass computed (belief, covariance, cross covariance with the
    # step before), the belief of the last step it filtered and the prior
    # of the step after the filtered ones (or None: the window ends)
    start: Tensor
    entry: GaussianBelief
    entry_cov: Tensor
    filtered: List[Tuple[Tensor, Tensor]]
    predicted: List[Tuple[GaussianBelief, Tensor, Tensor]]
    last: Optional[GaussianBelief]
    after: Optional[Tuple[GaussianBelief, Tensor]]


class WindowChains:
    r"""Each agent's chain over :class:`~tg_nebp.filters.FixedLagGaussianBP`'s
    window solved exactly (a part of the tracker): the sums of the links'
    messages into every space-time node, the forward filter along each
    agent's motion factors and the RTS backward pass that smooths it, and
    the settled steps of a long window (filtered once and relinearized as
    iSAM2 relinearizes, smoothed backward from the iterated newest
    steps)."""

    def _settled_and_iterated(self, state: WindowState, window: Window,
                              points: Tensor, messages, fresh: Tensor,
                              split: int, anchor: Tensor, graph_of: Tensor,
                              num_graphs: int, generator, t: int,
                              memory: Optional[Tensor] = None):
        # a step of a window whose first 'split' steps are settled: their
        # messages held, the forward pass over them (continued from the
        # state's where it holds) is the prior of the newest steps, the
        # iterations run over the newest steps alone, and the backward
        # pass carries the result into the settled steps once. The
        # settled messages with an end that moved by more than the
        # threshold from its point are then relinearized at the smoothed
        # beliefs (its point moves there), at every relinearize_skip-th
        # time step t. Returns the window's beliefs, messages,
        # covariances, points, the settled steps' filtered means and
        # covariances that still hold, and the iterated rows' 'memory'
        num, width, size = points.shape
        agents = (~anchor).nonzero().view(-1)
        held = 0 if state.settled_mean is None else min(
            state.settled_mean.size(1), split)
        cached = None if held == 0 else (
            state.settled_mean[agents, :held],
            state.settled_cov[agents, :held])
        # the forward pass reads the sums of the steps after the held ones
        chain = self._filtered(window, points, self._sums(
            window, messages, agents, num, width, held), agents, split,
            cached, settled=True)
        newest = self._newest(window, chain, agents, split)
        rows = torch.arange(width * num, device=anchor.device) >= split * num
        kept = rows[window.factors.index[1]]
        iterated = type(messages)(*(m[kept] for m in messages))
        belief, covs = self.share(*self._solve(newest, points[:, split:],
                                               iterated, agents))
        belief, iterated, covs, memory = self._iterate_window(
            newest, belief, iterated, fresh[kept], covs, anchor, graph_of,
            num_graphs, generator, memory)
        position = kept.nonzero().view(-1)
        messages = type(messages)(*(m.index_copy(0, position, i) for m, i in
                                    zip(messages, iterated)))
        points = torch.cat([points[:, :split], belief.mean.view(
            width - split, num, size).transpose(0, 1)], 1)
        filtered_mean = torch.stack([m for m, _ in chain.filtered], 1)
        filtered_cov = torch.stack([c for _, c in chain.filtered], 1)
        mean, info, cov = self._settled_smoothed(
            window, agents, chain, points[agents, :split + 1], filtered_mean,
            filtered_cov,
            belief.mean[:num][agents], covs[agents, 0])
        settled = GaussianBelief(
            points[:, :split].transpose(0, 1).clone(
                memory_format=torch.contiguous_format),
            points.new_zeros(split, num, size, size))
        settled_cov = points.new_zeros(num, split, size, size)
        settled.mean[:, agents] = mean.transpose(0, 1)
        settled.info[:, agents] = info.transpose(0, 1)
        settled_cov[agents] = cov
        belief, covs = self.share(GaussianBelief(
            torch.cat([settled.mean.view(-1, size), belief.mean]),
            torch.cat([settled.info.view(-1, size, size), belief.info])),
            torch.cat([settled_cov, covs], 1))
        messages, points, holds = (messages, points, split) if \
            t % self.relinearize_skip else self._relinearized(
                window, belief, messages, points, split, anchor, generator)
        # the fewest over the ranks of a partitioned run (each forward
        # pass restarts where every other does)
        holds = split - int(self.largest_moves(
            points.new_full((1, ), float(split - holds)),
            torch.zeros(1, dtype=torch.long, device=points.device), 1)[0])
        if holds == 0:
            return belief, messages, covs, points, (None, None), memory
        cache_mean = points.new_zeros(num, holds, size)
        cache_cov = points.new_zeros(num, holds, size, size)
        cache_mean[agents] = filtered_mean[:, :holds]
        cache_cov[agents] = filtered_cov[:, :holds]
        return (belief, messages, covs, points, (cache_mean, cache_cov),
                memory)

    def _settled_smoothed(self, window: Window, agents: Tensor,
                          chain: Chains, points: Tensor, filtered_mean,
                          filtered_cov, mean: Tensor, cov: Tensor):
        # the backward pass over the settled steps of the agents (their
        # filtered means (A, s, S) and covariances (A, s, S, S)) from the
        # smoothed Gaussian of the step after them (mean, cov): the
        # transitions of all steps at once, then the Rauch-Tung-Striebel
        # pass over the chain at once. Returns the smoothed means,
        # information and covariances (A, s, ...); a step before an
        # agent's first holds its prior
        count = filtered_mean.size(1)
        # the transitions as the forward pass linearized them: at the
        # points (the last row of the points is not read)
        linearized = self._linearized_motion(window, points, agents)
        ahead, ahead_cov, cross = self._transition(
            linearized, points[:, :-1], (filtered_mean, filtered_cov))
        mean, cov = rts_backward_chain(filtered_mean, filtered_cov,
                                       ahead.mean, ahead_cov, cross, mean,
                                       cov)
        info = _inverse(cov)
        absent = (chain.start.view(-1, 1) > torch.arange(
            count, device=agents.device)).view(-1, count, 1, 1)
        return (torch.where(absent.squeeze(-1), chain.entry.mean.unsqueeze(1),
                            mean),
                torch.where(absent, chain.entry.info.unsqueeze(1), info),
                torch.where(absent, chain.entry_cov.unsqueeze(1), cov))

    def _newest(self, window: Window, chain: Chains, agents: Tensor,
                split: int) -> Window:
        # the window of the steps after the first 'split' (settled): every
        # agent's prior at its first step there is the forward pass's
        # prediction (the prior it joined with, if later)
        num = window.start.numel()
        prior, prior_cov = chain.after
        mean, info = (part.clone() for part in window.prior)
        cov = window.prior_cov.clone()
        mean[agents], info[agents], cov[agents] = prior.mean, prior.info, \
            prior_cov
        keep = torch.arange(window.anchor.numel(),
                            device=window.anchor.device) >= split * num
        links = keep[window.links[1]]
        return Window(
            GaussianBelief(mean, info), cov,
            (window.start - split).clamp_min(0), window.motions[split:],
            None if window.control is None else window.control[:, split:],
            window.links[:, links] - split * num, window.link_attr[links],
            window.anchor[split * num:],
            self.conv.restricted_factors(window.factors, keep,
                                         mean.size(-1)))

    def _relinearized(self, window: Window, belief: GaussianBelief,
                      messages, points: Tensor, split: int, anchor: Tensor,
                      generator):
        # the settled steps' messages of the factors with an end whose
        # smoothed mean moved by more than the threshold from its point,
        # recomputed from the smoothed beliefs (once; the points of those
        # ends move to their means). Returns the messages, the points and
        # the count of settled steps before the first that moved (their
        # forward pass holds)
        num, width, size = points.shape
        if self.relinearize_threshold is None:
            return messages, points, split
        settled = belief.mean[:split * num].view(split, num, size).transpose(
            0, 1)
        moved = ~((settled - points[:, :split]).abs().amax(-1) <=
                  self.relinearize_threshold) & ~anchor.view(-1, 1)
        steps = moved.any(0).nonzero().view(-1)
        if steps.numel() == 0:
            return messages, points, split
        rows = torch.cat([moved.t().reshape(-1), moved.new_zeros(
            (width - split) * num)])
        chosen = rows[window.factors.ends].any(1)
        points = torch.cat([torch.where(moved.unsqueeze(-1), settled,
                                        points[:, :split]),
                            points[:, split:]], 1)
        holds = int(steps[0])
        if not bool(chosen.any()):
            return messages, points, holds
        messages, _ = self._recomputed(
            window, belief, messages, chosen, torch.zeros(
                messages[0].size(0), dtype=torch.bool, device=chosen.device),
            generator)
        return messages, points, holds

    def _solve(self, window: Window, points: Tensor, messages,
               rows: Tensor, into: Optional[SolvedWindow] = None) -> SolvedWindow:
        # the windows of the agents 'rows' given their first step's prior,
        # their motion factors linearized at 'points' (N, W, S) and the
        # summed messages of each step: a Kalman filter (each update
        # Gaussian BP's belief of the step) and the backward pass. The
        # other nodes keep theirs in 'into' (by default their points and
        # no information: anchors, known states)
        num, width, size = points.shape
        chain = self._filtered(window, points, self._sums(
            window, messages, rows, num, width), rows, width)
        means, infos, covs = self._smoothed(chain, chain.last.mean,
                                            chain.last.info,
                                            chain.filtered[-1][1])
        # every node of every window step
        if into is None:
            mean = points.transpose(0, 1).clone(
                memory_format=torch.contiguous_format)
            info = points.new_zeros(width, num, size, size)
            cov = points.new_zeros(num, width, size, size)
        else:
            mean = into.belief.mean.view(width, num, size).clone()
            info = into.belief.info.view(width, num, size, size).clone()
            cov = into.cov.clone()
        mean[:, rows] = torch.stack(means)
        info[:, rows] = torch.stack(infos)
        cov[rows] = torch.stack(covs, 1)
        return SolvedWindow(GaussianBelief(mean.view(-1, size),
                                      info.view(-1, size, size)), cov)

    def _sums(self, window: Window, messages, rows: Tensor, num: int,
              width: int, first: int = 0) -> Tensor:
        # every node's summed messages at every window step (W, N, R^2 + R)
        # (only the rows' where they are few, and zero before step 'first':
        # a kept forward pass reads only the steps after it)
        factors = window.factors
        into = None
        if 2 * rows.numel() < num:
            solved = torch.zeros(num, dtype=torch.bool, device=rows.device)
            solved[rows] = True
            into = solved.repeat(width)[factors.index[1]]
        if first > 0:
            later = factors.index[1] >= first * num
            into = later if into is None else into & later
        if into is not None:
            messages = type(messages)(*(m[into] for m in messages))
            factors = factors._replace(index=factors.index[:, into])
        return self.conv.message_sums(as_factor_messages(messages), factors,
                                      num * width).view(width, num, -1)

    def _filtered(self, window: Window, points: Tensor, sums: Tensor,
                  rows: Tensor, count: int,
                  cached: Optional[Tuple[Tensor, Tensor]] = None,
                  settled: bool = False) -> Chains:
        # the forward pass of the agents 'rows' over the window's first
        # 'count' steps (each update Gaussian BP's belief of the step),
        # continued after the filtered means and covariances 'cached' of
        # its first steps where given, and the prediction into the step
        # after them where the window has one. The transitions are
        # linearized at the points (all at once: a settled step's point
        # moves only where it is relinearized, and the filter runs again
        # from there); settled steps' filtered covariances are inflated
        # (bounded) by the settled inflation: a Kalman filter linearized
        # about the points, whose steps hold from one time step to the
        # next
        start = window.start.index_select(0, rows)
        entry = GaussianBelief(*(part.index_select(0, rows)
                                 for part in window.prior))
        entry_cov = window.prior_cov.index_select(0, rows)
        here = points.index_select(0, rows)
        known = torch.zeros_like(start, dtype=torch.bool)
        reach = min(count + 1, here.size(1))
        held = 0 if cached is None else cached[0].size(1)
        base = max(held - 1, 0)  # the step the first transition leaves
        motion = self._motion_factors(window, here[:, base:reach], rows,
                                      base)
        prior, cov = entry, entry_cov
        filtered = [] if cached is None else list(zip(cached[0].unbind(1),
                                                      cached[1].unbind(1)))
        predicted, last = [], None
        for k in range(held, reach):
            if k > 0:
                linearized, point = motion[k - base], here[:, k - 1]
                prior, cov, cross = self._transition(linearized, point,
                                                     filtered[-1])
                predicted.append((prior, cov, cross))
                entering = start >= k
                if bool(entering.any()):  # not yet in the window: its prior
                    prior = GaussianBelief(*(
                        torch.where(entering.view(
                            (-1, ) + (1, ) * (e.dim() - 1)), e, p)
                        for e, p in zip(entry, prior)))
                    cov = torch.where(entering.view(-1, 1, 1), entry_cov,
                                      cov)
            if k == count:  # the step after them: its prior only
                return Chains(start, entry, entry_cov, filtered, predicted,
                              last, (prior, cov))
            last = self.conv.updated(prior, here[:, k],
                                     sums[k].index_select(0, rows), known)
            filtered_cov = _inverse(last.info)
            if settled and self.settled_inflation != 1.0:
                filtered_cov = bounded_inflation(
                    filtered_cov, cov, filtered_cov.new_full(
                        filtered_cov.shape[:1], self.settled_inflation))
            filtered.append((last.mean, filtered_cov))
        return Chains(start, entry, entry_cov, filtered, predicted, last,
                      None)

    @staticmethod
    def _smoothed(chain: Chains, mean: Tensor, info: Tensor, cov: Tensor):
        # the backward pass over the chain's filtered steps from the
        # smoothed Gaussian (mean, info, cov) of the step its last
        # prediction reaches: every step's smoothed means, information and
        # covariances, that step's last
        means, infos, covs = [mean], [info], [cov]
        start, entry, entry_cov = chain.start, chain.entry, chain.entry_cov
        for k in range(len(chain.predicted) - 1, -1, -1):
            (belief, belief_cov), (ahead, ahead_cov, cross) = \
                chain.filtered[k], chain.predicted[k]
            mean, cov = rts_backward(belief_cov, cross, ahead_cov, covs[0],
                                     belief, ahead.mean, means[0])
            info = _inverse(cov)
            absent = start > k
            if bool(absent.any()):  # not yet in the window: its prior
                mean = torch.where(absent.view(-1, 1), entry.mean, mean)
                info = torch.where(absent.view(-1, 1, 1), entry.info, info)
                cov = torch.where(absent.view(-1, 1, 1), entry_cov, cov)
            means.insert(0, mean)
            infos.insert(0, info)
            covs.insert(0, cov)
        return means, infos, covs

    def _motion_factors(self, window: Window, points: Tensor,
                        rows: Tensor, first: int = 0
                        ) -> List[Optional[Tuple[Tensor, ...]]]:
        # the window's transitions out of steps first, first + 1, ...
        # linearized at the agents' 'points' (A, P, S) of steps first, ...,
        # first + P - 1: entry j > 0 is the f, F and Q of the transition
        # into step first + j
        if points.size(1) < 2:
            return [None]
        return [None] + list(zip(*(part.unbind(1) for part in
                                   self._linearized_motion(
                                       window, points, rows, first))))

    @staticmethod
    def _linearized_motion(window: Window, points: Tensor, rows: Tensor,
                           first: int = 0) -> Tuple[Tensor, ...]:
        # the f, F and Q (A, P - 1, ...) of the transitions out of steps
        # first, ..., first + P - 2 linearized at the agents' 'points' (A,
        # P, S) of those steps (the last is not read): one call of the
        # model for all steps where they share it
        here = points[:, :-1]
        count = here.size(1)
        steps = slice(first + 1, first + 1 + count)
        control = (None if window.control is None else
                   window.control.index_select(0, rows)[:, steps])
        motions = window.motions[steps]
        if motions.count(motions[0]) == count:
            return motions[0].linearize(here, **inputs(control))
        return tuple(torch.stack(part, 1) for part in zip(*(
            motion.linearize(here[:, k], **inputs(
                None if control is None else control[:, k]))
            for k, motion in enumerate(motions))))

    @staticmethod
    def _transition(linearized: Tuple[Tensor, ...], point: Tensor,
                    previous: tuple):
        # the prior of a window step from the filtered mean and covariance
        # of the step before through the motion factor linearized at
        # 'point' (its f, F and Q): the prediction, its covariance and the
        # cross covariance P F^T, of the agents (of their steps, with a
        # dimension of steps)
        filtered_mean, cov = previous
        moved_mean, jacobian, noise = linearized
        mean = moved_mean + (
            jacobian @ (filtered_mean - point).unsqueeze(-1)).squeeze(-1)
        cross = cov @ jacobian.transpose(-1, -2)
        moved = jacobian @ cross + noise
        moved = symmetrize(moved)
        return GaussianBelief(mean, _inverse(moved)), moved, cross
