r"""The reading protocol of real recordings of ranges (UWB two-way ranging
in ROS bags, MILUV's CSV folders): every reader gives a :class:`Recording`,
time-stamped ranges between named nodes and the nodes' ground truth where
there is any, and one shared step (:func:`recording_realization`) bins it
into the :class:`~tg_nebp.data.Realization` that every tracker takes.

**The binning**, one for every real dataset (MRCLAM's reader bins its
camera's measurements with the same two functions, :func:`step_of` and
:func:`merge_links`; the step :math:`\Delta` given by the scenario, said in
the report): from :math:`t_0`, one step after the first time at which every
node with truth has it (plus the scenario's :obj:`start`), step :math:`k = 0, 1,
\dots` holds the ranges measured in :math:`(t_0 + k \Delta, t_0 + (k + 1)
\Delta]`, and its time is the middle of that interval. The ranges of one
pair within a step are merged into their mean (a UWB pair ranges at several
hertz: the mean of a step's ranges is one measurement with a smaller
spread, which the fitted model states, and it is the range at the middle
of the step, where the moving robots are taken to be). A range measured by an anchor of an agent is the agent's range to
the anchor (a two-way range is symmetric); one between two anchors carries
no information and is dropped. Every range is corrected by its pair's
calibrated bias before it is merged (:attr:`RangeCalibration`). The states
:math:`[\mathbf{p}, \mathbf{v}]` are the ground truth interpolated at the
steps' middles (the velocity the central difference over one step), for the
metrics only; the prior is the truth one step before the first step's middle
(:math:`t_0 - \Delta / 2`; :math:`t_0` is one step after the start of the
truth's span, so that the prior's velocity, a central difference over one
step, lies in it) with the scenario's
standard deviations; anchors sit at their truth at :math:`t_0` (a standing
robot declared an anchor: its position surveyed once), or at their surveyed
position."""
import dataclasses
import math
from typing import (Dict, List, Mapping, NamedTuple, Optional,
                    Sequence, Tuple)

import numpy as np
import torch

from tg_nebp.data.realization import Realization

__all__ = ['Recording', 'RangeCalibration', 'recording_realization',
           'step_of', 'merge_links', 'Links', 'MERGES', 'READ_COUNTS',
           'BIN_COUNTS', 'recording_report']

#: The ranges a reader drops and counts (those not finite, negative or
#: beyond the reader's :obj:`max_range`, absurd, and those of a node that is
#: not tracked, without truth and not surveyed).
READ_COUNTS = ('not_finite', 'negative', 'absurd', 'untracked')
#: The ranges the binning drops or merges (outside the span, between two
#: anchors, and repeated within a step, merged into their mean).
BIN_COUNTS = ('outside', 'between_anchors', 'merged')


@dataclasses.dataclass
class Recording:
    r"""A real recording, read: what every reader gives.

    Attributes:
        source (str): The file or folder it was read from.
        nodes (list): The nodes' names, in node order.
        position_dim (int): :math:`D`, 2 or 3.
        ranges (numpy.ndarray): :math:`(M, 5)` float64 rows :math:`[t,
            \text{receiver}, \text{sender}, z, k]` in time order: node
            :obj:`receiver` measured its range :math:`z` (metres) to node
            :obj:`sender` at time :math:`t` (seconds) with sensor :math:`k`
            (an index into :obj:`sensors`).
        truth (dict): Node index to its ground truth :math:`(P, 1 + D)`,
            rows :math:`[t, \mathbf{p}]` in time order.
        surveyed (dict): Node index to a fixed position :math:`(D)` (an
            anchor of a constellation surveyed beforehand).
        sensors (list): The names of the sensors that measured the ranges
            (one: every range is a UWB two-way range).
        counts (dict): What the reader dropped
            (:data:`~tg_nebp.datasets.recording.READ_COUNTS`), and
            what else it counts (a reader's own kinds of rows).
    """
    source: str
    nodes: List[str]
    position_dim: int
    ranges: np.ndarray
    truth: Dict[int, np.ndarray]
    surveyed: Dict[int, np.ndarray] = dataclasses.field(default_factory=dict)
    sensors: List[str] = dataclasses.field(default_factory=lambda: ['uwb'])
    counts: Dict[str, int] = dataclasses.field(
        default_factory=lambda: dict.fromkeys(READ_COUNTS, 0))

    def node(self, name: str) -> int:
        r"""The index of the node named :obj:`name`; a name that is not
        there is a :class:`ValueError` that lists those that are."""
        try:
            return self.nodes.index(str(name))
        except ValueError:
            raise ValueError(f"'{self.source}' has no node '{name}' (its "
                             f"nodes: {', '.join(self.nodes)})") from None

    def span(self) -> Tuple[float, float]:
        r"""The first and the last time at which every node with ground
        truth has it."""
        if not self.truth:
            raise ValueError(f"'{self.source}' has no ground truth of any "
                             f"node")
        return (max(float(t[0, 0]) for t in self.truth.values()),
                min(float(t[-1, 0]) for t in self.truth.values()))

    def positions(self, node: int, times: np.ndarray) -> np.ndarray:
        r"""The position :math:`(T, D)` of :obj:`node` at :obj:`times`:
        its ground truth interpolated linearly (its surveyed position where
        it has one)."""
        if node in self.surveyed:
            return np.broadcast_to(self.surveyed[node], (len(times),
                                   self.position_dim)).copy()
        truth = self.truth[node]
        return np.stack([np.interp(times, truth[:, 0], truth[:, 1 + c])
                         for c in range(self.position_dim)], -1)


@dataclasses.dataclass(frozen=True)
class RangeCalibration:
    r"""Range biases: what is subtracted from a measured range before it is
    used. UWB two-way ranges are longer than the distance by an amount that
    depends on the pair (the antenna delays of both ends, the bodies between
    them); :func:`~tg_nebp.datasets.fit_range_models` measures it.

    Args:
        pairs (dict, optional): :obj:`"receiver->sender"` (node names) to
            its bias in metres. (default: none)
        default (float, optional): The bias of a pair not in
            :obj:`pairs`. (default: :obj:`0.0`)
    """
    pairs: Mapping[str, float] = dataclasses.field(default_factory=dict)
    default: float = 0.0

    def __post_init__(self):
        for key, value in self.pairs.items():
            if not isinstance(key, str) or key.count('->') != 1:
                raise ValueError(f"'pairs': key {key!r} is not "
                                 f"'receiver->sender'")
            if not (isinstance(value, (int, float)) and
                    math.isfinite(value)) or isinstance(value, bool):
                raise ValueError(f"'pairs[{key!r}]' must be a finite "
                                 f"number of metres, got {value!r}")
        if not (isinstance(self.default, (int, float)) and
                math.isfinite(self.default)) or \
                isinstance(self.default, bool):
            raise ValueError(f"'default' must be a finite number of metres, "
                             f"got {self.default!r}")
        object.__setattr__(self, 'pairs', dict(self.pairs))

    def bias(self, receiver: str, sender: str) -> float:
        r"""The bias of the ranges that :obj:`receiver` measures to
        :obj:`sender` (the reverse pair's where only it is given: a two-way
        range is the same both ways)."""
        return float(self.pairs.get(f'{receiver}->{sender}', self.pairs.get(
            f'{sender}->{receiver}', self.default)))

    def to_fields(self) -> dict:
        return dict(pairs=dict(sorted(self.pairs.items())),
                    default=self.default)

    @classmethod
    def from_fields(cls, fields, where: str) -> 'RangeCalibration':
        if fields is None:
            return cls()
        if not isinstance(fields, dict) or set(fields) - {'pairs',
                                                          'default'}:
            raise ValueError(f"'{where}': 'calibration' must be an object "
                             f"with 'pairs' and 'default', got {fields!r}")
        try:
            return cls(**fields)
        except (TypeError, ValueError) as e:
            raise ValueError(f"'{where}': 'calibration': {e}") from None


def step_of(times: np.ndarray, t0: float, dt: float,
            steps: int) -> np.ndarray:
    r"""The step of every time in :obj:`times`: step :math:`k` holds the
    times in :math:`(t_0 + k \Delta, t_0 + (k + 1) \Delta]`, :math:`k <`
    :obj:`steps`; :math:`-1` for a time outside them. The binning of every
    real dataset (MRCLAM's and the recordings')."""
    times = np.asarray(times, dtype=np.float64)
    inside = (times > t0) & (times <= t0 + steps * dt)
    step = np.minimum(np.ceil((times - t0) / dt).astype(np.int64) - 1,
                      steps - 1)
    return np.where(inside, step, -1)


class Links(NamedTuple):
    r"""A realization's links, as :func:`merge_links` gives them: sorted
    by step, receiver, sender and sensor."""
    edge_index: torch.Tensor
    edge_attr: torch.Tensor
    edge_time: torch.Tensor
    #: Each link's sensor (an index into the recording's sensors).
    sensor: torch.Tensor
    #: The rows merged into another's link.
    merged: int


#: How :func:`~tg_nebp.datasets.merge_links` merges one step's
#: rows of a link: into their mean (ranges at several hertz), or the latest
#: row (MRCLAM's camera: a bearing is not averaged across the robot's
#: turn).
MERGES = ('mean', 'latest')


def merge_links(step: np.ndarray, receiver: np.ndarray, sender: np.ndarray,
                values: np.ndarray, merge: str,
                times: Optional[np.ndarray] = None,
                sensor: Optional[np.ndarray] = None) -> Links:
    r"""The links of binned rows (:obj:`step` from :func:`step_of`, every
    row inside): one link per step, receiver, sender and sensor, its
    features :obj:`values` :math:`(M, F)` merged by :obj:`merge`
    (:data:`~tg_nebp.datasets.recording.MERGES`; :obj:`"latest"`: the
    row of the largest of :obj:`times`, of two at one time the later row),
    as float32."""
    if merge not in MERGES:
        raise ValueError(f"'merge' must be one of {list(MERGES)}, got "
                         f"{merge!r}")
    if merge == 'latest' and times is None:
        raise ValueError("merge 'latest' needs the rows' 'times'")
    sensor = np.zeros(len(step), np.int64) if sensor is None else sensor
    rows: Dict[Tuple[int, int, int, int], List[int]] = {}
    for k in range(len(step)):
        rows.setdefault((int(step[k]), int(receiver[k]), int(sender[k]),
                         int(sensor[k])), []).append(k)
    keys = sorted(rows)
    width = values.shape[1]
    attr = np.empty((len(keys), width))
    for link, key in enumerate(keys):
        if merge == 'mean':
            # each column's own mean, summed in row order
            attr[link] = [np.mean(values[rows[key], c])
                          for c in range(width)]
        else:
            # the largest time; of equal times the later row
            chosen = max(rows[key], key=lambda k: (times[k], k))
            attr[link] = values[chosen]
    return Links(
        edge_index=torch.tensor([[k[2] for k in keys], [k[1] for k in keys]],
                                dtype=torch.long).view(2, -1),
        edge_attr=torch.from_numpy(attr).float(),
        edge_time=torch.tensor([k[0] for k in keys], dtype=torch.long),
        sensor=torch.tensor([k[3] for k in keys], dtype=torch.long),
        merged=sum(len(r) - 1 for r in rows.values()))


def _truth_at(recording: Recording, node: int, times: np.ndarray,
              dt: float) -> np.ndarray:
    # [p, v] at 'times': the interpolated truth, the velocity its central
    # difference over one step
    position = recording.positions(node, times)
    velocity = (recording.positions(node, times + 0.5 * dt) -
                recording.positions(node, times - 0.5 * dt)) / dt
    return np.concatenate([position, velocity], -1)


def recording_realization(recording: Recording, dt: float,
                          start: float = 0.0,
                          duration: Optional[float] = None,
                          anchors: Sequence[str] = (),
                          calibration: Optional[RangeCalibration] = None,
                          prior_std: float = 0.5, velocity_std: float = 0.5,
                          symmetric: bool = True,
                          ) -> Tuple[Realization, Dict[str, int]]:
    r"""The realization of :obj:`recording` in steps of :obj:`dt` seconds
    from :obj:`start` seconds after the first time every node with truth has
    it, for :obj:`duration` seconds (to the end of the truth's span with
    :obj:`None`), under the binning of the module docstring; and what was
    dropped or merged (:data:`~tg_nebp.datasets.recording.BIN_COUNTS`, after the
    reader's :data:`~tg_nebp.datasets.recording.READ_COUNTS`).

    Nodes: the recording's, in its order; the :obj:`anchors` (names of
    nodes with truth, or surveyed nodes, which are anchors always) static at
    their position at :math:`t_0`. A node with neither truth nor a surveyed
    position (a reader keeps one only when asked: a bag's
    :obj:`without_truth`) is an agent tracked and used but not scored: its
    :obj:`states` NaN (:func:`~tg_nebp.data.scored_of`), its prior
    uninformed, centred on the nodes with truth (their mean position at
    the prior's time, at rest) with the standard deviation of their extent
    (the largest distance of one from that centre, at least
    :obj:`prior_std`): it is somewhere among them.

    With :obj:`symmetric` (two-way ranging: both ends report the one range
    the exchange measured, so the two directions of a pair are one
    measurement, not two), the ranges of both directions of a pair within a
    step are merged into one link, received by the pair's first agent in
    node order; without it each direction is its own link."""
    calibration = calibration or RangeCalibration()
    begin, end = recording.span()
    # the prior's time is half a step before t0, and its velocity's central
    # difference half a step before that: inside the truth's span
    t0 = begin + dt + float(start)
    if duration is None:
        steps = int(math.floor((end - t0) / dt + 1e-9))
    else:
        steps = int(round(float(duration) / dt))
    # the last step's middle and its velocity's half step after it inside
    if steps < 1 or t0 + steps * dt > end + 1e-6:
        raise ValueError(
            f"'{recording.source}': {duration if duration is not None else 'the rest'} "
            f"s from {start} s in steps of {dt} s leave the span in which "
            f"every node has ground truth ({end - begin:.3f} s)")
    count = len(recording.nodes)
    anchor = np.zeros(count, dtype=bool)
    for name in anchors:
        anchor[recording.node(name)] = True
    for node in recording.surveyed:
        anchor[node] = True
    unknown = np.array([node not in recording.truth and
                        node not in recording.surveyed
                        for node in range(count)], dtype=bool)
    if (anchor & unknown).any():
        node = int(np.flatnonzero(anchor & unknown)[0])
        raise ValueError(f"'{recording.source}': anchor "
                         f"'{recording.nodes[node]}' has neither ground "
                         f"truth nor a surveyed position to place it")
    if unknown.all():
        raise ValueError(f"'{recording.source}': no node has ground truth")
    if anchor.all():
        raise ValueError(f"'{recording.source}': every node is an anchor: "
                         f"there is no agent to localize")
    times = t0 + dt * (np.arange(steps) + 0.5)  # the steps' middles
    states = np.zeros((count, steps, 2 * recording.position_dim))
    prior = np.zeros((count, 2 * recording.position_dim))
    position_std = np.full(count, float(prior_std))
    for node in np.flatnonzero(~unknown):
        states[node] = _truth_at(recording, node, times, dt)
        prior[node] = _truth_at(recording, node, np.array([t0 - 0.5 * dt]),
                                dt)[0]
        if anchor[node]:  # static at its position at t0
            states[node] = np.concatenate(
                [prior[node, :recording.position_dim],
                 np.zeros(recording.position_dim)])
            prior[node] = states[node, 0]
    if unknown.any():
        known = prior[~unknown, :recording.position_dim]
        centre = known.mean(0)
        states[unknown] = np.nan
        prior[unknown] = np.concatenate([centre, np.zeros_like(centre)])
        position_std[unknown] = max(
            float(np.linalg.norm(known - centre, axis=-1).max()),
            float(prior_std))
    counts = dict(recording.counts, **dict.fromkeys(BIN_COUNTS, 0))
    t, receiver, sender, z, sensor = (recording.ranges[:, c]
                                      for c in range(5))
    receiver, sender = receiver.astype(np.int64), sender.astype(np.int64)
    sensor = sensor.astype(np.int64)
    step = step_of(t, t0, dt, steps)
    inside = step >= 0
    counts['outside'] = int((~inside).sum())
    both = anchor[receiver] & anchor[sender]
    counts['between_anchors'] = int((inside & both).sum())
    kept = np.flatnonzero(inside & ~both)
    values = np.empty(len(kept))
    bias = {}
    for row, k in enumerate(kept):
        pair = (int(receiver[k]), int(sender[k]))
        if pair not in bias:
            bias[pair] = calibration.bias(recording.nodes[pair[0]],
                                          recording.nodes[pair[1]])
        values[row] = float(z[k]) - bias[pair]
        # an anchor never receives: its range to an agent is the agent's
        rx, tx = pair[::-1] if anchor[pair[0]] else pair
        if symmetric and not anchor[tx] and tx < rx:
            rx, tx = tx, rx
        receiver[k], sender[k] = rx, tx
    links = merge_links(step[kept], receiver[kept], sender[kept],
                        values[:, None], 'mean', sensor=sensor[kept])
    counts['merged'] = links.merged
    edge_attr = links.edge_attr
    if len(recording.sensors) > 1:
        # with several sensors, each link names its own (the likelihood's
        # second feature, StudentTRangeBySensor's)
        edge_attr = torch.cat([edge_attr, links.sensor.float()[:, None]],
                              -1)
    dim = recording.position_dim
    variance = np.concatenate([np.repeat(position_std[:, None]**2, dim, 1),
                               np.full((count, dim), velocity_std**2)], 1)
    prior_cov = torch.diag_embed(torch.from_numpy(variance).float())
    anchor_t = torch.from_numpy(anchor)
    prior_cov[anchor_t] = 0
    data = Realization(
        states=torch.from_numpy(states).float(),
        edge_index=links.edge_index, edge_attr=edge_attr,
        edge_time=links.edge_time, anchor=anchor_t,
        prior_mean=torch.from_numpy(prior).float(), prior_cov=prior_cov,
        num_steps=steps, num_nodes=count)
    return data, counts


def recording_report(what: str, counts: Sequence[Dict[str, int]],
                     links: Sequence[int], dt: float) -> str:
    r"""One line on the reading of a recording's realizations
    (:obj:`what`): the step, the links kept (:obj:`links`, per realization)
    and what was dropped or merged (:obj:`counts`, per realization, as
    :func:`recording_realization` gives them)."""
    total = {key: sum(c.get(key, 0) for c in counts)
             for key in READ_COUNTS + BIN_COUNTS}
    # a reader's own counts (MILUV's rigid and height rows), said as they are
    own = sorted({key for c in counts for key in c} - set(total))
    extra = ''.join(f"; {key.replace('_', ' ')}: "
                    f"{sum(c.get(key, 0) for c in counts):,}" for key in own)
    return (f"{what}: steps of {dt:g} s, {sum(links):,} links kept; ranges "
            f"dropped: {total['not_finite']:,} not finite, "
            f"{total['negative']:,} negative, {total['absurd']:,} beyond "
            f"the reader's largest range, {total['untracked']:,} of nodes "
            f"without truth, {total['outside']:,} outside the span, "
            f"{total['between_anchors']:,} between anchors; "
            f"{total['merged']:,} repeated within a step merged (the mean "
            f"of the step's ranges kept){extra}")
