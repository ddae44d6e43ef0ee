r"""Whether better candidates could relocate the window's lost agents
(issue 64, item 1): fixed-lag Gaussian BP of ``--lag`` steps with the
relocation with hindsight (:class:`~tg_nebp.filters.TrajectorySearch`),
its search given one more candidate per agent, the window trajectory
translated by its mean offset from the truth over the window (an oracle:
the truth is read only to place that candidate, then taken to its
optimum by the search's own Gauss-Newton steps and scored by the window's
own likelihood like every other). Printed: for every search of an agent
whose window is more than 5 m off the truth on average, whether the
truth's candidate beats the agent's trajectory by the search's margin,
whether it is the best candidate and whether the agent moved there; and
the tracker's RMSE, P_out(1 m), largest error and lost agents with and
without the oracle's candidate, filtered and smoothed. If the truth's
own candidate rarely wins, no candidate of one agent can: the window's
links, its neighbours' beliefs held, favour where it is.

    python benchmarks/window_truth_candidate.py --scenario \
        paper_test_sparse --realizations 10 --seed 1 --lag 10
"""
import argparse

import torch

from lost_agents import LOST, realizations, report  # beside this one
from tg_nebp.filters import FixedLagGaussianBP, Smoothed, TrajectorySearch


class WithTruthCandidate(TrajectorySearch):
    r""":class:`~tg_nebp.filters.TrajectorySearch` with one more candidate
    per agent: its window trajectory translated by its mean offset from
    :obj:`truth` :math:`(N, T, S)` over the window's steps (set before each
    realization); every search of a lost agent is recorded."""
    def __init__(self):
        super().__init__()
        self.truth, self.t, self.records = None, 0, []

    def due(self, fresh, anchor, graph_of, t):
        self.t = t  # the window's newest time index
        return super().due(fresh, anchor, graph_of, t)

    def _truth_window(self, points, dim):
        width = points.size(1)
        return self.truth[:, self.t - width + 1:self.t + 1, :dim].to(points)

    def _transforms(self, conv, points, sourced, into, link_attr, pairs,
                    degree, agent, dim):
        rotation, offset = super()._transforms(
            conv, points, sourced, into, link_attr, pairs, degree, agent,
            dim)
        if self.truth is None:
            return rotation, offset
        shift = (self._truth_window(points, dim) - points[..., :dim]).mean(1)
        eye = torch.eye(dim, dtype=points.dtype, device=points.device)
        return (torch.cat([rotation, eye.expand(points.size(0), 1, dim, dim)],
                          1), torch.cat([offset, shift.unsqueeze(1)], 1))

    def search_window(self, conv, points, *args, **kwargs):
        result = super().search_window(conv, points, *args, **kwargs)
        if self.truth is None or result.scores.size(1) == 1:
            return result  # nobody searched: no candidate at all
        dim = result.curvature.size(-1)
        off = (points[..., :dim] - self._truth_window(points, dim)).norm(
            dim=-1).mean(1)
        for agent in ((off > LOST) & result.searched).nonzero().flatten():
            scores = result.scores[agent]
            best = int(result.best[agent]) == scores.numel() - 1
            self.records.append((
                float(scores[-1] - scores[0]) > self.margin, best,
                best and bool(result.moved[agent])))
        return result


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    args, dataset, models = realizations(parser)
    for oracle in (False, True):
        search = WithTruthCandidate() if oracle else TrajectorySearch()
        tracker = FixedLagGaussianBP.recommended(lag=args.lag,
                                                 relocation=search, **models)
        name = (f'gbp-lag{args.lag} + TrajectorySearch' +
                (" + the truth's candidate" if oracle else ''))
        for key, method in [(name, tracker),
                            (name + ', smoothed', Smoothed(tracker))]:
            report(key, method, dataset, before=lambda data: setattr(
                search, 'truth', data.states.double()) if oracle else None)
        if oracle:
            # both runs (filtered, smoothed) searched alike: the first's
            records = search.records[:len(search.records) // 2]
            print(f"searches of an agent more than {LOST:g} m off over the "
                  f"window: {len(records)}; the truth's candidate beats its "
                  f"trajectory by the margin in "
                  f"{sum(r[0] for r in records)}, is the best in "
                  f"{sum(r[1] for r in records)}, and the agent is moved "
                  f"there in {sum(r[2] for r in records)}")


if __name__ == '__main__':
    main()
