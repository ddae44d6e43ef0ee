r"""Tracking live from the command line: behind :obj:`tg-nebp track`
(:func:`track_stream`: JSON lines of measurements in, one line of
estimates per step out), :obj:`tg-nebp record` (:func:`record_realization`:
a scenario's realization as such a stream, its truth apart) and
:obj:`tg-nebp score` (:func:`score_files`)."""
import contextlib
import dataclasses
import gc
import sys
from pathlib import Path
from typing import Callable, Optional, Union

import torch

from tg_nebp.datasets import Scenario, load_datasets
from tg_nebp.experiments.evaluate import method_tracker, scenario_of
from tg_nebp.experiments.options import MethodOptions
from tg_nebp.filters.live.session import TrackingSession
from tg_nebp.io import write_text
from tg_nebp.live import (read_lines, realization_lines, score, track_lines,
                          truth_lines)

__all__ = ['LIVE_METHODS', 'track_stream', 'record_realization',
           'score_files']

#: Every tracker of :data:`~tg_nebp.experiments.options.METHODS` runs
#: live (the bound, which is not a tracker, does not).
LIVE_METHODS = ('bp', 'nebp', 'gbp', 'gnebp', 'hybrid', 'iekf')


@contextlib.contextmanager
def _opened(path: str, mode: str, standard):
    # '-' is the standard stream (left open), else the file
    if path == '-':
        yield standard
        return
    with open(path, mode, encoding='utf-8') as stream:
        yield stream


def _kept_lines(path: str, count: int) -> None:
    # a resumed run's output file: the lines of the saved steps only (a
    # killed run may have written one more), rewritten atomically
    if path == '-' or not Path(path).exists():
        return
    with open(path, encoding='utf-8') as stream:
        lines = stream.readlines()[:count]
    write_text(path, ''.join(lines))


def track_stream(method: str, input: str = '-', output: str = '-',
                 scenario: Union[str, Scenario] = 'paper_test',
                 on_error: str = 'stop', save_state: Optional[str] = None,
                 resume: Optional[str] = None, seed: int = 0,
                 device: str = 'cpu',
                 report: Optional[Callable[[str], None]] = None,
                 options: Optional[MethodOptions] = None,
                 window: Optional[str] = None, **given) -> dict:
    r"""Tracks a stream of measurement lines (:mod:`tg_nebp.live`) from
    :obj:`input` (a path, or :obj:`"-"`: standard input, read line by
    line as it arrives) with :obj:`method`'s tracker
    (:func:`~tg_nebp.experiments.evaluate.method_tracker` with the models
    of :obj:`scenario` and the :obj:`options`, a record or keywords
    :obj:`given`), writing every step's estimate
    line to :obj:`output` (:obj:`"-"`: standard output) at once, flushed.

    :obj:`save_state` saves the session after every line (atomically);
    :obj:`resume` continues a saved session: the lines it had read are
    skipped (feed the same stream again), and an output file is cut to the
    lines of the saved steps before the new ones are appended, so that it
    ends as an uninterrupted run's. A bad line ends the run with a
    :class:`ValueError` naming its line number (:obj:`on_error="stop"`) or
    is reported by :obj:`report` (standard error by default) and skipped
    (:obj:`"skip"`). A smoother's lines hold its :obj:`window`
    (:data:`~tg_nebp.live.WINDOW_LINES`: every earlier step revised, the
    final one alone, or none; :func:`~tg_nebp.live.estimate_line`; every
    earlier step by default); a :obj:`window` given to a tracker whose
    lines carry none (a filter, or the incremental smoother, whose window
    is the whole sequence) is a :class:`ValueError`, as another option a
    method does not take is.
    Returns the counts of :func:`~tg_nebp.live.track_lines`."""
    if method not in LIVE_METHODS:
        raise ValueError(f"method must be one of {', '.join(LIVE_METHODS)} "
                         f"(the bound does not track), got {method!r}")
    options = (MethodOptions.of(given) if options is None else
               dataclasses.replace(options, **given))
    if options.lag is not None and method not in ('gbp', 'hybrid') \
            and not options.incremental:
        raise ValueError(f"'lag' (--lag) tracks live with method gbp "
                         f"(fixed-lag Gaussian BP), hybrid (over it) or iekf "
                         f"--lag all --incremental (the incremental "
                         f"smoother); the batch {method} smoother is an "
                         f"offline reference")
    tracker, _ = method_tracker(method, scenario_of(scenario),
                                options=options)
    lag = getattr(tracker, 'lag', None)
    if window is not None and not (lag is not None and lag > 1):
        raise ValueError(
            f"'window' (--window) is for a smoother whose lines carry its "
            f"window (gbp or hybrid with --lag L > 1, a window checkpoint); "
            f"{method}'s lines carry "
            + ("the newest states only (the incremental smoother's window "
               "is the whole sequence: a line would grow with it)"
               if options.incremental else "no window"))
    tracker = tracker.to(device).eval()
    done = written = 0
    digests = None
    if resume is not None:
        session = TrackingSession.load(resume, tracker, device=device)
        progress = session.progress or {}
        done, written = progress.get('lines', 0), progress.get('written', 0)
        digests = progress.get('digests')
        _kept_lines(output, written)
    else:
        session = TrackingSession(tracker, seed=seed, device=device)
    if report is None:
        def report(message: str):
            sys.stderr.write(message + '\n')
            sys.stderr.flush()
    with _opened(input, 'r', sys.stdin) as source, \
            _opened(output, 'a' if resume is not None else 'w',
                    sys.stdout) as sink:
        def write(line: str):
            sink.write(line + '\n')
            sink.flush()

        # what exists now (the library, the tracker, the session) leaves
        # the collector's full passes for the run: they walked it all now
        # and then, and one step in about 50 took 0.23 s instead of 0.02
        gc.freeze()
        try:
            with torch.no_grad():
                return track_lines(session, read_lines(source), write,
                                   on_error, report, save_state, done,
                                   written, digests,
                                   'all' if window is None else window)
        finally:
            gc.unfreeze()


def record_realization(measurements: str, truth: str,
                       scenario: Union[str, Scenario] = 'paper_test',
                       index: int = 0, seed: int = 0,
                       root: str = 'datasets') -> Scenario:
    r"""Writes realization :obj:`index` of :obj:`scenario`'s test data of
    :obj:`seed` (the realizations :obj:`tg-nebp evaluate --realizations
    index + 1 --seed seed` tracks) as measurement lines
    (:func:`~tg_nebp.live.realization_lines`, the scenario's measurement
    features only) to :obj:`measurements` and its true states
    (:func:`~tg_nebp.live.truth_lines`) to :obj:`truth`, each
    atomically. Returns the scenario."""
    scenario = scenario_of(scenario)
    dataset, = load_datasets(root, (scenario, index + 1, seed))
    data = dataset[index]
    features = len(scenario.measurement_model.features)
    # a real sequence's step, a simulated network's motion model's
    dt = getattr(scenario, 'dt', None) or scenario.motion_model.params(
    ).get('dt', 1.0)
    write_text(measurements, ''.join(
        line + '\n' for line in realization_lines(data, features, dt)))
    write_text(truth, ''.join(line + '\n' for line in truth_lines(data, dt)))
    return scenario


def score_files(estimates: str, truth: str) -> dict:
    r"""The accuracy of an estimate file (:obj:`tg-nebp track`'s output)
    against a truth file (:obj:`tg-nebp record`'s):
    :func:`~tg_nebp.live.score`."""
    # past a byte-order mark, which common editors write
    with open(estimates, encoding='utf-8-sig') as e, \
            open(truth, encoding='utf-8-sig') as t:
        return score(e, t)
