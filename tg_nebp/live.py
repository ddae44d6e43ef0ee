r"""The JSON-lines format of live tracking (:obj:`tg-nebp track`): one
time step per line in, one line of estimates per step out.

A measurement line is a JSON object with any of

* :obj:`"dt"` (seconds since the last step) or :obj:`"time"` (the step's
  time; neither: the motion model's own time step),
* :obj:`"join"`: nodes that join before the step, each
  :obj:`{"id": ..., "mean": [...], "cov": [[...]]}` (an agent's prior
  over its state :math:`[\mathbf{p}, \mathbf{v}]`) or
  :obj:`{"id": ..., "anchor": [...]}` (an anchor's position),
* :obj:`"leave"`: identifiers of nodes that leave before the step,
* :obj:`"links"`: :obj:`[from, to, range]` (agent :obj:`to` measured its
  range to node :obj:`from`; further link features of the measurement
  model after the range, such as a bearing),
* :obj:`"control"`: agents' known inputs of the step (odometry) for a
  motion model that takes them, :obj:`{"r1": [...], ...}` by identifier
  (an integer identifier as its decimal string); an agent without one
  gets the model's input-free prediction.

Identifiers are strings or integers. An estimate line is
:obj:`{"t": ..., "time": ..., "estimates": [{"id": ..., "mean": [...],
"cov": [[...]]}, ...]}` with every agent's mean and covariance; a
smoother's line adds :obj:`"window": [{"t": ..., "estimates": [...]},
...]`, the revised estimates of the earlier steps of its window, oldest
first (:func:`estimate_line`).
:func:`realization_lines` writes a recorded realization in that format
(measurements only; :func:`truth_lines` the true states apart), so that
it can be replayed through the live path and scored (:func:`score`)."""
import hashlib
import json
import math
from typing import (Callable, Dict, Iterable, Iterator, List, NamedTuple,
                    Optional, TextIO, Tuple)

import torch
from torch_geometric.data import Data

from tg_nebp import metrics
from tg_nebp.data.realization import position_dim_of, scored_of
from tg_nebp.evaluation import summarize
from tg_nebp.filters.live.session import TrackingSession
from tg_nebp.filters.live.session_inputs import AgentPrior, AnchorAt
from tg_nebp.filters.tracker import StepOutput
from tg_nebp.io import first_line

__all__ = ['StreamStep', 'parse_step', 'estimate_line', 'realization_lines',
           'truth_lines', 'track_lines', 'score', 'read_lines', 'ON_ERROR',
           'WINDOW_LINES', 'StreamInterrupted']

#: What :func:`track_lines` does with a bad line: report it and go on
#: (:obj:`"skip"`) or end the run (:obj:`"stop"`).
ON_ERROR = ('skip', 'stop')

#: What a smoother's estimate line holds of its window
#: (:func:`estimate_line`, :obj:`tg-nebp track --window`): every earlier
#: step, revised at this step (:obj:`"all"`); the final one alone, the step
#: that leaves the full window at the next step (:obj:`"final"`: a line
#: whose length does not grow with the lag); or none (:obj:`"none"`).
WINDOW_LINES = ('all', 'final', 'none')


_KEYS = ('dt', 'time', 'join', 'leave', 'links', 'control')


def _check_window(window: str) -> None:
    # a value of WINDOW_LINES, else a ValueError naming it
    if window not in WINDOW_LINES:
        raise ValueError(f"'window' must be one of {list(WINDOW_LINES)}, "
                         f"got {window!r}")


class StreamStep(NamedTuple):
    r"""One measurement line, read: the arguments of
    :meth:`TrackingSession.update <tg_nebp.filters.TrackingSession.update>`."""
    links: List[tuple]
    ranges: List
    dt: Optional[float]
    time: Optional[float]
    join: Dict
    leave: List
    control: Dict = {}


def _list(value, where: str) -> list:
    if not isinstance(value, list):
        raise ValueError(f"{where} must be a list, got {value!r}")
    return value


def parse_step(text: str) -> StreamStep:
    r"""Reads one measurement line (see the module docstring); a line that
    is not a JSON object of the format is a :class:`ValueError` naming the
    field and the entry. What the entries refer to (known identifiers,
    ranges) is checked by the session."""
    try:
        line = json.loads(text)
    except ValueError as e:
        raise ValueError(f"not JSON: {e}") from None
    if not isinstance(line, dict):
        raise ValueError(f"a line is a JSON object, got "
                         f"{type(line).__name__}")
    unknown = sorted(set(line) - set(_KEYS))
    if unknown:
        raise ValueError(f"unknown field '{unknown[0]}' (a line holds "
                         f"{', '.join(_KEYS)})")
    join = {}
    for k, entry in enumerate(_list(line.get('join', []), "'join'")):
        if not isinstance(entry, dict) or 'id' not in entry:
            raise ValueError(f"'join[{k}]' must be an object with an 'id', "
                             f"got {entry!r}")
        fields = set(entry) - {'id'}
        if fields == {'anchor'}:
            prior = AnchorAt(entry['anchor'])
        elif fields == {'mean', 'cov'}:
            prior = AgentPrior(entry['mean'], entry['cov'])
        else:
            raise ValueError(f"'join[{k}]' must hold 'mean' and 'cov' (an "
                             f"agent) or 'anchor' (an anchor's position), "
                             f"got {sorted(fields)}")
        node = entry['id']
        if isinstance(node, (list, dict)):
            raise ValueError(f"'join[{k}]': the identifier {node!r} is not "
                             f"a string or an integer")
        if node in join:
            raise ValueError(f"'join[{k}]': the identifier {node!r} is "
                             f"repeated")
        join[node] = prior
    raw = _list(line.get('links', []), "'links'")
    # a malformed link is handed on as it is, without a range: the
    # session refuses that link alone, naming it
    links = [link[:2] if type(link) is list and len(link) >= 3 else link
             for link in raw]
    ranges = [(link[2:] if len(link) > 3 else link[2])
              if type(link) is list and len(link) >= 3 else None
              for link in raw]
    control = line.get('control', {})
    if not isinstance(control, dict):
        raise ValueError(f"'control' must be an object of inputs by "
                         f"identifier, got {control!r}")
    return StreamStep(links, ranges, line.get('dt'), line.get('time'), join,
                      _list(line.get('leave', []), "'leave'"), control)


def estimate_line(session: TrackingSession, output: StepOutput,
                  window: str = 'all') -> str:
    r"""The estimate line of a step's :obj:`output`: its time index, the
    session's time and every agent's mean and covariance (floats written
    exactly: they read back bit for bit); a smoother's
    (:class:`~tg_nebp.filters.FixedLagGaussianBP`) adds the revised
    estimates of the earlier steps of its window, oldest first,
    :obj:`"window": [{"t": ..., "estimates": [...]}, ...]` (the oldest is
    final: it leaves the window at the next step; an agent that joined
    since a step has no estimate there). :obj:`window`
    (:data:`WINDOW_LINES`) keeps all of them, only the final one (once the
    window is full: the step that leaves it at the next step, with its
    estimate as :class:`~tg_nebp.filters.Smoothed` gives it), or none."""
    _check_window(window)
    agents = ~session.anchor
    ids = session.agent_ids

    def estimates(means, covs, present=None):
        return [dict(id=node, mean=m, cov=c)
                for node, m, c, there in zip(ids, means, covs, present or
                                             [True] * len(ids)) if there]

    line = dict(t=output.t, time=session.time,
                estimates=estimates(output.mean[agents].tolist(),
                                    output.cov[agents].tolist()))
    width = 0 if output.window_mean is None else output.window_mean.size(1)
    full = width > 1 and width == getattr(session.tracker, 'lag', None)
    # the earlier steps written: all, the oldest of a full window, none
    count = {'all': width - 1, 'final': int(full), 'none': 0}[window]
    if count > 0:
        # one conversion of the steps written: steps first
        means = output.window_mean[agents, :count].transpose(0,
                                                             1).tolist()
        covs = output.window_cov[agents, :count].transpose(0, 1).tolist()
        # an agent that joined (or rejoined) within the window has no
        # estimate of the steps before it: left out of theirs
        start = ([0] * len(ids) if output.window_start is None else
                 output.window_start[agents].tolist())
        line['window'] = [
            dict(t=output.t - width + 1 + k,
                 estimates=estimates(means[k], covs[k],
                                     [first <= k for first in start]))
            for k in range(count)]
    return json.dumps(line)


def _step_times(data: Data, dt: float) -> List[float]:
    # the time of every step: dt summed, as a session's clock would
    times, time = [], 0.0
    for _ in range(data.num_time_steps):
        time += dt
        times.append(time)
    return times


def realization_lines(data: Data, num_features: int = 1,
                      dt: float = 1.0) -> Iterator[str]:
    r"""The measurement lines of a single realization whose steps are
    :obj:`dt` seconds apart (the motion model's): every line gives its
    step's :obj:`"time"` (so that a lost or skipped line is a longer time
    step for the next, and the estimates are matched to the truth by
    time) and the step's links in the realization's order, with the first
    :obj:`num_features` link features (the measurement model's: the true
    NLOS flag of generated data stays out); the first line joins every
    node (identifier: its index; agents with their prior, anchors at
    their position). A realization with known inputs gives every step's
    :obj:`"control"` of the agents that have one."""
    dim = position_dim_of(data)
    join = []
    for i in range(data.num_nodes):
        if bool(data.anchor[i]):
            join.append(dict(id=i, anchor=data.prior_mean[i, :dim].tolist()))
        else:
            join.append(dict(id=i, mean=data.prior_mean[i].tolist(),
                             cov=data.prior_cov[i].tolist()))
    times = _step_times(data, dt)
    for t, ((edge_index, edge_attr), control) in enumerate(zip(
            data.edges_by_step(), data.controls_by_step())):
        line = dict(time=times[t])
        if t == 0:
            line['join'] = join
        if control is not None:
            given = ~torch.isnan(control).any(-1)
            line['control'] = {str(i): control[i].tolist()
                               for i in given.nonzero().view(-1).tolist()}
        line['links'] = [
            [j, i, *features[:num_features]]
            for (j, i), features in zip(edge_index.t().tolist(),
                                        edge_attr.tolist())]
        yield json.dumps(line)


def truth_lines(data: Data, dt: float = 1.0) -> Iterator[str]:
    r"""The true states of a realization's agents, one line per time step:
    :obj:`{"t": ..., "time": ..., "states": [{"id": ..., "state": [...]},
    ...]}` (identifiers and times as :func:`realization_lines` writes
    them), with :obj:`"position_dim"` where the realization declares it
    (a state layout other than :math:`[\mathbf{p}, \mathbf{v}]`); an agent
    without ground truth (:func:`~tg_nebp.data.scored_of`) has the state
    :obj:`null` (tracked, not scored)."""
    agents = (~data.anchor).nonzero().view(-1).tolist()
    scored = scored_of(data)
    extra = ({} if getattr(data, 'position_dim', None) is None else
             dict(position_dim=position_dim_of(data)))
    for t, time in enumerate(_step_times(data, dt)):
        yield json.dumps(dict(t=t, time=time, **extra, states=[
            dict(id=i, state=data.states[i, t].tolist() if scored[i] else
                 None)
            for i in agents]))


class _ReadLines:
    # a running SHA-256 of the lines read (line endings aside), and its
    # value after every power of two of lines and after the last: what a
    # saved session keeps to know its input again, in O(log n) space
    def __init__(self):
        self.digest = hashlib.sha256()
        self.marks: Dict[str, str] = {}

    def read(self, number: int, text: str) -> str:
        self.digest.update(text.rstrip('\r\n').encode('utf-8') + b'\n')
        value = self.digest.hexdigest()
        if number & (number - 1) == 0:
            self.marks[str(number)] = value
        return value

    def saved(self, number: int) -> Dict[str, str]:
        return dict(self.marks, **{str(number): self.digest.hexdigest()})


class StreamInterrupted(KeyboardInterrupt):
    r"""An interrupt (Ctrl-C) of :func:`track_lines`, saying where the
    stream stopped: the lines tracked, the estimate lines written and the
    lines a saved state holds (each saved line is whole: a resumed run
    continues from it)."""


def _clock_kept(session: TrackingSession, text: str) -> str:
    # a skipped line's time passes all the same where it can be read (the
    # next step predicts over it); else the report says so
    try:
        step = parse_step(text)
        session.skip_step(step.dt, step.time)
    except ValueError:
        return " (its time could not be read: the clock may be off)"
    return ""


def track_lines(session: TrackingSession, lines: Iterable[str],
                write: Callable[[str], None], on_error: str = 'stop',
                report: Callable[[str], None] = print,
                save_state: Optional[str] = None, done: int = 0,
                written: int = 0,
                digests: Optional[Dict[str, str]] = None,
                window: str = 'all') -> dict:
    r"""Tracks a stream of measurement lines: every line is read
    (:func:`parse_step`), stepped (:meth:`TrackingSession.update
    <tg_nebp.filters.TrackingSession.update>`) and its estimate line
    written by :obj:`write` before the next line is read. A bad line is a
    :class:`ValueError` starting with its line number under
    :obj:`on_error="stop"`, or is reported (:obj:`report`) and skipped
    under :obj:`"skip"` (its time passes all the same where it can be
    read, :meth:`~tg_nebp.filters.TrackingSession.skip_step`; where it
    cannot, the report says that the clock may be off); either way the
    session is as before it. A link that fails its checks costs that
    link only: it is left out and reported (its line and position), and
    the step goes on with the others. With
    :obj:`save_state` the session is saved after every line (atomically),
    with the lines read and estimate lines written and the running
    SHA-256 of the lines read (after every power of two of lines and
    after the last), which a resumed run (:obj:`done`, :obj:`written`,
    :obj:`digests`: the saved ones) skips and continues: an input that
    does not start with the lines the session read is a
    :class:`ValueError` naming the lines where it first differs (between
    two saved digests). Blank lines are ignored. An interrupt (Ctrl-C) is
    a :class:`StreamInterrupted` saying where the stream stopped (what was
    saved and written before it stays whole). A smoother's lines hold
    its :obj:`window` as :func:`estimate_line` writes it. Returns the
    counts: :obj:`lines`, :obj:`written`, :obj:`skipped`."""
    if on_error not in ON_ERROR:
        raise ValueError(f"'on_error' must be one of {list(ON_ERROR)}, got "
                         f"{on_error!r}")
    _check_window(window)
    progress = dict(lines=done, written=written, skipped=0)
    try:
        return _tracked(session, lines, write, on_error, report, save_state,
                        done, digests, progress, window)
    except KeyboardInterrupt:
        saved = (f"; the saved state holds lines 1-{progress['lines']}"
                 if save_state is not None else '')
        raise StreamInterrupted(
            f"stopped at line {progress['lines'] + 1}: lines 1-"
            f"{progress['lines']} tracked ({progress['skipped']} skipped), "
            f"{progress['written']} estimate lines written{saved}"
        ) from None


def _tracked(session, lines, write, on_error, report, save_state, done,
             digests, progress, window) -> dict:
    # the loop of track_lines, keeping 'progress' (the lines done, the
    # estimate lines written, the lines skipped) as it goes
    skipped, number, matched, written = 0, 0, 0, progress['written']
    read = _ReadLines()
    for number, text in enumerate(lines, 1):
        if number == 1:  # a byte-order mark, which common editors write
            text = text.lstrip('\ufeff')
        value = read.read(number, text)
        if number <= done:
            expected = (digests or {}).get(str(number))
            if expected is not None and expected != value:
                raise ValueError(
                    f"the input is not the one the saved session read: it "
                    f"differs from it in lines {matched + 1}-{number} (the "
                    f"session read {done} lines)")
            if expected is not None:
                matched = number
            continue
        if text.strip():
            try:
                step = parse_step(text)
                output = session.update(step.links, step.ranges, step.dt,
                                        step.time, step.join, step.leave,
                                        step.control, bad_links='drop')
            except (ValueError, torch.linalg.LinAlgError) as e:
                message = f"line {number}: {e}"
                if on_error == 'stop':
                    raise ValueError(message) from None
                report(f"skipped {message}{_clock_kept(session, text)}")
                skipped += 1
            else:
                for _, why in session.refused_links:
                    report(f"line {number}: left out {why}")
                write(estimate_line(session, output, window))
                written += 1
        if save_state is not None:
            session.save(save_state, progress=dict(
                lines=number, written=written, digests=read.saved(number)))
        progress.update(lines=number, written=written, skipped=skipped)
    if number < done:
        raise ValueError(f"the input ended after {number} lines; the saved "
                         f"session read {done} of it")
    return dict(lines=max(number, done), written=written, skipped=skipped)


def _objects(lines: Iterable[str], what: str, fields: tuple
             ) -> Iterator[Tuple[int, dict]]:
    # the JSON objects of a file's lines, each with the fields given and
    # its line number; any other line is named
    for number, text in enumerate(lines, 1):
        if not text.strip():
            continue
        try:
            line = json.loads(text)
        except ValueError as e:
            raise ValueError(f"{what} line {number}: not JSON: {e}"
                             ) from None
        missing = [f for f in fields if not isinstance(line, dict) or
                   f not in line]
        if missing:
            raise ValueError(f"{what} line {number}: no '{missing[0]}'")
        yield number, line


def _time_of(line: dict, where: str) -> float:
    # a line's time: a finite number
    time = line['time']
    if isinstance(time, bool) or not isinstance(time, (int, float)) or \
            not math.isfinite(time):
        raise ValueError(f"{where}: 'time' must be a finite number, got "
                         f"{time!r}"[:200])
    return float(time)


def _entries(line: dict, field: str, where: str) -> list:
    # a line's list of objects with an 'id'
    entries = line[field]
    if not isinstance(entries, list):
        raise ValueError(f"{where}: '{field}' must be a list, got "
                         f"{entries!r}"[:200])
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict) or 'id' not in entry:
            raise ValueError(f"{where}: '{field}[{k}]' must be an object "
                             f"with an 'id', got {entry!r}"[:200])
    return entries


def score(estimates: Iterable[str], truth: Iterable[str]) -> dict:
    r"""The accuracy of estimate lines against truth lines
    (:func:`truth_lines`), matched by time and identifier: the
    :obj:`metrics.json` entry of :func:`~tg_nebp.evaluation.summarize`
    (RMSE, outage, P(accept)), computed as an evaluation of a Gaussian
    tracker computes it (positions in float64, the truth in the stored
    float32), with the number of steps and estimates scored and what the
    truth holds that no estimate covers (:obj:`"unscored_steps"`: truth
    times without an estimate line, :obj:`"unscored_states"`: true states
    without an estimate, both counted over the times estimated and not;
    :obj:`"without_truth"`: estimates of agents whose truth is
    :obj:`null`, tracked and not scored).
    A malformed line or entry (a time that is not a number, entries that
    are not a list of objects with an :obj:`"id"`, a mean or covariance
    that is not finite numbers of the truth's size), a time given twice
    in either file, an estimate of a time or node without truth is a
    :class:`ValueError` naming its line."""
    states, position_dims = {}, {}
    for number, line in _objects(truth, 'truth', ('time', 'states')):
        where = f"truth line {number}"
        time = _time_of(line, where)
        if time in states:
            raise ValueError(f"{where}: time {time} is given twice")
        step = {}
        for k, entry in enumerate(_entries(line, 'states', where)):
            state = entry.get('state')
            if state is None:  # an agent without ground truth
                step[json.dumps(entry['id'])] = None
                continue
            if not isinstance(state, list) or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool)
                    and math.isfinite(v) for v in state):
                raise ValueError(f"{where}: 'states[{k}]' must hold a "
                                 f"'state' of finite numbers (or null: "
                                 f"no ground truth)")
            step[json.dumps(entry['id'])] = state
        states[time] = step
        position_dims[time] = line.get('position_dim')
    errors, nees, seen, dim, without_truth = [], [], set(), 2, 0
    for number, line in _objects(estimates, 'estimates',
                                 ('time', 'estimates')):
        where = f"estimates line {number}"
        time = _time_of(line, where)
        where = f"{where} (time {line['time']})"
        step = states.get(time)
        if step is None:
            raise ValueError(f"{where}: no truth at that time")
        if time in seen:
            raise ValueError(f"{where}: that time is estimated twice")
        seen.add(time)
        entries = _entries(line, 'estimates', where)
        if not entries:  # no agent at that time
            continue
        missing = [e['id'] for e in entries
                   if json.dumps(e['id']) not in step]
        if missing:
            raise ValueError(f"{where}: no true state of {missing[0]!r}")
        rows = [(e, step[json.dumps(e['id'])]) for e in entries]
        without_truth += sum(s is None for _, s in rows)
        rows = [(e, s) for e, s in rows if s is not None]
        if not rows:  # only agents without ground truth
            continue
        try:
            # the stored truth's float32, as an evaluation reads it
            true = torch.tensor([s for _, s in rows], dtype=torch.float32)
            mean = torch.tensor([e['mean'] for e, _ in rows],
                                dtype=torch.float64)
            cov = torch.tensor([e['cov'] for e, _ in rows],
                               dtype=torch.float64)
            if mean.shape != true.shape or \
                    cov.shape != true.shape + true.shape[-1:]:
                raise ValueError('sizes differ')
        except (KeyError, TypeError, ValueError, OverflowError,
                RuntimeError) as e:
            raise ValueError(f"{where}: an estimate without a 'mean' and "
                             f"'cov' of the truth's size ({first_line(e)})"
                             ) from None
        if not bool(mean.isfinite().all() & cov.isfinite().all()):
            raise ValueError(f"{where}: an estimate that is not finite")
        dim = position_dims[time] or true.size(-1) // 2
        errors.append(metrics.position_errors(mean[:, :dim],
                                              true[:, :dim]))
        nees.append(metrics.nees(mean[:, :dim], cov[:, :dim, :dim],
                                 true[:, :dim]))
    if not errors:
        raise ValueError("no estimate lines to score")
    entry = summarize(torch.cat(errors), torch.cat(nees), dof=dim)
    scored = int(sum(e.numel() for e in errors))
    entry.update(steps=len(errors), estimates=scored,
                 unscored_steps=len(set(states) - seen),
                 unscored_states=sum(s is not None for step in states.values()
                                     for s in step.values()) - scored,
                 without_truth=without_truth)
    return entry


def read_lines(stream: TextIO) -> Iterator[str]:
    r"""The lines of :obj:`stream` as they arrive (no read-ahead that
    would wait for more input than one line)."""
    return iter(stream.readline, '')
