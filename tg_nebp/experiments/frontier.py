r"""The accuracy-cost frontier of particle BP: a grid of particle counts
:math:`K`, sender samples :math:`M` and resampling options run on the same
test realizations with the same prior particle draws, each point's outage,
consistency and seconds per realization, and the Pareto-optimal points.

Behind :obj:`tg-nebp frontier`, which writes :obj:`frontier.json` after
every point (an interrupted run resumes where it stopped),
:obj:`frontier.md` and :obj:`frontier.png`."""
import contextlib
import itertools
import os
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Union

from tg_nebp.evaluation import (CONFIDENCE_KEY, OUTAGE_KEY, summarize_result,
                                track_dataset)
from tg_nebp.datasets import Scenario, load_datasets
from tg_nebp.experiments.evaluate import check_run
from tg_nebp.filters import ParticleBP
from tg_nebp.io import NUMBER, read_resumable, write_json, write_text

__all__ = ['GridPoint', 'grid', 'pareto_front', 'run_frontier',
           'frontier_table', 'frontier', 'FRONTIER_VERSION']

#: The format version of :obj:`frontier.json` (2: the settings hold the
#: scenario's fingerprint).
FRONTIER_VERSION = 2


class GridPoint(dict):
    r"""One configuration of the grid: :obj:`particles`, :obj:`samples`,
    :obj:`resampler`, :obj:`regularize`, :obj:`ess_threshold`; its
    :attr:`~tg_nebp.experiments.frontier.GridPoint.key` names it in
    :obj:`frontier.json`."""
    @property
    def key(self) -> str:
        r"""The point's name, :obj:`"particles=K samples=M ..."`."""
        return ' '.join(f'{name}={value}' for name, value in self.items())

    def tracker(self, **models) -> ParticleBP:
        r"""The :class:`~tg_nebp.filters.ParticleBP` of this point, with
        the motion and measurement models :obj:`models`."""
        return ParticleBP(self['particles'], num_samples=self['samples'],
                          resampler=self['resampler'],
                          regularize=self['regularize'],
                          ess_threshold=self['ess_threshold'], **models)


def grid(particles: Sequence[int], samples: Sequence[Union[int, str]],
         resamplers: Sequence[str] = ('multinomial', ),
         regularize: Sequence[Union[float, str, None]] = (None, ),
         ess_thresholds: Sequence[Optional[float]] = (None, )
         ) -> List[GridPoint]:
    r"""The product of the options, cheapest :math:`K \cdot M` first;
    points with :math:`M > K` are left out (they do not exist)."""
    points = []
    for k, m, resampler, h, ess in itertools.product(
            particles, samples, resamplers, regularize, ess_thresholds):
        if m != 'all' and m > k:
            continue
        points.append(GridPoint(particles=k, samples=m, resampler=resampler,
                                regularize=h, ess_threshold=ess))
    return sorted(points, key=lambda p: p['particles'] * (
        p['particles'] if p['samples'] == 'all' else p['samples']))


def pareto_front(costs: Sequence[float],
                 losses: Sequence[float]) -> List[bool]:
    r"""Marks the points that no other point dominates (no more cost and
    no more loss, and less of one of them); a NaN loss is never on the
    front."""
    on_front = []
    for i, (cost, loss) in enumerate(zip(costs, losses)):
        dominated = loss != loss or any(
            c <= cost and v <= loss and (c < cost or v < loss)
            for j, (c, v) in enumerate(zip(costs, losses)) if j != i)
        on_front.append(not dominated)
    return on_front


def _settings(dataset, seed: int, device: str, batch_size: int,
              compile: bool) -> dict:
    # a scenario is its fingerprint (every generation parameter), not its
    # name: a file changed under the same name is another scenario
    return dict(version=FRONTIER_VERSION, scenario=dataset.scenario.name,
                fingerprint=dataset.scenario.fingerprint(),
                realizations=len(dataset), seed=seed, device=device,
                batch_size=batch_size, compile=compile)


# what every point of frontier.json holds, as the table and figure read it
POINT_SCHEMA = dict(outage={'0.5': NUMBER, '1.0': NUMBER, '2.0': NUMBER},
                    accept={CONFIDENCE_KEY: NUMBER},
                    seconds_per_realization=NUMBER, particles=int,
                    samples=(int, str), resampler=str,
                    regularize=(int, float, str, type(None)),
                    ess_threshold=(int, float, type(None)))


def _mark_fronts(points: Dict[str, dict]) -> None:
    entries = list(points.values())
    seconds = [e['seconds_per_realization'] for e in entries]
    outage = [e['outage'][OUTAGE_KEY] for e in entries]
    gap = [abs(e['accept'][CONFIDENCE_KEY] - float(CONFIDENCE_KEY))
           for e in entries]
    for entry, on_outage, on_accept in zip(entries,
                                           pareto_front(seconds, outage),
                                           pareto_front(seconds, gap)):
        entry['pareto'] = dict(outage=on_outage, accept=on_accept)


def run_frontier(points: Iterable[GridPoint], dataset, out: Path,
                 seed: int = 0, device: str = 'cpu', batch_size: int = 1,
                 progress: Optional[Callable] = None,
                 log: Callable = print, compile: bool = False) -> dict:
    r"""Runs every grid point on :obj:`dataset` and returns the content of
    :obj:`out/frontier.json`, written after every point.

    Points already in that file are skipped (resuming), as long as it was
    made with the same scenario, realizations, seed, device, batch size and
    :obj:`compile`;
    another file is an error rather than a mix of incomparable figures.
    Every point tracks the same realizations with the same prior particle
    draws (:func:`~tg_nebp.evaluation.track_dataset` with :obj:`seed`) and
    records its accuracy (:func:`~tg_nebp.evaluation.summarize`), its wall
    seconds per realization and the load average of the machine when it
    started (timings on a busy machine are not comparable).

    Args:
        points (iterable of GridPoint): The configurations (:func:`grid`).
        dataset: The test realizations, with a :obj:`scenario`.
        out (Path): Folder of :obj:`frontier.json`.
        seed (int, optional): Seed of the particle draws. (default: :obj:`0`)
        device (str, optional): Device. (default: :obj:`"cpu"`)
        batch_size (int, optional): Realizations tracked together.
            (default: :obj:`1`)
        progress (callable, optional): Called with the number of time steps
            done. (default: :obj:`None`)
        log (callable, optional): Receives one line per point.
            (default: :obj:`print`)
        compile (bool, optional): Fuse the per-edge work with
            :func:`torch.compile` (see :class:`~tg_nebp.filters.ParticleBP`).
            (default: :obj:`False`)
    """
    path = Path(out) / 'frontier.json'
    settings = _settings(dataset, seed, device, batch_size, compile)
    result = read_resumable(path, settings, 'points', 'a frontier',
                            POINT_SCHEMA)
    if result['points']:  # a file from before the marks, or edited
        _mark_fronts(result['points'])
    scenario = dataset.scenario
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model, compile=compile)
    # every point's options are checked before the first one runs
    trackers = [(point, point.tracker(**models)) for point in points]
    steps = len(dataset) * scenario.num_steps
    for point, tracker in trackers:
        if point.key in result['points']:
            if progress is not None:
                progress(steps)
            continue
        load = os.getloadavg()[0]
        tracker = tracker.to(device).eval()
        start = time.perf_counter()
        tracked = track_dataset(tracker, dataset, batch_size, device, seed,
                                progress=progress)
        seconds = time.perf_counter() - start
        entry = summarize_result(tracked)
        entry.update(dict(point), seconds=round(seconds, 3),
                     seconds_per_realization=round(seconds / len(dataset),
                                                   4),
                     load_average=round(load, 2))
        result['points'][point.key] = entry
        _mark_fronts(result['points'])
        write_json(path, result)
        log(f"{point.key}: P_out(1 m) {entry['outage'][OUTAGE_KEY]:.3f}, "
            f"P(accept 0.95) {entry['accept'][CONFIDENCE_KEY]:.3f}, "
            f"{entry['seconds_per_realization']:.2f} s per realization")
    return result


def frontier_table(frontier: dict) -> str:
    r"""The points of :obj:`frontier.json` as a Markdown table, fastest
    first; :obj:`*` marks a point on the Pareto front of the outage
    (first) and of the consistency (second)."""
    settings = frontier['settings']
    lines = [f"Scenario `{settings['scenario']}`, {settings['realizations']} "
             f"realizations, seed {settings['seed']}, {settings['device']}.",
             '', '| K | M | resampler | regularize | ESS threshold | '
             'P_out 0.5 / 1 / 2 m | P(accept 0.95) | s per realization | '
             'Pareto |', '| --- ' * 9 + '|']
    for e in sorted(frontier['points'].values(),
                    key=lambda e: e['seconds_per_realization']):
        o, front = e['outage'], e['pareto']
        marks = ''.join('*' if front[p] else '-' for p in ('outage',
                                                            'accept'))
        lines.append(
            f"| {e['particles']} | {e['samples']} | {e['resampler']} | "
            f"{e['regularize'] or 'no'} | {e['ess_threshold'] or 'no'} | "
            f"{o['0.5']:.3f} / {o['1.0']:.3f} / {o['2.0']:.3f} | "
            f"{e['accept'][CONFIDENCE_KEY]:.3f} | "
            f"{e['seconds_per_realization']:.2f} | {marks} |")
    return '\n'.join(lines) + '\n'


def frontier(particles: Sequence[int], samples: Sequence[Union[int, str]],
             resamplers: Sequence[str] = ('multinomial', ),
             regularize: Sequence[Union[float, str, None]] = (None, ),
             ess_threshold: Sequence[Optional[float]] = (None, ),
             scenario: Union[str, Scenario] = 'paper_test',
             realizations: int = 20, seed: int = 0,
             out: Union[str, Path] = 'results/frontier',
             root: str = 'datasets', device: str = 'cpu',
             batch_size: int = 1, compile: bool = False,
             progress_factory: Optional[Callable] = None,
             log: Callable = print) -> dict:
    r"""Behind :obj:`tg-nebp frontier`: runs the :func:`grid` of the
    options on :obj:`realizations` realizations of :obj:`scenario`
    (:func:`run_frontier`, resumable) and writes :obj:`out/frontier.md`
    (:func:`frontier_table`) and :obj:`out/frontier.png`
    (:func:`~tg_nebp.plot.plot_frontier`).

    Args:
        progress_factory (callable, optional): :obj:`(total, description)`
            to a context manager whose :obj:`update(n)` is called after
            every time step, and whose :obj:`write`, when it has one,
            replaces :obj:`log` (a progress bar). (default: :obj:`None`)
        log (callable, optional): Receives one line per point.
            (default: :obj:`print`)

    Returns:
        The content of :obj:`out/frontier.json`.
    """
    from tg_nebp.plot import plot_frontier

    check_run(realizations, batch_size, device)
    points = grid(particles, samples, resamplers, regularize, ess_threshold)
    if not points:
        raise ValueError('the grid is empty: every --samples M exceeds '
                         'every --particles K')
    dataset, = load_datasets(root, (scenario, realizations, seed))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    total = len(points) * len(dataset) * dataset.scenario.num_steps
    bar = (progress_factory(total, f'frontier ({len(points)} points)')
           if progress_factory is not None else None)
    with (bar if bar is not None else contextlib.nullcontext()):
        result = run_frontier(points, dataset, out, seed, device, batch_size,
                              progress=getattr(bar, 'update', None),
                              log=getattr(bar, 'write', log),
                              compile=compile)
    write_text(out / 'frontier.md', frontier_table(result))
    plot_frontier(result, out / 'frontier.png')
    return result
