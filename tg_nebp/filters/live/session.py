r"""Tracking live: a session that feeds any tracker one time step at a time,
as the measurements of a real network arrive, with nodes addressed by the
user's own identifiers, agents that join and leave, a time step that
differs per step, and a state that a restarted process continues from.

The session holds the tracker's state between steps and calls the same
:meth:`step <tg_nebp.filters.GaussianBP.step>` that the offline loop
(:meth:`~tg_nebp.filters.Tracker.steps`) calls, so streaming a recorded
realization gives what tracking it offline gives."""
import hashlib
import json
import math
import numbers
import re
from pathlib import Path
from typing import (Any, Dict, Hashable, List, Mapping, Optional, Sequence,
                    Tuple, Union)

import torch
from torch import Tensor

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import (check_position_dim, check_prior,
                                     check_state_dim, magnitude_limit)
from tg_nebp.filters.live.session_inputs import (LONGEST_SECONDS, AgentPrior,
                                                 AnchorAt, Identifier,
                                                 checked_identifier,
                                                 checked_numbers, identified,
                                                 seconds_or_none)
from tg_nebp.filters.tracker import StepOutput, Tracker
from tg_nebp.io import atomic_write, first_line, read_tensors

__all__ = ['TrackingSession', 'AgentPrior', 'AnchorAt', 'SESSION_FORMAT',
           'SESSION_VERSION', 'BAD_LINKS']

#: The :obj:`format` entry of a saved session.
SESSION_FORMAT = 'tg_nebp-session'
#: The version of the saved session's layout that this library writes and
#: reads.
SESSION_VERSION = 1
#: What :meth:`TrackingSession.update` does with a link that fails its
#: checks: refuse the step (:obj:`"raise"`) or leave the link out
#: (:obj:`"drop"`).
BAD_LINKS = ('raise', 'drop')
#: The types a session hands its tracker, by the name a saved one stores.
_DTYPES = {str(t).replace('torch.', ''): t
           for t in (torch.float16, torch.bfloat16, torch.float32,
                     torch.float64)}


def _fingerprint(tracker: Tracker) -> str:
    # the learned parameters and buffers, hashed: a session continues
    # under the network it was run with only
    digest = hashlib.sha256()
    for name, value in sorted(tracker.state_dict().items()):
        digest.update(name.encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


class TrackingSession:
    r"""A tracker run live, one time step at a time: created from the
    prior of the agents and the anchors, then fed every step's links and
    ranges by :meth:`~tg_nebp.filters.TrackingSession.update`, which
    returns that step's :class:`~tg_nebp.filters.StepOutput` (rows in the
    order of :attr:`~tg_nebp.filters.TrackingSession.ids`). Nodes are
    addressed by the user's identifiers (strings or integers); agents join
    (:class:`AgentPrior`) and anchors are added (:class:`AnchorAt`) before
    any step, and both leave; each step may have its own time step
    :obj:`dt` (the motion model's
    :meth:`~tg_nebp.models.MotionModel.with_time_step`).

    Every step runs the tracker's own :meth:`step
    <tg_nebp.filters.GaussianBP.step>`, the function of its offline loop:
    a realization streamed step by step gives what
    :meth:`~tg_nebp.filters.Tracker.steps` gives (bit for bit, and for
    the particle trackers with the same generator). A step's input is
    checked whole before anything changes; a step that fails leaves the
    session (state, generator, clock, nodes) as it was.

    :meth:`state_dict` and :meth:`save` hold everything to continue
    (beliefs, particles, the generator's state, the clock, the nodes);
    :meth:`load_state_dict` and :meth:`load` refuse, by name, a session of
    another tracker, configuration, model or network, and never run code
    from a file.

    Args:
        tracker (Tracker): The tracker (any of the library's, or a user's
            with :meth:`~tg_nebp.filters.Tracker.initial_state` and
            :meth:`~tg_nebp.filters.Tracker.step`).
        nodes (dict, optional): The nodes before the first step, by
            identifier, in row order: :class:`AgentPrior` or
            :class:`AnchorAt`. (default: none; join them with the first
            :meth:`update`)
        generator (torch.Generator, optional): The source of every draw
            (particles, resampling); a new one seeded with :obj:`seed` if
            :obj:`None`. (default: :obj:`None`)
        seed (int, optional): The seed of the session's own generator.
            (default: :obj:`0`)
        time (float, optional): The time of the prior, in seconds.
            (default: :obj:`0.0`)
        dtype (torch.dtype, optional): The type of the priors and ranges
            handed to the tracker (the Gaussian trackers compute in
            float64 whatever it is). (default: :obj:`torch.float32`, a
            generated realization's)
        device (str, optional): Device. (default: :obj:`"cpu"`)
    """
    def __init__(self, tracker: Tracker,
                 nodes: Optional[Mapping[Hashable, Any]] = None,
                 generator: Optional[torch.Generator] = None, seed: int = 0,
                 time: float = 0.0, dtype: torch.dtype = torch.float32,
                 device='cpu'):
        if not isinstance(tracker, Tracker):
            raise TypeError(f"'tracker' must be a Tracker, got "
                            f"{type(tracker).__name__}")
        if tracker.state_type is None:
            raise ValueError(
                f"'tracker' {type(tracker).__name__} does not run live: it "
                f"keeps no state from one line to the next (an offline "
                f"smoother, or Smoothed: a live smoother's estimate lines "
                f"carry their window, the oldest step final)")
        if dtype not in _DTYPES.values():
            raise ValueError(f"'dtype' must be one of "
                             f"{sorted(_DTYPES)}, got {dtype}")
        self.tracker = tracker
        self.device = torch.device(device)
        self.dtype = dtype
        self.generator = (torch.Generator(self.device).manual_seed(seed)
                          if generator is None else generator)
        if seconds_or_none(time) is None:
            raise ValueError(f"'time' must be a finite number (at most "
                             f"{LONGEST_SECONDS:.0e} s), got {time!r}"[:200])
        self.time = float(time)
        #: The time index of the next step (the steps done).
        self.num_steps = 0
        #: What the caller saved with the session (:meth:`save`), once
        #: loaded (:meth:`load`).
        self.progress = None
        #: The time of the steps skipped since the last (:meth:`skip_step`),
        #: which the next :meth:`update` predicts over.
        self.skipped_time = 0.0
        #: The links that the last :meth:`update` left out under
        #: :obj:`bad_links="drop"`: their positions and why.
        self.refused_links: List[Tuple[int, str]] = []
        self._ids: List[Identifier] = []
        self._row: Dict[Identifier, int] = {}
        self.anchor = torch.zeros(0, dtype=torch.bool, device=self.device)
        self.state = None
        self.state_size: Optional[int] = None
        if nodes:
            self._commit(*self._changed(leave=(), join=nodes))

    # ---- the nodes

    @property
    def ids(self) -> List[Identifier]:
        r"""The identifiers of the nodes, in the order of the rows of every
        :class:`~tg_nebp.filters.StepOutput` (agents and anchors)."""
        return list(self._ids)

    @property
    def agent_ids(self) -> List[Identifier]:
        r"""The identifiers of the agents, in row order."""
        return [i for i, a in zip(self._ids, self.anchor.tolist()) if not a]

    def estimates(self, output: StepOutput
                  ) -> Dict[Identifier, Tuple[Tensor, Tensor]]:
        r"""Every agent's mean :math:`(S)` and covariance :math:`(S, S)` of
        a step's :obj:`output`, by identifier."""
        return {i: (output.mean[r], output.cov[r])
                for r, (i, a) in enumerate(zip(self._ids,
                                               self.anchor.tolist()))
                if not a}

    # ---- a step

    def update(self, links: Sequence[Sequence[Identifier]] = (),
               ranges: Sequence = (), dt: Optional[float] = None,
               time: Optional[float] = None,
               join: Optional[Mapping[Hashable, Any]] = None,
               leave: Sequence[Identifier] = (),
               control: Optional[Mapping[Hashable, Any]] = None,
               bad_links: str = 'raise') -> StepOutput:
        r"""One time step: first the nodes of :obj:`leave` leave and those
        of :obj:`join` join (:class:`AgentPrior`, :class:`AnchorAt`, in
        that order, appended to the rows), then the tracker predicts over
        the time step and updates with the links.

        Args:
            links (sequence): :obj:`(from, to)` identifier pairs: agent
                :obj:`to` measured its range to node :obj:`from`.
                (default: none: the step predicts only)
            ranges (sequence): One measured range per link (or a row of
                the measurement model's link features, the range first).
            dt (float, optional): The time since the last step in seconds
                (the motion model's own :obj:`dt` if neither it nor
                :obj:`time` is given).
            time (float, optional): The time of this step; :obj:`dt` is
                then the time since the last.
            join (dict, optional): Joining nodes by identifier.
            leave (sequence, optional): Identifiers of leaving nodes.
            control (dict, optional): Agents' known inputs of the step
                (odometry) by identifier, :math:`C` numbers each, for a
                motion model that takes them
                (:attr:`~tg_nebp.models.MotionModel.control_dim`); an
                agent without one gets the model's input-free prediction.
                A key that is the decimal string of an integer identifier
                names it (JSON object keys are strings).
            bad_links (str, optional): What a link that fails its checks
                (an unknown or malformed end, a link to itself or into an
                anchor, a range that is not finite, too large, negative
                where the likelihood needs it non-negative, of another
                number of features than the model reads, a repeated link)
                does: :obj:`"raise"` refuses the step (a
                :class:`ValueError` naming the first); :obj:`"drop"`
                leaves those links out, lists them in
                :attr:`refused_links` (position and why), and the step
                goes on with the others. (default: :obj:`"raise"`)

        Returns:
            The step's :class:`~tg_nebp.filters.StepOutput`, rows in the
            order of :attr:`ids`.
        """
        if bad_links not in BAD_LINKS:
            raise ValueError(f"'bad_links' must be one of {list(BAD_LINKS)}"
                             f", got {bad_links!r}")
        dt, motion = self._time_step(dt, time)
        # everything is checked and computed before anything changes; the
        # generator (the joining particles' draws, the step's) is put back
        # if anything fails
        random = self.generator.get_state()
        ids = self._ids
        try:
            nodes = self._changed(leave, join or {})
            ids, row, anchor = nodes[:3]
            if not ids or bool(anchor.all()):
                raise ValueError("the session holds no agent to track: join "
                                 "one (an AgentPrior) first")
            edge_index, edge_attr, refused = self._links(
                links, ranges, row, anchor, bad_links)
            inputs = self._control(control, row, anchor)
            output, state = self.tracker.step(
                nodes[3], edge_index, edge_attr, anchor, self.num_steps,
                self.generator, motion=motion, control=inputs)
        except ValueError as e:
            self.generator.set_state(random)
            raise ValueError(identified(str(e), ids)) from None
        except BaseException:
            self.generator.set_state(random)
            raise
        self._commit(ids, row, anchor, state, nodes[4])
        self.refused_links = refused
        self.num_steps += 1
        # a given time is kept as given (no drift of summed time steps)
        self.time = float(time) if time is not None else self.time + dt
        self.skipped_time = 0.0
        return output

    def _time_step(self, dt: Optional[float], time: Optional[float]):
        # the step's dt and the motion model over it: the tracker's own
        # without dt or time (its clock advances by its own dt, or by one
        # where it has none), else the model over that time step (a model
        # that cannot says so)
        # the time of skipped steps (skip_step) since the last is part of
        # this step's: a time given counts from the last step tracked, a dt
        # or the model's own is added to it
        motion = self.tracker.motion
        if dt is not None and time is not None:
            raise ValueError("give 'dt' or 'time', not both")
        if dt is None and time is None:
            dt = float(motion.params().get('dt', 1.0))
            if not self.skipped_time:
                return dt, motion
            dt += self.skipped_time
        elif time is not None:
            given = seconds_or_none(time)
            if given is None:
                raise ValueError(
                    f"'time' must be a finite number (at most "
                    f"{LONGEST_SECONDS:.0e} s), got {time!r}"[:200])
            # a given time counts from the last step tracked (what skipped
            # steps passed is in it)
            if not given > self.time:
                raise ValueError(f"'time' = {given} does not come after the "
                                 f"last step's time {self.time}")
            dt = given - self.time
        else:
            given = seconds_or_none(dt)
            if given is None or not given > 0:
                raise ValueError(
                    f"'dt' must be a finite number above 0 (at most "
                    f"{LONGEST_SECONDS:.0e} s), got {dt!r}"[:200])
            dt = given + self.skipped_time
        return float(dt), motion.with_time_step(float(dt))

    def skip_step(self, dt: Optional[float] = None,
                  time: Optional[float] = None) -> None:
        r"""A step whose measurements were refused (a bad line of a
        stream): nothing is tracked, but its time passes, so the next
        :meth:`update` predicts over it too and is labelled with its own
        time. :obj:`dt` and :obj:`time` as in :meth:`update` (neither:
        the motion model's own time step). A bad :obj:`dt` or
        :obj:`time` is a :class:`ValueError` and changes nothing."""
        step, _ = self._time_step(dt, time)
        self.skipped_time = step

    def _control(self, control: Optional[Mapping], row: Dict[Identifier, int],
                 anchor: Tensor) -> Optional[Tensor]:
        # the step's inputs as rows (N, C), NaN for an agent without one;
        # checked whole: known agents, C finite numbers each
        if not control or not self.tracker.use_control:
            return None
        motion = self.tracker.motion
        if motion.control_dim == 0:
            raise ValueError(f"'control': the motion model {motion} takes "
                             f"no known inputs")
        if not isinstance(control, Mapping):
            raise ValueError(f"'control' must map identifiers to inputs, "
                             f"got {control!r}")
        rows = torch.full((anchor.numel(), motion.control_dim), math.nan,
                          dtype=torch.float64)
        for node, values in control.items():
            where = f"'control[{node!r}]'"
            if node not in row and isinstance(node, str) and \
                    node.isdecimal() and int(node) in row:
                node = int(node)
            if isinstance(node, (list, dict)) or node not in row:
                raise ValueError(f"{where}: unknown identifier")
            if bool(anchor[row[node]]):
                raise ValueError(f"{where}: {node!r} is an anchor, which "
                                 f"does not move")
            value = checked_numbers(values, (motion.control_dim, ), where)
            if not bool(torch.isfinite(value).all()):
                raise ValueError(f"{where} must be finite, got "
                                 f"{value.tolist()}")
            if not bool(motion.representable(value)):
                raise ValueError(f"{where} = {value.tolist()} is beyond the "
                                 f"inputs the motion model {motion} "
                                 f"represents ({motion.input_limit})")
            rows[row[node]] = value
        return rows.to(self.device, self.dtype)

    def _links(self, links, ranges, row: Dict[Identifier, int],
               anchor: Tensor, bad_links: str
               ) -> Tuple[Tensor, Tensor, List[Tuple[int, str]]]:
        # the step's links as rows, sorted by receiver (as a realization's
        # edges_by_step gives them), their features, and the links refused
        # (index, why): checked in bulk (a dict lookup per end, then
        # tensor comparisons), each problem named by the link's position
        # and identifiers. Under bad_links 'raise' the first problem is a
        # ValueError; under 'drop' the links with one are left out
        links, ranges = list(links), list(ranges)
        if len(links) != len(ranges):
            raise ValueError(f"{len(links)} links but {len(ranges)} ranges: "
                             f"one range per link")
        features = self.tracker.measurement.features
        problems: Dict[int, str] = {}
        try:
            # a bool or a float equal to an integer identifier would find
            # it in the dict: only strings and integers pass
            if not {type(end) for link in links for end in link} <= \
                    {str, int}:
                raise TypeError
            if any(type(link) not in (list, tuple) or len(link) != 2
                   for link in links):
                raise TypeError
            # one flat list: torch reads it far faster than pairs
            ends = torch.tensor([row[end] for link in links for end in link],
                                dtype=torch.long).view(-1, 2)
            if not {type(value) for value in ranges} <= {float, int} or \
                    len(features) != 1:
                raise TypeError  # feature rows: checked one by one
            values = torch.tensor(ranges, dtype=torch.float64).view(-1, 1)
        except (KeyError, TypeError, ValueError, OverflowError):
            ends, values = self._checked_links(links, ranges, row,
                                               len(features), problems)

        def where(k: int) -> str:
            return f"'links[{k}]' {list(links[k])}"

        sender, receiver = ends[:, 0], ends[:, 1]
        into_anchor = anchor.cpu()[receiver]
        finite = torch.isfinite(values).all(1)
        too_large = values[:, 0].abs() > magnitude_limit(self.dtype)
        # a likelihood defined for negative ranges takes them as measured
        negative = values[:, 0] < 0
        if self.tracker.measurement.negative_ranges:
            negative = torch.zeros_like(negative)
        for k in (sender == receiver).nonzero().view(-1).tolist():
            problems.setdefault(k, f"{where(k)}: a link to itself")
        for k in into_anchor.nonzero().view(-1).tolist():
            problems.setdefault(k, f"{where(k)}: {links[k][1]!r} is an "
                                f"anchor, and anchors never measure")
        for k in (~finite).nonzero().view(-1).tolist():
            problems.setdefault(k, f"'ranges[{k}]' of {where(k)} is not "
                                f"finite: {ranges[k]!r}")
        for k in too_large.nonzero().view(-1).tolist():
            problems.setdefault(k, f"'ranges[{k}]' of {where(k)} is too "
                                f"large: {ranges[k]!r} (at most "
                                f"{magnitude_limit(self.dtype):.3g})")
        for k in negative.nonzero().view(-1).tolist():
            problems.setdefault(
                k, f"'ranges[{k}]' of {where(k)} is negative: "
                f"{values[k, 0].item()!r} (the likelihood of "
                f"{self.tracker.measurement} needs ranges of at least 0)")
        key = sender * max(len(row), 1) + receiver
        if torch.unique(key).numel() < key.numel():
            seen = {}
            for k, pair in enumerate(key.tolist()):
                if k in problems:
                    continue
                if pair in seen:
                    problems[k] = (f"{where(k)}: the same link as "
                                   f"'links[{seen[pair]}]'")
                else:
                    seen[pair] = k
        refused = sorted(problems.items())
        if refused and bad_links == 'raise':
            raise ValueError(refused[0][1])
        keep = torch.ones(len(links), dtype=torch.bool)
        keep[[k for k, _ in refused]] = False
        ends, values = ends[keep], values[keep]
        order = torch.argsort(ends[:, 1], stable=True)
        return (ends[order].t().contiguous().to(self.device),
                values[order].to(self.device, self.dtype), refused)

    def _checked_links(self, links, ranges, row, width: int,
                       problems: Dict[int, str]) -> Tuple[Tensor, Tensor]:
        # the links one by one: a malformed link, an unknown identifier, a
        # range that is not a number or a row of the model's feature count
        # is recorded in 'problems' (its row a placeholder)
        pairs, values = [], []
        for k, (link, value) in enumerate(zip(links, ranges)):
            pairs.append([0, 0])
            values.append([0.0] * width)
            shown = list(link) if isinstance(link, (list, tuple)) else link
            where = f"'links[{k}]' {shown!r}"
            if not isinstance(link, (list, tuple)) or len(link) != 2:
                problems[k] = f"{where}: a link is a pair [from, to]"
                continue
            try:
                unknown = [end for end in link
                           if checked_identifier(end, where) not in row]
            except ValueError as e:
                problems[k] = str(e)
                continue
            if unknown:
                problems[k] = (f"{where}: unknown identifier {unknown[0]!r} "
                               f"(join it first)")
                continue
            if value is None:
                problems[k] = f"'ranges[{k}]' of {where} is missing"
                continue
            value = value if isinstance(value, (list, tuple)) else [value]
            if not value or not all(isinstance(v, numbers.Real) and
                                    not isinstance(v, bool) for v in value):
                problems[k] = (f"'ranges[{k}]' of {where} must be a number "
                               f"or a row of numbers, got {value!r}")
                continue
            if len(value) != width:
                problems[k] = (
                    f"'ranges[{k}]' of {where} has {len(value)} features; "
                    f"the measurement model reads {width} "
                    f"({', '.join(self.tracker.measurement.features)})")
                continue
            try:
                values[-1] = [float(v) for v in value]
            except OverflowError:
                problems[k] = (f"'ranges[{k}]' of {where} is too large: "
                               f"{value!r}")
                continue
            pairs[-1] = [row[link[0]], row[link[1]]]
        return (torch.tensor(pairs, dtype=torch.long).view(-1, 2),
                torch.tensor(values, dtype=torch.float64).view(-1, width))

    # ---- joining and leaving

    def _changed(self, leave, join):
        # the nodes and the tracker's state after the leaves and joins,
        # computed without touching the session: (ids, rows, anchor,
        # state, state size)
        if not leave and not join:  # the usual step: nothing to redo
            return (self._ids, self._row, self.anchor, self.state,
                    self.state_size)
        ids = list(self._ids)
        leaving = set()
        for k, node in enumerate(leave):
            node = checked_identifier(node, f"'leave[{k}]'")
            if node in leaving:
                raise ValueError(f"'leave[{k}]': {node!r} is repeated")
            if node not in self._row:
                raise ValueError(f"'leave[{k}]': unknown identifier "
                                 f"{node!r}")
            leaving.add(node)
        state, anchor, size = self.state, self.anchor, self.state_size
        if leaving:
            keep = torch.tensor([i not in leaving for i in ids],
                                dtype=torch.bool, device=self.device)
            state = self.tracker.select_state(state, keep, anchor)
            anchor = anchor[keep]
            ids = [i for i in ids if i not in leaving]
        if not isinstance(join, Mapping):
            raise ValueError(f"'join' must map identifiers to an AgentPrior "
                             f"or an AnchorAt, got {type(join).__name__}")
        if join:
            present = set(ids)
            joined, size = self._joined(join, present, size)
            ids += list(joined['ids'])
            new_anchor = joined['anchor']
            new_state = self._initial_state(joined)
            state = (new_state if state is None else
                     self.tracker.join_state(state, new_state))
            anchor = torch.cat([anchor, new_anchor])
        row = {i: r for r, i in enumerate(ids)}
        return ids, row, anchor, state, size

    def _joined(self, join: Mapping, present: set, size: Optional[int]):
        # the joining nodes checked: identifiers new, priors of one state
        # size, finite, covariances symmetric positive semi-definite
        ids, means, covs, anchors = [], [], [], []
        motion = self.tracker.motion
        # a motion model of one state size (a robot's [x, y, heading])
        size = size or motion.state_dim
        for k, (node, prior) in enumerate(join.items()):
            where = f"'join[{k}]' ({node!r})"
            node = checked_identifier(node, where)
            if node in present or node in ids:
                raise ValueError(f"{where}: the identifier is already in "
                                 f"use")
            if isinstance(prior, AnchorAt):
                position = checked_numbers(
                    prior.position, (None if size is None else
                                     motion.layout(size).position_dim, ),
                    f"{where} position")
                size = size or 2 * position.numel()
                means.append(torch.cat([position, position.new_zeros(
                    size - position.numel())]))
                covs.append(position.new_zeros(size, size))
                anchors.append(True)
            elif isinstance(prior, AgentPrior):
                mean = checked_numbers(prior.mean, (size, ), f"{where} mean")
                size = size or mean.numel()
                cov = checked_numbers(prior.cov, (size, size), f"{where} cov")
                means.append(mean)
                covs.append(cov)
                anchors.append(False)
            else:
                raise ValueError(f"{where}: a joining node is an AgentPrior "
                                 f"or an AnchorAt, got {prior!r}")
            if motion.state_dim is None and size not in (4, 6):
                raise ValueError(f"{where}: states have 4 or 6 entries (a "
                                 f"2-D or 3-D position, then the velocity), "
                                 f"got {size}")
            ids.append(node)
        check_state_dim(size, self.tracker.motion)
        position_dim = getattr(self.tracker, 'position_dim', None)
        layout = motion.layout(size)
        name = type(self.tracker).__name__
        if position_dim is not None and layout.angles == () and \
                layout.position_dim == size // 2:  # [p, v]
            check_position_dim(position_dim, size, name)
        elif position_dim is not None and \
                layout.position_dim != position_dim:
            raise ValueError(f"{name} was built for {position_dim}-D "
                             f"positions, but the motion model's states of "
                             f"size {size} hold {layout.position_dim}-D ones")
        mean, cov = torch.stack(means), torch.stack(covs)
        anchor = torch.tensor(anchors)
        try:
            # a realization's checks: finite, symmetric PSD, positions
            # within the compute type's distances
            check_prior(mean.to(self.dtype), cov.to(self.dtype), anchor,
                        position_dim=motion.layout(size).position_dim)
        except ValueError as e:
            # named by the joining entry, not the row of the check
            def entry(found) -> str:
                k = int(found.group(2))
                return f"'join[{k}]' ({ids[k]!r}) {found.group(1)}"

            raise ValueError(re.sub(r"'prior_(mean|cov)\[(\d+)\]'", entry,
                                    str(e))) from None
        return dict(ids=ids, mean=mean, cov=cov,
                    anchor=anchor.to(self.device)), size

    def _initial_state(self, joined: dict):
        # the tracker's state of the joining nodes, drawn (particles) from
        # the session's generator
        data = Realization(
            prior_mean=joined['mean'].to(self.device, self.dtype),
            prior_cov=joined['cov'].to(self.device, self.dtype),
            anchor=joined['anchor'], num_nodes=len(joined['ids']))
        try:
            return self.tracker.initial_state(data, self.generator)
        except ValueError as e:
            # the tracker's checks name rows of the joining nodes
            raise ValueError(f"joining {joined['ids']} (rows 0-"
                             f"{len(joined['ids']) - 1} below): {e}"
                             ) from None

    def _commit(self, ids, row, anchor, state, size):
        self._ids, self._row, self.anchor = ids, row, anchor
        self.state, self.state_size = state, size

    # ---- state that survives

    def identity(self) -> Dict[str, str]:
        r"""What a saved session must match to be loaded into this one:
        the tracker's class, its settings, its motion and measurement
        models (JSON) and a fingerprint of its parameters."""
        return dict(
            tracker=type(self.tracker).__name__,
            settings=json.dumps(self.tracker.settings(), sort_keys=True),
            motion=json.dumps(self.tracker.motion.config(), sort_keys=True),
            measurement=json.dumps(self.tracker.measurement.config(),
                                   sort_keys=True),
            parameters=_fingerprint(self.tracker))

    def state_dict(self) -> Dict[str, Any]:
        r"""Everything to continue: the nodes, the clock, the tracker's
        state and the generator's, as tensors and plain values only (so
        :func:`torch.load` with :obj:`weights_only=True` reads it), with
        :meth:`identity`."""
        state = None
        if self.state is not None:
            state = {name: (list(value) if isinstance(value, tuple) else
                            value)
                     for name, value in self.state._asdict().items()}
            state = {name: (value.detach().cpu() if isinstance(value, Tensor)
                            else [v.detach().cpu() for v in value]
                            if isinstance(value, list) else value)
                     for name, value in state.items()}
        return dict(format=SESSION_FORMAT, version=SESSION_VERSION,
                    identity=self.identity(), ids=json.dumps(self._ids),
                    anchor=self.anchor.cpu(), time=self.time,
                    skipped_time=self.skipped_time,
                    num_steps=self.num_steps, state_size=self.state_size,
                    dtype=str(self.dtype).replace('torch.', ''),
                    state=state,
                    state_type=(None if self.state is None else
                                type(self.state).__name__),
                    generator=self.generator.get_state())

    def load_state_dict(self, saved: Dict[str, Any]) -> None:
        r"""Continues from a :meth:`state_dict`: refuses one of another
        format or version, tracker, configuration, model or network,
        naming what differs."""
        if not isinstance(saved, dict) or \
                saved.get('format') != SESSION_FORMAT:
            raise ValueError("not a saved tg_nebp tracking session")
        if saved.get('version') != SESSION_VERSION:
            raise ValueError(f"a saved session of version "
                             f"{saved.get('version')}; this tg_nebp reads "
                             f"version {SESSION_VERSION}")
        mine, theirs = self.identity(), saved.get('identity') or {}
        for key, what in (('tracker', 'tracker'),
                          ('motion', 'motion model'),
                          ('measurement', 'measurement model'),
                          ('settings', 'configuration'),
                          ('parameters', 'network parameters')):
            if theirs.get(key) != mine[key]:
                held = (theirs.get(key) if key != 'parameters' else
                        'other parameters')
                here = mine[key] if key != 'parameters' else 'these'
                raise ValueError(f"the session was saved by another "
                                 f"{what}: {held} (this session: {here})")
        state_type = self.tracker.state_type
        if saved.get('state_type') not in (None, state_type.__name__):
            raise ValueError(f"the saved state is a {saved['state_type']}, "
                             f"not this tracker's {state_type.__name__}")
        try:
            state = self._saved_state(saved.get('state'), state_type)
            ids = [checked_identifier(i, "'ids'")
                   for i in json.loads(saved['ids'])]
            anchor = saved['anchor']
            time, steps = saved['time'], saved['num_steps']
            skipped = saved.get('skipped_time', 0.0)
            size, random = saved['state_size'], saved['generator']
            dtype = _DTYPES[saved['dtype']]
            self._check_saved(state, ids, anchor, time, steps, size, dtype)
            if not isinstance(skipped, float) or not \
                    0 <= skipped <= LONGEST_SECONDS:
                raise ValueError(f"'skipped_time' must be a number of "
                                 f"seconds of at least 0, got {skipped!r}")
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise ValueError(f"a damaged saved session: {first_line(e)}"
                             ) from None
        if random.numel() != self.generator.get_state().numel():
            raise ValueError(f"the session's generator was saved on another "
                             f"kind of device than this session's "
                             f"{self.device}")
        # all read and checked: nothing is half-loaded
        self.generator.set_state(random)
        self._commit(ids, {i: r for r, i in enumerate(ids)},
                     anchor.to(self.device), state, size)
        self.time, self.num_steps, self.dtype = float(time), steps, dtype
        self.skipped_time = skipped

    def _check_saved(self, state, ids, anchor, time, steps, size,
                     dtype) -> None:
        # everything a saved session holds against what this session's
        # tracker could have written: the clock, the counts, the anchor
        # flags and the tracker's state field by field
        if not isinstance(time, (int, float)) or isinstance(time, bool) or \
                not math.isfinite(time):
            raise ValueError(f"'time' must be a finite number, got {time!r}")
        for name, value, least in (('num_steps', steps, 0),
                                   ('state_size', size, 1)):
            if size is None and name == 'state_size':
                continue
            if not isinstance(value, int) or isinstance(value, bool) or \
                    value < least:
                raise ValueError(f"'{name}' must be an integer of at least "
                                 f"{least}, got {value!r}")
        if not isinstance(anchor, Tensor) or anchor.dtype != torch.bool or \
                anchor.dim() != 1:
            raise ValueError(f"'anchor' must be a vector of booleans, got "
                             f"{getattr(anchor, 'dtype', type(anchor))}")
        held = 0 if state is None else state[0].size(0)
        if len({len(ids), anchor.numel(), held}) != 1 or \
                len(set(ids)) != len(ids):
            raise ValueError(f"{len(ids)} identifiers, {anchor.numel()} "
                             f"anchor flags and {held} state rows")
        if state is not None:
            if size is None:
                raise ValueError("'state_size' is missing")
            self.tracker.check_state(state, anchor.to(self.device), size,
                                     dtype)

    def _saved_state(self, state: Optional[dict], state_type: type):
        # the tracker's state of a state_dict, on this session's device
        if state is None:
            return None
        # an optional field that a session saved by an earlier version
        # lacks is absent (None), as a state without it holds
        absent = {name: None for name, field in getattr(
            state_type, 'FIELDS', {}).items()
            if field.optional and name not in state}
        try:
            return state_type(**absent, **{
                name: (value.to(self.device) if isinstance(value, Tensor)
                       else tuple(v.to(self.device) for v in value)
                       if isinstance(value, list) else value)
                for name, value in state.items()})
        except (TypeError, AttributeError) as e:
            raise ValueError(f"the saved state does not fit "
                             f"{state_type.__name__}: {first_line(e)}"
                             ) from None

    def save(self, path: Union[str, Path],
             progress: Optional[Dict[str, Any]] = None) -> None:
        r"""Writes :meth:`state_dict` to :obj:`path` atomically (a killed
        write leaves the previous file), with the caller's
        :obj:`progress` (JSON values: how far its input was read), which
        :meth:`load` gives back as :attr:`progress`."""
        saved = dict(self.state_dict(), progress=json.dumps(progress))
        atomic_write(path, lambda tmp: torch.save(saved, tmp))

    @classmethod
    def load(cls, path: Union[str, Path], tracker: Tracker,
             generator: Optional[torch.Generator] = None,
             device='cpu') -> 'TrackingSession':
        r"""A session of :obj:`tracker` continued from the file that
        :meth:`save` wrote; the file is read with
        :obj:`weights_only=True` (no code runs)."""
        saved = read_tensors(path, 'saved session')
        session = cls(tracker, generator=generator, device=device)
        try:
            session.load_state_dict(saved)
        except ValueError as e:
            raise ValueError(f"'{path}': {e}") from None
        session.progress = json.loads(saved.get('progress') or 'null')
        return session
