r"""Real robots: the UTIAS Multi-Robot Cooperative Localization and Mapping
dataset (MRCLAM) read into :class:`~tg_nebp.data.Realization` form, as the
trackers take simulated data.

K. Y. K. Leung, Y. Halpern, T. D. Barfoot and H. H. T. Liu, "The UTIAS
multi-robot cooperative localization and mapping dataset", International
Journal of Robotics Research 30(8), 2011. Nine sequences, one zip each
(:obj:`MRCLAM_DatasetN.zip`, the folder :obj:`MRCLAM_DatasetN/` inside):
five robots with wheel odometry and a camera that measures range and
bearing to barcodes on 15 surveyed landmarks and on the other robots, with
Vicon ground truth.

**The test protocol** (:func:`~tg_nebp.datasets.mrclam_realization`): from the
first time :math:`t_0` at which all five robots have ground truth and odometry,
:obj:`duration` seconds in steps of :obj:`dt`; step :math:`k` holds the
measurements in :math:`(t_0 + (k - 1) \Delta, t_0 + k \Delta]`; a robot's
repeated measurement of one subject within a step: the latest (the binning
of every real dataset, :func:`~tg_nebp.datasets.step_of` and
:func:`~tg_nebp.datasets.merge_links`; a bearing is not averaged
across a turn, so MRCLAM merges by the latest where the UWB recordings take
the mean); a barcode not in
:obj:`Barcodes.dat` (or a subject without ground truth) is dropped and counted;
landmarks are anchors at their surveyed positions; the robots' states
:math:`[x, y, \theta]` are the ground truth interpolated at the step times (for
the metrics only), the prior the ground truth at :math:`t_0` with
:obj:`prior_std` metres and :obj:`heading_std` radians of standard deviation;
each robot's odometry (forward and angular velocity, held from one sample to
the next) is integrated over every step into the step's input :math:`[\delta_d,
\delta_\theta]` (:class:`~tg_nebp.models.UnicycleOdometry`'s), NaN where a step
is not covered by the robot's odometry."""
import math
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import check_positive_int, magnitude_limit
from tg_nebp.datasets.recording import merge_links, step_of

__all__ = ['MRCLAMSequence', 'read_mrclam', 'mrclam_realization',
           'integrate_odometry', 'interpolate_pose', 'fit_models',
           'long_run_factor', 'NUM_ROBOTS', 'LINKS', 'FIT_HORIZON',
           'FIT_MIN_LINKS']

#: The robots of every sequence (subjects 1 to 5).
NUM_ROBOTS = 5
#: The steps over which :func:`~tg_nebp.datasets.fit_models` fits the long-run noise by
#: default: 40 steps of 0.5 s, 20 s. Chosen on sequence 6 as the shortest
#: of 1, 10, 20 and 40 steps with which the centralized IEKF's P(accept
#: 0.95) reaches 0.85 (0.34, 0.72, 0.848, 0.92 at RMSE 0.108, 0.117,
#: 0.118, 0.120 m).
FIT_HORIZON = 40
#: Which links :func:`~tg_nebp.datasets.mrclam_realization` keeps: every
#: one, those to landmarks only, those between robots only.
LINKS = ('all', 'landmarks', 'robots')


def _table(text: str, name: str, columns: int) -> np.ndarray:
    # a whitespace-separated table after '#' header lines, float64
    rows = [line.split() for line in text.splitlines()
            if line.strip() and not line.lstrip().startswith('#')]
    bad = next((k for k, row in enumerate(rows) if len(row) != columns),
               None)
    if bad is not None:
        raise ValueError(f"'{name}': data row {bad + 1} has "
                         f"{len(rows[bad])} columns, expected {columns}")
    try:
        table = np.array(rows, dtype=np.float64).reshape(-1, columns)
    except ValueError as e:
        raise ValueError(f"'{name}': not a table of numbers ({e})") from None
    if not np.isfinite(table).all():
        row = int(np.flatnonzero(~np.isfinite(table).all(1))[0])
        raise ValueError(f"'{name}': data row {row + 1} is not finite")
    # the realizations hold float32, whose squared distances must be finite
    limit = magnitude_limit(torch.float32)
    beyond = np.flatnonzero((np.abs(table) > limit).any(1))
    if beyond.size:
        row = int(beyond[0])
        raise ValueError(f"'{name}': data row {row + 1} holds a number "
                         f"beyond {limit:.3g} in magnitude "
                         f"({float(np.abs(table[row]).max()):.3g})")
    return table


@dataclass
class MRCLAMSequence:
    r"""The files of one sequence, read: :obj:`barcodes` (barcode to
    subject), :obj:`landmarks` (subject to surveyed :math:`[x, y]`), and per
    robot :math:`r = 1..5` its :obj:`groundtruth` (time, x, y, heading),
    :obj:`odometry` (time, forward velocity, angular velocity) and
    :obj:`measurements` (time, barcode, range, bearing), in time order."""
    barcodes: Dict[int, int]
    landmarks: Dict[int, Tuple[float, float]]
    groundtruth: List[np.ndarray] = field(default_factory=list)
    odometry: List[np.ndarray] = field(default_factory=list)
    measurements: List[np.ndarray] = field(default_factory=list)

    def start(self) -> float:
        r"""The first time at which every robot has ground truth and
        odometry."""
        return max(max(float(g[0, 0]), float(o[0, 0]))
                   for g, o in zip(self.groundtruth, self.odometry))

    def end(self) -> float:
        r"""The last time at which every robot has ground truth and
        odometry."""
        return min(min(float(g[-1, 0]), float(o[-1, 0]))
                   for g, o in zip(self.groundtruth, self.odometry))


def _is_data_file(name: str) -> bool:
    # a sequence's .dat file, not the resource fork that macOS's archiver
    # writes beside it ('__MACOSX/', '._Name.dat')
    path = Path(name)
    return path.suffix == '.dat' and not path.name.startswith('._') and \
        '__MACOSX' not in path.parts


def _text(raw: bytes) -> str:
    # the numbers are ASCII; a header comment in another encoding (Latin-1)
    # is read with replacement characters, not refused
    return raw.decode('utf-8', errors='replace')


def _files(source: Union[str, os.PathLike]):
    # name -> text of a sequence's files, from its zip, its folder or a
    # folder holding either; a damaged member is named
    source = Path(source)
    if source.is_file() and zipfile.is_zipfile(source):
        out = {}
        with zipfile.ZipFile(source) as archive:
            for name in filter(_is_data_file, archive.namelist()):
                try:
                    out[Path(name).name] = _text(archive.read(name))
                except (zipfile.BadZipFile, zlib.error, EOFError,
                        NotImplementedError) as e:
                    raise ValueError(f"'{source}': its member '{name}' is "
                                     f"damaged ({e})") from None
        return out
    if source.is_dir():
        found = {p.name: p for p in source.glob('*.dat')
                 if _is_data_file(p.name)}
        if found:
            return {name: _text(p.read_bytes())
                    for name, p in found.items()}
    raise ValueError(f"'{source}' is neither an MRCLAM zip nor a folder "
                     f"of its .dat files")


def read_mrclam(source: Union[str, os.PathLike]) -> MRCLAMSequence:
    r"""Reads a sequence from its zip (:obj:`MRCLAM_DatasetN.zip`) or the
    folder of its files (:obj:`MRCLAM_DatasetN/`; macOS's resource forks
    beside them skipped); a missing or damaged file, a row of the wrong
    width, a value that is not a finite number, a robot's row that goes
    back in time, a barcode given to two subjects and a landmark listed
    under a robot's subject (or twice) and a bearing outside
    :math:`[-\pi, \pi]` are a :class:`ValueError` naming the file and
    the row, and so is a sequence none of whose measurements names another
    robot or a surveyed landmark (an empty :obj:`Barcodes.dat`). A negative
    range is read as it is (whether a likelihood takes it is the model's to
    say: :func:`mrclam_realization`)."""
    files = _files(source)

    def table(name, columns):
        if name not in files:
            raise ValueError(f"'{source}' has no '{name}'")
        data = _table(files[name], name, columns)
        back = np.flatnonzero(np.diff(data[:, 0]) < 0)
        if name.startswith('Robot') and back.size:
            row = int(back[0]) + 1  # its index; its data row is one more
            raise ValueError(
                f"'{name}': data row {row + 1} goes back in time "
                f"({float(data[row, 0])!r} after "
                f"{float(data[row - 1, 0])!r}): the rows "
                f"of a robot's file are in time order (a second log "
                f"appended?)")
        return data

    barcodes = {}
    for row, (subject, barcode) in enumerate(table('Barcodes.dat', 2)):
        if int(barcode) in barcodes:
            raise ValueError(f"'Barcodes.dat': data row {row + 1} gives "
                             f"barcode {int(barcode)} to subject "
                             f"{int(subject)}; it is subject "
                             f"{barcodes[int(barcode)]}'s already")
        barcodes[int(barcode)] = int(subject)
    landmarks = {}
    for row, (subject, x, y, _, _) in enumerate(
            table('Landmark_Groundtruth.dat', 5)):
        subject = int(subject)
        if 1 <= subject <= NUM_ROBOTS or subject in landmarks:
            raise ValueError(
                f"'Landmark_Groundtruth.dat': data row {row + 1} lists "
                f"subject {subject}, "
                + (f"a robot's (1 to {NUM_ROBOTS})" if subject <= NUM_ROBOTS
                   else "listed already"))
        landmarks[subject] = (float(x), float(y))
    sequence = MRCLAMSequence(barcodes, landmarks)
    for r in range(1, NUM_ROBOTS + 1):
        sequence.groundtruth.append(table(f'Robot{r}_Groundtruth.dat', 4))
        sequence.odometry.append(table(f'Robot{r}_Odometry.dat', 3))
        sequence.measurements.append(table(f'Robot{r}_Measurement.dat', 4))
        # a bearing is an angle from the robot's heading, in (-pi, pi]: a
        # value beyond is a damaged row, not an angle to wrap
        beyond = np.flatnonzero(np.abs(sequence.measurements[-1][:, 3]) >
                                math.pi + 1e-6)
        if beyond.size:
            row = int(beyond[0])
            raise ValueError(
                f"'Robot{r}_Measurement.dat': data row {row + 1} gives a "
                f"bearing of {float(sequence.measurements[-1][row, 3])!r} "
                f"rad, "
                f"outside [-pi, pi]")
        for what, data in (('Groundtruth', sequence.groundtruth[-1]),
                           ('Odometry', sequence.odometry[-1])):
            if len(data) < 2:
                raise ValueError(f"'Robot{r}_{what}.dat' holds fewer than "
                                 f"two rows")
    # a link needs a barcode of another robot or of a surveyed landmark:
    # without one (an empty Barcodes.dat) the robots would be tracked on
    # odometry alone
    usable = sum(int(np.isin(rows[:, 1], [
        barcode for barcode, subject in barcodes.items()
        if subject != r + 1 and (1 <= subject <= NUM_ROBOTS or
                                 subject in landmarks)]).sum())
        for r, rows in enumerate(sequence.measurements))
    if usable == 0:
        total = sum(len(rows) for rows in sequence.measurements)
        raise ValueError(
            f"'{source}' holds no usable measurement: none of its {total} "
            f"measurements names the barcode of another robot or of a "
            f"surveyed landmark in 'Barcodes.dat' ({len(barcodes)} "
            f"barcode{'s' * (len(barcodes) != 1)})")
    return sequence


def interpolate_pose(groundtruth: np.ndarray,
                     times: np.ndarray) -> np.ndarray:
    r"""The poses :math:`[x, y, \theta]` :math:`(T, 3)` at :obj:`times`,
    linear between the ground truth's samples (the heading unwrapped
    first, so that it turns the short way across :math:`\pm \pi`, then
    wrapped to :math:`(-\pi, \pi]`)."""
    t = groundtruth[:, 0]
    heading = np.unwrap(groundtruth[:, 3])
    pose = np.stack([np.interp(times, t, groundtruth[:, 1]),
                     np.interp(times, t, groundtruth[:, 2]),
                     np.interp(times, t, heading)], -1)
    pose[:, 2] = math.pi - np.mod(math.pi - pose[:, 2], 2 * math.pi)
    return pose


def integrate_odometry(odometry: np.ndarray,
                       times: np.ndarray) -> np.ndarray:
    r"""The inputs :math:`[\delta_d, \delta_\theta]` :math:`(T - 1, 2)` of
    the intervals between consecutive :obj:`times` :math:`(T)`: the
    integrals of the forward and angular velocity, each sample held until
    the next; NaN for an interval not inside the odometry's span."""
    t = odometry[:, 0]
    rates = odometry[:, 1:]
    # the integral at every sample time, then anywhere by the held rate
    at_samples = np.concatenate([np.zeros((1, 2)), np.cumsum(
        rates[:-1] * np.diff(t)[:, None], 0)])
    last = np.clip(np.searchsorted(t, times, side='right') - 1, 0,
                   len(t) - 1)
    integral = at_samples[last] + rates[last] * (times - t[last])[:, None]
    inputs = np.diff(integral, axis=0)
    covered = (times[:-1] >= t[0]) & (times[1:] <= t[-1])
    inputs[~covered] = np.nan
    return inputs


def mrclam_realization(sequence: MRCLAMSequence, dt: float = 0.5,
                         duration: float = 600.0,
                         start: Optional[float] = None,
                         features: Sequence[str] = ('range', 'bearing'),
                         odometry: bool = True, links: str = 'all',
                         prior_std: float = 0.5, heading_std: float = 0.2,
                         negative_ranges: bool = True
                         ) -> Tuple[Realization, Dict[str, int]]:
    r"""The realization of :obj:`duration` seconds of :obj:`sequence` from
    :obj:`start` (the sequence's :meth:`~MRCLAMSequence.start` by
    default) in steps of :obj:`dt` under the test protocol (see the module
    docstring), with the link :obj:`features` (:obj:`('range',)` or
    :obj:`('range', 'bearing')`), the odometry as known inputs or not, and
    the :obj:`links` (:obj:`"all"`, :obj:`"landmarks"` or
    :obj:`"robots"`); and what was dropped or merged
    (:obj:`"unknown_barcodes"`, :obj:`"repeated"`, :obj:`"outside"`).
    A negative range kept is refused naming its file and row unless the
    likelihood takes :obj:`negative_ranges` (the measurement role's
    :attr:`~tg_nebp.models.MeasurementModel.negative_ranges`).

    Nodes: the robots first (agents, subject order), then the landmarks
    (anchors, subject order)."""
    if links not in LINKS:
        raise ValueError(f"'links' must be one of {list(LINKS)}, got "
                         f"{links!r}")
    if tuple(features) not in (('range', ), ('range', 'bearing')):
        raise ValueError(f"'features' must be ('range',) or ('range', "
                         f"'bearing'), got {tuple(features)!r}")
    t0 = sequence.start() if start is None else float(start)
    steps = int(round(duration / dt))
    if steps < 1 or t0 + steps * dt > sequence.end() + 1e-9:
        raise ValueError(f"{duration} s from {t0:.3f} in steps of {dt} s "
                         f"leave the span in which every robot has ground "
                         f"truth and odometry ({sequence.start():.3f} to "
                         f"{sequence.end():.3f})")
    times = t0 + dt * np.arange(steps + 1)  # t_0 .. t_T
    landmark_ids = sorted(sequence.landmarks)
    node_of = {r: r - 1 for r in range(1, NUM_ROBOTS + 1)}
    node_of.update({s: NUM_ROBOTS + k for k, s in enumerate(landmark_ids)})
    count = NUM_ROBOTS + len(landmark_ids)
    poses = np.zeros((count, steps + 1, 3))
    for r in range(NUM_ROBOTS):
        poses[r] = interpolate_pose(sequence.groundtruth[r], times)
    for s in landmark_ids:
        poses[node_of[s], :, :2] = sequence.landmarks[s]
    counts = dict(unknown_barcodes=0, repeated=0, outside=0)
    width = len(tuple(features))
    kept = []  # per robot: (times, receivers, senders, features)
    for r in range(NUM_ROBOTS):
        rows = sequence.measurements[r]
        subject = np.array([sequence.barcodes.get(int(b), -1)
                            for b in rows[:, 1]], dtype=np.int64)
        known = np.isin(subject, list(node_of)) & (subject != r + 1)
        counts['unknown_barcodes'] += int((~known).sum())
        step = step_of(rows[:, 0], t0, dt, steps)
        counts['outside'] += int((known & (step < 0)).sum())
        to_robot = subject <= NUM_ROBOTS
        use = known & (step >= 0) & {
            'all': True, 'landmarks': ~to_robot, 'robots': to_robot}[links]
        negative = np.flatnonzero(use & (rows[:, 2] < 0))
        if negative.size and not negative_ranges:
            row = int(negative[0])
            raise ValueError(
                f"'Robot{r + 1}_Measurement.dat': data row {row + 1} "
                f"gives a negative range ({float(rows[row, 2])!r} m), "
                f"which the likelihood does not take (its ranges are "
                f"non-negative)")
        kept.append((rows[use, 0], step[use], np.full(int(use.sum()), r),
                     np.array([node_of[s] for s in subject[use]],
                              dtype=np.int64), rows[use, 2:2 + width]))
    times_kept, step, receiver, sender, values = (
        np.concatenate(part) for part in zip(*kept))
    merged = merge_links(step, receiver, sender, values.reshape(-1, width),
                         'latest', times=times_kept)
    counts['repeated'] = merged.merged
    edge_index, edge_attr, edge_time = (merged.edge_index, merged.edge_attr,
                                        merged.edge_time)
    anchor = torch.arange(count) >= NUM_ROBOTS
    prior_var = torch.tensor([prior_std**2] * 2 + [heading_std**2],
                             dtype=torch.float32)
    prior_cov = torch.diag_embed(prior_var.expand(count, 3)).clone()
    prior_cov[anchor] = 0
    data = Realization(
        states=torch.from_numpy(poses[:, 1:]).float(),
        edge_index=edge_index, edge_attr=edge_attr, edge_time=edge_time,
        anchor=anchor, prior_mean=torch.from_numpy(poses[:, 0]).float(),
        prior_cov=prior_cov, num_steps=steps, num_nodes=count,
        position_dim=2)
    if odometry:
        control = np.full((count, steps, 2), np.nan)
        for r in range(NUM_ROBOTS):
            control[r] = integrate_odometry(sequence.odometry[r], times)
        data.control = torch.from_numpy(control).float()
    return data, counts


def _scale(residuals: np.ndarray) -> float:
    # a robust standard deviation: 1.4826 times the median absolute
    # deviation from the median (a Gaussian's sigma)
    return float(1.4826 * np.median(np.abs(residuals -
                                           np.median(residuals))))


def _variance_fit(squared: np.ndarray, columns: np.ndarray,
                  floor: float) -> np.ndarray:
    # non-negative coefficients c of squared ~ columns @ c (least squares,
    # a column whose coefficient would be negative dropped), the first
    # (the constant) at least 'floor'
    active = list(range(columns.shape[1]))
    while True:
        c, *_ = np.linalg.lstsq(columns[:, active], squared, rcond=None)
        if (c >= 0).all() or len(active) == 1:
            break
        active.pop(int(np.argmin(np.where(np.arange(len(c)) == 0, np.inf,
                                          c))))
    out = np.zeros(columns.shape[1])
    out[active] = np.clip(c, 0, None)
    out[0] = max(out[0], floor)
    return out


def long_run_factor(residuals: np.ndarray, horizon: int) -> float:
    r"""How much the variance of the mean of :obj:`horizon` consecutive
    residuals exceeds that of independent ones: :math:`1 + 2
    \sum_{k=1}^{H-1} (1 - k / H) \rho_k` (at least 1), with
    :math:`\rho_k` the correlation of the residuals :math:`k` steps apart
    over the rows of :obj:`residuals` :math:`(P, T)` (one series per row,
    NaN where a step has none)."""
    factor = 1.0
    for k in range(1, horizon):
        x, y = residuals[:, :-k].reshape(-1), residuals[:, k:].reshape(-1)
        both = np.isfinite(x) & np.isfinite(y)
        if both.sum() < 3:
            break
        rho = float(np.corrcoef(x[both], y[both])[0, 1])
        factor += 2 * (1 - k / horizon) * rho
    return max(factor, 1.0)


def _block_sums(values: np.ndarray, horizon: int) -> np.ndarray:
    # the sums of 'horizon' consecutive steps of every row (R, T), the
    # blocks that do not overlap; a block with a NaN is NaN
    blocks = values.shape[1] // horizon
    return values[:, :blocks * horizon].reshape(
        values.shape[0], blocks, horizon).sum(-1).reshape(-1)


#: The fewest links that :func:`fit_models` fits the measurement noise on
#: (a spread, and a range bias's line that is not through every point).
FIT_MIN_LINKS = 3


def _check_fittable(data: Realization, horizon: int) -> None:
    # what fit_models needs of a sequence, each lack said as it is: enough
    # links, at least one block of the horizon's steps, robots that move
    # and odometry to compare their moves with
    links = int(data.edge_index.size(1))
    if links < FIT_MIN_LINKS:
        raise ValueError(f"the sequence has {links} usable links (a range "
                         f"and bearing to a known barcode); fitting the "
                         f"measurement noise needs at least {FIT_MIN_LINKS}")
    moves = int(data.num_steps) - 1
    if moves < horizon:
        raise ValueError(f"the sequence has {moves + 1} steps, fewer moves "
                         f"({moves}) than the horizon of {horizon} steps "
                         f"that the long-run variances sum over: give a "
                         f"horizon of at most {max(moves, 1)} or a longer "
                         f"sequence")
    agents = ~data.anchor
    states = data.states[agents].double()
    moved = (states[:, 1:] - states[:, :-1]).abs().amax()
    if not bool(moved > 0):
        raise ValueError("no robot moves in the sequence's ground truth: "
                         "the odometry's noise has nothing to be fitted on")
    control = data.control[agents, 1:]
    if not bool(torch.isfinite(control).all(-1).any()):
        raise ValueError("the sequence has no odometry (no robot step with "
                         "both inputs): the odometry's noise cannot be "
                         "fitted")


def fit_models(data: Realization, max_range: float = 10.0,
               field_of_view: float = 2 * math.pi,
               horizon: int = FIT_HORIZON
               ) -> Tuple['UnicycleOdometry', 'StudentTRangeBearing', Dict]:
    r"""The noise of a sequence's sensors, fitted on its ground truth
    (a realization of :func:`~tg_nebp.datasets.mrclam_realization` with
    bearings and odometry): the models the trackers take and what was
    measured.

    Real errors are not independent from step to step (a range to one
    landmark is off by nearly the same amount for seconds; odometry drifts),
    while every tracker treats them as independent. Over the
    :obj:`horizon` :math:`H` steps a filter's estimate averages, the
    variances that keep it consistent are the long-run ones: the
    variance of a sum of :math:`H` steps' errors divided by :math:`H`
    (:obj:`horizon` 1: the one-step variances; by default
    :data:`~tg_nebp.datasets.mrclam.FIT_HORIZON`).

    * **Range and bearing**: the residuals of every link against the
      interpolated true poses; the scales :math:`\sigma` are robust
      (1.4826 times the median absolute deviation) times the square root of
      the :func:`~tg_nebp.datasets.long_run_factor` of the residuals of each link (receiver
      and sender) over :math:`H` steps (from the residuals standardized
      and clipped at three scales); the Student-t's :math:`\nu` the
      maximum-likelihood one on a grid (2, 3, 4, 6, 8, 16, 32) over both
      residuals at the one-step scales; reported beside them: the one-step
      scales and the factors, the median residuals, the range bias's slope
      against the distance (least squares) and the fraction of residuals
      beyond three one-step scales.
    * **Odometry**: the inputs against the true moves (the distance between
      the true positions, the wrapped change of the true heading), summed
      over blocks of :math:`H` steps; :math:`\sigma_d^2 + s_d^2
      \delta_d^2` and :math:`\sigma_\theta^2 + s_\theta^2
      \delta_\theta^2 + s_{\theta d}^2 \delta_d^2` by non-negative
      least squares of the squared block errors against the blocks' sums of
      those terms, the constants at least :math:`10^{-3}` m and rad; the
      input-free prediction (a step without odometry) a random walk whose
      variance per step is the mean square of the true moves (per
      coordinate, and of the heading) summed over blocks of :math:`H`
      steps, divided by :math:`H` (robots drive smoothly: over 20 s they
      move much further than independent steps of their size would).

    Returns the :class:`~tg_nebp.models.UnicycleOdometry`, the
    :class:`~tg_nebp.models.StudentTRangeBearing` (with :obj:`max_range`
    and :obj:`field_of_view`) and a report of the figures. A sequence it
    cannot fit (fewer than ``FIT_MIN_LINKS`` links, fewer moves than
    the horizon, no robot that moves, no odometry) is a
    :class:`ValueError` that says which."""
    from tg_nebp.models import (StudentTRangeBearing, UnicycleOdometry,
                                wrap_angle)
    from tg_nebp.models.range_bearing import RangeBearingModel
    states = data.states.double()
    horizon = check_positive_int(horizon, 'horizon')
    _check_fittable(data, horizon)
    src, dst = data.edge_index
    t = data.edge_time
    expected = RangeBearingModel.expected(states[src, t], states[dst, t])
    z = data.edge_attr.double()
    range_res = (z[:, 0] - expected[:, 0]).numpy()
    bearing_res = wrap_angle(z[:, 1] - expected[:, 1]).numpy()
    distance = expected[:, 0].numpy()
    sigma, sigma_bearing = _scale(range_res), _scale(bearing_res)
    slope, intercept = np.polyfit(distance, range_res, 1)
    centred = np.stack([range_res - np.median(range_res),
                        bearing_res - np.median(bearing_res)], -1)
    # every link's residual series over the steps (NaN where it has none)
    link_keys = (src * data.num_nodes + dst).numpy()
    links, row = np.unique(link_keys, return_inverse=True)
    factors = []
    for column, scale in ((0, sigma), (1, sigma_bearing)):
        series = np.full((len(links), int(data.num_steps)), np.nan)
        series[row, t.numpy()] = np.clip(centred[:, column] / scale, -3, 3)
        factors.append(long_run_factor(series, horizon))
    best, best_nu = -np.inf, None
    for nu in (2.0, 3.0, 4.0, 6.0, 8.0, 16.0, 32.0):
        model = StudentTRangeBearing(sigma, sigma_bearing, nu)
        value = float(model.log_likelihood_of_residuals(
            torch.from_numpy(centred)).sum())
        if value > best:
            best, best_nu = value, nu
    agents = ~data.anchor
    control = data.control[agents].double()
    moved = states[agents, 1:, :2] - states[agents, :-1, :2]
    true_distance = moved.norm(dim=-1).numpy().reshape(-1)
    true_turn = wrap_angle(states[agents, 1:, 2] -
                           states[agents, :-1, 2]).numpy().reshape(-1)
    d = control[:, 1:, 0].numpy().reshape(-1)
    turn = control[:, 1:, 1].numpy().reshape(-1)
    keep = np.isfinite(d) & np.isfinite(turn)
    shape = control[:, 1:, 0].shape
    # per agent and step (NaN where the odometry has no value), summed
    # over blocks of the horizon
    d = np.where(keep, d, np.nan).reshape(shape)
    turn = np.where(keep, turn, np.nan).reshape(shape)
    e_d = _block_sums(np.abs(d) - true_distance.reshape(shape), horizon)
    e_t = _block_sums(turn - true_turn.reshape(shape), horizon)
    columns = [_block_sums(v, horizon) for v in
               (np.ones_like(d), d**2, turn**2)]
    whole = np.isfinite(e_d) & np.isfinite(e_t)
    ones, d2, turn2 = (c[whole] for c in columns)
    distance_fit = _variance_fit(e_d[whole]**2, np.stack([ones, d2], -1),
                                 1e-6)
    turn_fit = _variance_fit(e_t[whole]**2, np.stack([ones, turn2, d2], -1),
                             1e-6)
    # the input-free prediction: a random walk that spreads over the
    # horizon as far as the true moves summed over it
    moves = moved.numpy()
    position_sums = np.concatenate([_block_sums(moves[..., c], horizon)
                                    for c in range(moves.shape[-1])])
    idle_position = float(np.sqrt(np.mean(position_sums**2) / horizon))
    turn_sums = _block_sums(true_turn.reshape(shape), horizon)
    idle_heading = float(np.sqrt(np.mean(turn_sums**2) / horizon))
    motion = UnicycleOdometry(
        idle_position=idle_position, idle_heading=idle_heading,
        sigma_distance=float(np.sqrt(distance_fit[0])),
        distance_scale=float(np.sqrt(distance_fit[1])),
        sigma_turn=float(np.sqrt(turn_fit[0])),
        turn_scale=float(np.sqrt(turn_fit[1])),
        turn_per_distance=float(np.sqrt(turn_fit[2])))
    measurement = StudentTRangeBearing(
        sigma * math.sqrt(factors[0]), sigma_bearing * math.sqrt(factors[1]),
        best_nu, max_range, field_of_view)
    report = dict(
        links=int(len(range_res)), range_median=float(np.median(range_res)),
        range_bias_slope=float(slope), range_bias_intercept=float(intercept),
        range_beyond_3_sigma=float(np.mean(np.abs(centred[:, 0]) >
                                           3 * sigma)),
        bearing_median=float(np.median(bearing_res)),
        bearing_beyond_3_sigma=float(np.mean(np.abs(centred[:, 1]) >
                                             3 * sigma_bearing)),
        nu=best_nu, agent_steps=int(keep.sum()), horizon=horizon,
        range_sigma_one_step=sigma, bearing_sigma_one_step=sigma_bearing,
        range_long_run_factor=factors[0],
        bearing_long_run_factor=factors[1])
    return motion, measurement, report
