r"""Real UWB ranging as scenarios and datasets: a :class:`RecordingScenario`
names a recording (a ROS bag with its topics, the TIERS dataset's runs by
name; a MILUV experiment by name), the step, which nodes are anchors, the range calibration and the
models; :class:`RecordingDataset` (PyG's
:class:`~torch_geometric.data.InMemoryDataset`) reads it into
:class:`~tg_nebp.data.Realization`\ s (:func:`~tg_nebp.datasets.recording_realization`),
so that every tracker, metric and command takes it as it takes simulated
data; :func:`fit_range_models` calibrates the models on a recording's
truth."""
import dataclasses
import logging
import math
import os
import re
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

import numpy as np
import torch
from torch_geometric.data import InMemoryDataset

from tg_nebp.data.realization import Realization, scored_of
from tg_nebp.data.validation import check_positive_int, check_realization
from tg_nebp.datasets.mrclam import _scale, long_run_factor
from tg_nebp.datasets.recording import (RangeCalibration, Recording,
                                        recording_realization,
                                        recording_report)
from tg_nebp.datasets.miluv import read_miluv
from tg_nebp.datasets.rosbag import BagTopics, read_bag
from tg_nebp.datasets.scenario import RecordedScenarioFields
from tg_nebp.io import read_json
from tg_nebp.models import MeasurementModel, MotionModel

__all__ = ['MIN_SIGMA', 'RecordingScenario', 'RecordingDataset',
           'fit_range_models',
           'fitted_recording_scenario', 'RECORDING_PARTS', 'UWB_FIT_HORIZON',
           'READERS', 'UWB_MIN_NU']

LOG = logging.getLogger('tg_nebp.datasets')

#: The parts of a recording that a scenario covers (all of the span in
#: which every node has truth, or its first or second half, to fit or train
#: on one half and test on the other).
RECORDING_PARTS = ('all', 'first-half', 'second-half')
#: The steps over which :func:`~tg_nebp.datasets.fit_range_models` fits the
#: ranges' long-run spread by default (10 steps of 0.5 s; a UWB pair's
#: error holds for seconds while the robots move).
UWB_FIT_HORIZON = 10
#: The readers a scenario names.
READERS = ('rosbag', 'miluv')

# tiers-uwb-testN and its options
_TIERS = re.compile(r'tiers-uwb-(test[0-9]+)((?:-[a-z0-9]+)*)\Z')
_TIERS_OPTIONS = {
    'ros1': dict(ros1=True),
    'raw': dict(raw=True),
    'all-nodes': dict(without_truth=True),
    'first-half': dict(part='first-half'),
    'second-half': dict(part='second-half'),
}
# miluv-EXPERIMENT and its options
_MILUV = re.compile(r'miluv-([A-Za-z0-9_]+)((?:-[a-z0-9]+)*)\Z')
_MILUV_OPTIONS = {
    'no-height': dict(height=False),
    'first-half': dict(part='first-half'),
    'second-half': dict(part='second-half'),
}
# the models fitted on the first half of TIERS case 4 test3 and of MILUV's
# cirObstacles_1_random3_0, shipped
_FITTED = {'tiers': 'tiers-uwb.json', 'miluv': 'miluv.json'}


def _options(text: str, rest: str, known: Dict[str, dict],
             family: str) -> Dict[str, Any]:
    # the options after a name, each after a hyphen, the longest first
    # ('first-half' before 'first'); one that repeats or contradicts
    # another is refused
    chosen: Dict[str, Any] = {}
    while rest:
        token = next((t for t in sorted(known, key=len, reverse=True)
                      if rest.startswith('-' + t)
                      and rest[len(t) + 1:len(t) + 2] in ('', '-')), None)
        if token is None:
            raise ValueError(f"scenario '{text}': unknown option "
                             f"'{rest[1:].split('-')[0]}'; the options of "
                             f"{family} are {sorted(known)}")
        for key, value in known[token].items():
            if key in chosen:
                raise ValueError(f"scenario '{text}': the option '{token}' "
                                 f"repeats or contradicts another")
            chosen[key] = value
        rest = rest[len(token) + 1:]
    return chosen


def _positive(value) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0)


@dataclasses.dataclass(frozen=True)
class RecordingScenario(RecordedScenarioFields):
    r"""A recording of ranges between nodes, binned into steps
    (:func:`~tg_nebp.datasets.recording_realization`), and the models the
    trackers read: what :class:`RecordingDataset` reads and what
    :obj:`--scenario tiers-uwb-testN` or a JSON file names.

    By name (:meth:`load`): :obj:`"miluv-EXPERIMENT"` is MILUV's experiment
    of that name under the root (:func:`~tg_nebp.datasets.read_miluv`: its
    tags as nodes, 3-D, the height sensor read), steps of 0.5 s, with the
    models and the calibration fitted on the first half of
    :obj:`cirObstacles_1_random3_0` (shipped); options: :obj:`no-height`,
    :obj:`first-half`, :obj:`second-half`. :obj:`"tiers-uwb-testN"` is run :math:`N` of
    the TIERS UWB dataset's case 4 (its ROS 2 bag
    :obj:`case_4/ros2/testN` under the root), turtlebots 1 and 2 declared
    anchors (they stand still in every run), nodes :obj:`n_1` to
    :obj:`n_7` (:obj:`n_8` has no truth), 2-D, steps of 0.5 s, with the
    models and the range calibration fitted on the first half of
    :obj:`test3` (shipped). Options follow the name: :obj:`ros1` (the ROS 1
    copy :obj:`case_4/ros1/testN.bag`), :obj:`raw` (no range calibration),
    :obj:`all-nodes` (:obj:`n_8` tracked too, not scored),
    :obj:`first-half` or :obj:`second-half`.

    Args:
        name (str): Name.
        recording (str): The recording, a path under the dataset's root
            (or absolute).
        options (dict): What the reader is told: a bag's
            :class:`~tg_nebp.datasets.BagTopics` fields; MILUV's
            :obj:`{"height": true}` (the height sensor read, or not).
        motion (dict or MotionModel): The motion model (its configuration).
        measurement (dict or MeasurementModel): The likelihood of a range.
        reader (str, optional): One of
            :data:`~tg_nebp.datasets.uwb.READERS`: :obj:`"rosbag"`
            (the recording a bag's path under the root) or :obj:`"miluv"`
            (the recording an experiment's name, the root MILUV's).
            (default: :obj:`"rosbag"`)
        position_dim (int, optional): 2 or 3 (MILUV: 3). (default: :obj:`2`)
        anchors (list, optional): Names of nodes declared anchors (standing
            still: their truth at the start is their surveyed position).
            (default: none)
        calibration (dict, optional): The
            :class:`~tg_nebp.datasets.RangeCalibration` fields.
            (default: none)
        dt (float, optional): Step, seconds. (default: :obj:`0.5`)
        part (str, optional): One of
            :data:`~tg_nebp.datasets.uwb.RECORDING_PARTS`.
            (default: :obj:`"all"`)
        duration (float, optional): Seconds from the part's start;
            :obj:`None` for the whole part (filled in when the recording is
            read: :meth:`resolved`). (default: :obj:`None`)
        prior_std (float, optional): The prior's position standard
            deviation around the truth, metres. (default: :obj:`0.5`)
        velocity_std (float, optional): The prior's velocity standard
            deviation, metres per second. (default: :obj:`0.3`)
        symmetric (bool, optional): Both directions of a pair are one
            two-way range (merged within a step). (default: :obj:`True`)
        without_truth (bool, optional): A bag's nodes without ground truth
            tracked and their ranges used, not scored; left out (their
            ranges counted) without it. (default: :obj:`False`)
        description (str, optional): Free text, not part of the
            fingerprint. (default: :obj:`""`)
    """
    name: str
    recording: str
    options: Dict[str, Any]
    motion: Dict[str, Any]
    measurement: Dict[str, Any]
    reader: str = 'rosbag'
    position_dim: int = 2
    anchors: Tuple[str, ...] = ()
    calibration: Optional[Dict[str, Any]] = None
    dt: float = 0.5
    part: str = 'all'
    duration: Optional[float] = None
    prior_std: float = 0.5
    velocity_std: float = 0.3
    symmetric: bool = True
    without_truth: bool = False
    description: str = ''

    def __post_init__(self):
        fix = object.__setattr__  # frozen: normalize once
        for key in ('motion', 'measurement'):
            value = getattr(self, key)
            if isinstance(value, (MotionModel, MeasurementModel)):
                fix(self, key, value.config())
        if isinstance(self.options, BagTopics):
            fix(self, 'options', self.options.to_fields())
        if isinstance(self.calibration, RangeCalibration):
            fix(self, 'calibration', self.calibration.to_fields())
        if isinstance(self.anchors, list):
            fix(self, 'anchors', tuple(self.anchors))
        self._check()

    def _check(self):
        for key in ('name', 'recording'):
            if not isinstance(getattr(self, key), str) or \
                    not getattr(self, key):
                raise ValueError(f"'{key}' must be a non-empty string, got "
                                 f"{getattr(self, key)!r}")
        if self.reader not in READERS:
            raise ValueError(f"'reader' must be one of {list(READERS)}, got "
                             f"{self.reader!r}")
        if not isinstance(self.options, dict):
            raise ValueError(f"'options' must be an object, got "
                             f"{self.options!r}")
        try:
            _reader_options(self.reader, self.options)
        except (TypeError, ValueError) as e:
            raise ValueError(f"'options': {e}") from None
        if self.reader == 'miluv' and self.position_dim != 3:
            raise ValueError(f"'position_dim' of a MILUV experiment is 3, "
                             f"got {self.position_dim!r}")
        if self.position_dim not in (2, 3) or isinstance(self.position_dim,
                                                         bool):
            raise ValueError(f"'position_dim' must be 2 or 3, got "
                             f"{self.position_dim!r}")
        if not isinstance(self.anchors, tuple) or not all(
                isinstance(a, str) for a in self.anchors):
            raise ValueError(f"'anchors' must be a list of node names, got "
                             f"{self.anchors!r}")
        RangeCalibration.from_fields(self.calibration, 'calibration')
        for key in ('dt', 'prior_std', 'velocity_std', 'duration'):
            if key == 'duration' and self.duration is None:
                continue
            if not _positive(getattr(self, key)):
                raise ValueError(f"'{key}' must be a positive number, got "
                                 f"{getattr(self, key)!r}")
        if self.part not in RECORDING_PARTS:
            raise ValueError(f"'part' must be one of {list(RECORDING_PARTS)}"
                             f", got {self.part!r}")
        for key in ('symmetric', 'without_truth'):
            if not isinstance(getattr(self, key), bool):
                raise ValueError(f"'{key}' must be true or false, got "
                                 f"{getattr(self, key)!r}")
        motion, measurement = self.motion_model, self.measurement_model
        if tuple(measurement.features) not in (('range', ),
                                               ('range', 'sensor')):
            raise ValueError(f"'measurement' ({measurement.name}) must be a "
                             f"range likelihood (of one sensor or named "
                             f"sensors), reads {list(measurement.features)}")
        if motion.state_dim not in (None, 2 * self.position_dim):
            raise ValueError(f"'motion' ({motion.name}) must move "
                             f"[p, v] states of {2 * self.position_dim} "
                             f"entries")

    @classmethod
    def load(cls, name_or_path: Union[str, os.PathLike]
             ) -> 'RecordingScenario':
        r"""A scenario by name (:obj:`"tiers-uwb-testN"` with options,
        see the class) or from a JSON file of its fields."""
        text = str(name_or_path)
        match = _TIERS.match(text)
        if match is not None and not text.endswith('.json'):
            run = match.group(1)
            chosen = _options(text, match.group(2), _TIERS_OPTIONS,
                              'tiers-uwb-testN')
            recording = (f'case_4/ros1/{run}.bag' if chosen.get('ros1')
                         else f'case_4/ros2/{run}')
            changes = dict(name=text, recording=recording,
                           part=chosen.get('part', 'all'))
            if chosen.get('raw'):
                changes['calibration'] = None
            if chosen.get('without_truth'):
                changes['without_truth'] = True
            return _shipped('tiers').replace(**changes)
        match = _MILUV.match(text)
        if match is not None and not text.endswith('.json'):
            chosen = _options(text, match.group(2), _MILUV_OPTIONS,
                              'miluv-EXPERIMENT')
            return _shipped('miluv').replace(
                name=text, recording=match.group(1),
                part=chosen.get('part', 'all'),
                options=dict(height=chosen.get('height', True)))
        path = Path(name_or_path)
        if path.suffix != '.json':
            raise ValueError(f"unknown scenario '{text}'; a UWB recording is "
                             f"tiers-uwb-testN with the options "
                             f"{sorted(_TIERS_OPTIONS)}, miluv-EXPERIMENT "
                             f"with the options {sorted(_MILUV_OPTIONS)}, or "
                             f"a .json file")
        if not path.is_file():
            raise ValueError(f"scenario file '{path}' does not exist")
        return cls.from_fields(read_json(path), str(path))

    __hash__ = RecordedScenarioFields.__hash__

    @property
    def range_calibration(self) -> RangeCalibration:
        return RangeCalibration.from_fields(self.calibration, self.name)

    @property
    def num_steps(self) -> Optional[int]:
        r"""The steps of the realization; :obj:`None` before the recording
        is read when it is a whole part (:meth:`resolved`)."""
        if self.duration is None:
            return None
        return int(math.floor(self.duration / self.dt + 1e-9))

    def resolved(self, recording: Recording) -> 'RecordingScenario':
        r"""This scenario with the :obj:`duration` of a whole part filled
        in from the read :obj:`recording` (itself otherwise); a part too
        short for the duration, or for one step, is a
        :class:`ValueError`."""
        # the binning starts one step in (the prior's time before it)
        length = self.span(recording)[1] - self.dt
        duration = length if self.duration is None else self.duration
        steps = int(math.floor(duration / self.dt + 1e-9))
        if steps < 1 or duration > length + 1e-6:
            raise ValueError(
                f"scenario '{self.name}': the {self.part} part of "
                f"'{recording.source}' ({length:.3f} s) holds no "
                f"{duration:g} s in steps of {self.dt} s")
        return self.replace(duration=steps * self.dt)

    def path(self, root: Union[str, os.PathLike]) -> Path:
        r"""Where the recording lies under :obj:`root`."""
        if self.reader == 'miluv':
            return Path(root) / 'data' / self.recording
        return Path(root) / self.recording

    def read(self, root: Union[str, os.PathLike]) -> Recording:
        r"""The recording under :obj:`root`, read by the scenario's
        reader."""
        options = _reader_options(self.reader, self.options)
        if self.reader == 'miluv':
            return read_miluv(root, self.recording, **options)
        return read_bag(self.path(root), options, self.position_dim,
                        self.without_truth)

    def span(self, recording: Recording) -> Tuple[float, float]:
        r"""The part's start and length in seconds from the first time
        every node with truth has it."""
        begin, end = recording.span()
        half = 0.5 * (end - begin)
        return {'all': (0.0, end - begin), 'first-half': (0.0, half),
                'second-half': (half, end - begin - half)}[self.part]

    def realization(self, recording: Recording
                    ) -> Tuple[Realization, Dict[str, int]]:
        r"""The part of the read :obj:`recording`, binned, and what was
        dropped or merged."""
        start = self.span(recording)[0]
        return recording_realization(
            recording, self.dt, start, self.resolved(recording).duration,
            self.anchors,
            self.range_calibration, self.prior_std, self.velocity_std,
            self.symmetric)


def _reader_options(reader: str, options: Dict[str, Any]):
    # the reader's own options from a scenario's: a bag's topics, MILUV's
    # keyword arguments
    if reader == 'rosbag':
        return BagTopics(**options)
    unknown = set(options) - {'height'}
    if unknown:
        raise ValueError(f"MILUV's options are 'height', got "
                         f"{sorted(unknown)}")
    if not isinstance(options.get('height', True), bool):
        raise ValueError(f"'height' must be true or false, got "
                         f"{options['height']!r}")
    return dict(options)


def _shipped(family: str) -> RecordingScenario:
    path = resources.files('tg_nebp.datasets') / 'fitted' / _FITTED[family]
    return RecordingScenario.from_fields(read_json(path), _FITTED[family])


def _distances(data: Realization) -> np.ndarray:
    # every link's true distance at its step, float64
    src, dst = data.edge_index
    dim = data.states.size(-1) // 2
    states = data.states.double()
    t = data.edge_time
    return (states[src, t, :dim] - states[dst, t, :dim]).norm(
        dim=-1).numpy()


#: The smallest Student-t :math:`\nu` that
#: :func:`~tg_nebp.datasets.fit_range_models` gives a
#: sensor. Chosen on the fit halves (validation) of both recordings; the
#: maximum-likelihood :math:`\nu` at the truth is 2-3 for UWB, and with it
#: the filters lose MILUV's drone (1 to 2 UWB ranges a tag a step, each
#: easily discounted as an outlier once the estimate is off: IEKF 1.07 m,
#: Gaussian BP 2.04 m on the first half), while :math:`\nu` = 4, 8, 32
#: give 0.61, 0.40, 0.35 m (Gaussian BP 0.55, 0.46, 0.42 m); on TIERS's
#: test3 every :math:`\nu` gives 0.148-0.150 m.
UWB_MIN_NU = 32.0
#: The smallest range scale that :func:`~tg_nebp.datasets.fit_range_models`
#: gives a sensor, in metres (a link known exactly, a rigid body's, still gets a likelihood
#: whose precision a float32 linearization can hold).
MIN_SIGMA = 0.01


def _sensor_noise(centred: np.ndarray, row: np.ndarray, times: np.ndarray,
                  pairs: int, steps: int, horizon: int
                  ) -> Tuple[float, float, float]:
    # a sensor's one-step robust scale, long-run factor and the Student-t
    # nu of the largest likelihood at the truth
    from tg_nebp.models import StudentTRange
    sigma = max(_scale(centred), MIN_SIGMA)
    series = np.full((pairs, steps), np.nan)
    series[row, times] = np.clip(centred / sigma, -3, 3)
    factor = long_run_factor(series, horizon)
    best, best_nu = -np.inf, None
    for nu in (2.0, 3.0, 4.0, 6.0, 8.0, 16.0, 32.0):
        value = float(StudentTRange(sigma, nu).log_likelihood_of_distance(
            torch.from_numpy(centred).view(-1, 1),
            torch.zeros(len(centred), 1, dtype=torch.float64)).sum())
        if value > best:
            best, best_nu = value, nu
    return sigma, factor, best_nu


def fit_range_models(data: Realization, nodes: List[str], dt: float,
                     horizon: int = UWB_FIT_HORIZON,
                     max_range: float = 50.0,
                     sigma_a: float = 0.05,
                     sensors: Tuple[str, ...] = ('uwb', ),
                     min_nu: float = UWB_MIN_NU
                     ) -> Tuple[MotionModel, MeasurementModel,
                                RangeCalibration, Dict[str, Any]]:
    r"""The models of a recording, fitted on its truth: :obj:`data` a
    realization of :func:`~tg_nebp.datasets.recording_realization` in steps
    of :obj:`dt` seconds binned without a calibration, whose nodes are
    named :obj:`nodes` and whose links were measured by :obj:`sensors`
    (with more than one, each link's second feature names its sensor).

    * **Range calibration**: each pair's bias, the median of its links'
      residuals :math:`z - \|\mathbf{p}_j - \mathbf{p}_i\|`; a pair not
      seen gets the median of the pairs' biases.
    * **Range noise**, per sensor: the residuals less their pair's bias; a
      Student-t (:obj:`max_range` its communication range) whose scale is
      robust (1.4826 times the median absolute deviation, at least
      :data:`~tg_nebp.datasets.uwb.MIN_SIGMA`) times the square root of the
      :func:`~tg_nebp.datasets.long_run_factor` of each pair's residual
      series over :obj:`horizon` steps (a UWB pair's error holds for
      seconds: a filter that averages the ranges as independent would be
      overconfident), and whose :math:`\nu` is the maximum-likelihood one on
      a grid (2, 3, 4, 6, 8, 16, 32) at the one-step scale (reported), at
      least :obj:`min_nu`
      (:data:`~tg_nebp.datasets.uwb.UWB_MIN_NU`: a tracker whose estimate is
      off must not discount the few ranges that would correct it).
    * **Motion**: a constant-velocity model whose acceleration noise
      :math:`\sigma_a` is the root mean square of the true accelerations
      of the agents that move (the change of the truth's velocity over a
      step divided by the step), over every axis; in a recording in which
      no agent moves (a calibration run) :obj:`sigma_a` is kept, and the
      report says so.

    Returns the :class:`~tg_nebp.models.ConstantVelocity`, the
    :class:`~tg_nebp.models.StudentTRange` (one sensor) or
    :class:`~tg_nebp.models.StudentTRangeBySensor`, the
    :class:`~tg_nebp.datasets.RangeCalibration` and a report of the
    figures. A sensor with fewer than 3 links is a :class:`ValueError`."""
    from tg_nebp.models import (ConstantVelocity, StudentTRange,
                                StudentTRangeBySensor)
    horizon = check_positive_int(horizon, 'horizon')
    # the links of two nodes with truth: a node without has no residual
    fitted = np.isfinite(_distances(data))
    if not fitted.all():
        data = data.clone()
        data.edge_index = data.edge_index[:, fitted]
        data.edge_attr = data.edge_attr[fitted]
        data.edge_time = data.edge_time[fitted]
    residual = data.edge_attr[:, 0].double().numpy() - _distances(data)
    sensor = (data.edge_attr[:, 1].round().long().numpy()
              if len(sensors) > 1 else np.zeros(len(residual), np.int64))
    src, dst = data.edge_index.numpy()
    count = int(data.num_nodes)
    pairs, row = np.unique(dst * count + src, return_inverse=True)
    biases = np.array([np.median(residual[row == k])
                       for k in range(len(pairs))])
    calibration = RangeCalibration(
        {f'{nodes[int(k) // count]}->{nodes[int(k) % count]}': float(b)
         for k, b in zip(pairs, biases)},
        float(np.median(biases[np.unique(row[sensor == 0])]))
        if (sensor == 0).any() else 0.0)
    centred = residual - biases[row]
    report: Dict[str, Any] = dict(links=int(len(residual)),
                                  pairs=int(len(pairs)), horizon=horizon)
    scales, nus = [], []
    for k, name in enumerate(sensors):
        mine = sensor == k
        if mine.sum() < 3:
            raise ValueError(f"the recording has {int(mine.sum())} links of "
                             f"the sensor '{name}'; fitting its noise needs "
                             f"at least 3")
        sigma, factor, nu = _sensor_noise(
            centred[mine], row[mine], data.edge_time.numpy()[mine],
            len(pairs), int(data.num_steps), horizon)
        scales.append(sigma * math.sqrt(factor))
        nus.append(max(nu, min_nu))
        mine_biases = biases[np.unique(row[mine])]
        report[name] = dict(
            links=int(mine.sum()), pairs=int(len(mine_biases)),
            bias_median=float(np.median(mine_biases)),
            bias_min=float(mine_biases.min()),
            bias_max=float(mine_biases.max()), sigma_one_step=sigma,
            long_run_factor=factor, nu_at_truth=nu, nu=nus[-1],
            beyond_3_sigma=float(np.mean(np.abs(centred[mine]) >
                                         3 * sigma)))
    dim = data.states.size(-1) // 2
    velocity = data.states[scored_of(data), :, dim:].double()
    moving = velocity.norm(dim=-1).amax(-1) > 0.05
    if bool(moving.any()) and velocity.size(1) > 1:
        acceleration = (velocity[moving, 1:] - velocity[moving, :-1]) / dt
        sigma_a = float(acceleration.square().mean().sqrt())
        report['sigma_a'] = sigma_a
    else:
        report['sigma_a'] = f'kept at {sigma_a} (no agent moves)'
    motion = ConstantVelocity(sigma_a, dt)
    if len(sensors) == 1:
        measurement = StudentTRange(scales[0], nus[0], max_range)
    else:
        measurement = StudentTRangeBySensor(scales, nus, max_range)
    return motion, measurement, calibration, report


def fitted_recording_scenario(scenario: RecordingScenario,
                              root: Union[str, os.PathLike],
                              name: Optional[str] = None,
                              horizon: int = UWB_FIT_HORIZON
                              ) -> Tuple[RecordingScenario, Dict[str, Any]]:
    r""":obj:`scenario` with its models and range calibration fitted
    (:func:`fit_range_models`) on its own part of its recording under
    :obj:`root` (binned without a calibration), and the fit's report: what
    :obj:`tg-nebp fit` writes and prints."""
    recording = scenario.read(root)
    data, counts = scenario.replace(calibration=None).realization(recording)
    LOG.info(recording_report(f"'{recording.source}' (the fit's part)",
                              [counts], [data.num_edges], scenario.dt))
    old = scenario.measurement_model
    motion, measurement, calibration, report = fit_range_models(
        data, recording.nodes, scenario.dt, horizon, old.max_range,
        getattr(scenario.motion_model, 'sigma_a', 0.05),
        tuple(recording.sensors))
    fitted = scenario.replace(
        name=name or scenario.name, motion=motion, measurement=measurement,
        calibration=calibration,
        description=(f"{scenario.name}: the models and the range calibration "
                     f"fitted on its {report['links']} links ("
                     f"{report['pairs']} pairs of "
                     f"{', '.join(recording.sensors)}; long-run spread over "
                     f"{horizon} steps)"))
    return fitted, report


class RecordingDataset(InMemoryDataset):
    r"""A real recording of ranges between nodes (UWB two-way ranging in a
    ROS bag; the TIERS UWB dataset's runs by name) as one
    :class:`~tg_nebp.data.Realization` of its scenario's part: the
    recording is read from :obj:`root` (:meth:`RecordingScenario.path`),
    binned into steps (:func:`~tg_nebp.datasets.recording_realization`),
    and what was kept, merged and dropped is reported.

    Args:
        root (str): The dataset's folder (laid out as the dataset is: for
            TIERS, the folder that holds :obj:`case_4/`).
        scenario (str or RecordingScenario): A name, a JSON file or one.
        num_realizations (int, optional): 1 or :obj:`None` (a recording is
            one realization). (default: :obj:`None`)
        transform (callable, optional): Applied on every access.
            (default: :obj:`None`)

    Attributes:
        scenario (RecordingScenario): The scenario.
        nodes (list): The nodes' names, in node order.
        counts (list): What was dropped or merged.
        report (str): One line on it (logged to :obj:`tg_nebp.datasets`).
    """
    def __init__(self, root: str,
                 scenario: Union[str, RecordingScenario],
                 num_realizations: Optional[int] = None,
                 transform: Optional[Callable] = None, log: bool = True):
        if isinstance(scenario, (str, os.PathLike)):
            scenario = RecordingScenario.load(scenario)
        if not isinstance(scenario, RecordingScenario):
            raise TypeError(f"'scenario' must be a name, a path or a "
                            f"RecordingScenario, got {scenario!r}")
        if num_realizations is not None:
            check_positive_int(num_realizations, 'num_realizations')
            if num_realizations > 1:
                raise ValueError(f"scenario '{scenario.name}' is one "
                                 f"recording: one realization, not "
                                 f"{num_realizations}")
        self.scenario = scenario
        super().__init__(str(root), transform, log=log)
        path = scenario.path(root)
        if not path.exists():
            raise ValueError(f"scenario '{scenario.name}': its recording "
                             f"'{path}' does not exist (give --root, the "
                             f"folder laid out as the dataset is)")
        recording = scenario.read(root)
        data, counts = scenario.realization(recording)
        check_realization(data, scenario.measurement_model.features,
                          negative_ranges=True)
        self.scenario = scenario.resolved(recording)
        self.nodes = list(recording.nodes)
        self.counts = [counts]
        self.report = recording_report(
            f"'{recording.source}' ('{scenario.name}')", self.counts,
            [data.num_edges], scenario.dt)
        self.data, self.slices = self.collate([data])
        LOG.info(self.report)

    @property
    def raw_dir(self) -> str:
        return self.root

    @property
    def raw_file_names(self) -> List[str]:
        return []

    @property
    def processed_file_names(self) -> List[str]:
        return []  # read in seconds: nothing is cached

    def download(self):
        pass

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}({len(self)}, scenario='
                f'{self.scenario.name})')
