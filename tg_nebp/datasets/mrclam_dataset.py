r"""The UTIAS MRCLAM sequences as scenarios and datasets: an
:class:`MRCLAMScenario` says which sequence, which part of it, which
information and which models; :class:`MRCLAM` (PyG's
:class:`~torch_geometric.data.InMemoryDataset`) reads the sequence (its zip,
downloaded where absent, or its folder) and holds its windows as
:class:`~tg_nebp.data.Realization`\ s, so that every tracker, metric and
command takes real robots as it takes simulated ones."""
import dataclasses
import logging
import math
import os
import re
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

import numpy as np
from torch_geometric.data import InMemoryDataset

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import check_positive_int, check_realization
from tg_nebp.datasets.mrclam import (FIT_HORIZON, LINKS, fit_models,
                                     mrclam_realization, read_mrclam)
from tg_nebp.datasets.scenario import RecordedScenarioFields
from tg_nebp.io import read_json
from tg_nebp.models import MeasurementModel, MotionModel, model_like

__all__ = ['MRCLAMScenario', 'MRCLAM', 'PARTS', 'fitted_scenario',
           'range_part', 'sequence_source', 'MRCLAM_URL']

#: Where the official zip of sequence N is downloaded from.
MRCLAM_URL = ('http://asrl.utias.utoronto.ca/datasets/mrclam/'
              'MRCLAM_Dataset{}.zip')

#: The parts of a sequence that a scenario's windows lie in, all of the
#: span in which every robot has ground truth and odometry or the first or
#: the second half of it (to train a learned correction on one half and
#: test it on the other).
PARTS = ('all', 'first-half', 'second-half')

# mrclam-N and its options: range (range features only), no-odometry,
# landmarks / robots (those links only), first-half / second-half (the
# whole half as one window)
_NAME = re.compile(r'mrclam-([1-9])((?:-[a-z]+)*)\Z')
_NAME_OPTIONS = {
    'range': dict(features=('range', )),
    'no-odometry': dict(odometry=False),
    'landmarks': dict(links='landmarks'),
    'robots': dict(links='robots'),
    'first-half': dict(part='first-half', duration=None),
    'second-half': dict(part='second-half', duration=None),
}
# the models fitted on sequence 6 (fitted_scenario), shipped
_FITTED = 'mrclam-6.json'
_FITTED_FOLDER = 'fitted'
_RANGE_ONLY = {'student-t-range-bearing': 'student-t',
               'range-bearing': 'gaussian'}


@dataclasses.dataclass(frozen=True)
class MRCLAMScenario(RecordedScenarioFields):
    r"""A part of a UTIAS MRCLAM sequence under the test protocol
    (:func:`~tg_nebp.datasets.mrclam_realization`) and the models the
    trackers read: what :class:`MRCLAM` makes realizations of, and what
    :obj:`--scenario mrclam-N` names.

    The realizations are windows of :obj:`duration` seconds in steps of
    :obj:`dt`: the first starts :obj:`start` seconds into the
    :obj:`part`, the next ones every :obj:`stride` seconds, as many as fit
    in it (one without a stride). The part is the span in which all five
    robots have ground truth and odometry (:obj:`"all"`) or its first or
    second half.

    By name (:meth:`load`): :obj:`"mrclam-N"` (:math:`N = 1..9`) is the
    test protocol of sequence :math:`N` with everything it has (ranges,
    bearings, odometry), 600 s from the start, and the models fitted on
    sequence 6 (:func:`fitted_scenario`); options follow the name, each
    after a hyphen: :obj:`range` (the range alone, the fitted likelihood's
    range part), :obj:`no-odometry`, :obj:`landmarks` or :obj:`robots`
    (those links only), :obj:`first-half` or :obj:`second-half` (the
    whole half as one window); for example :obj:`"mrclam-6-range-no-
    odometry"` is range-only tracking. A JSON file of these fields (what
    :obj:`tg-nebp fit` writes) sets any of them.

    Args:
        name (str): Name.
        sequence (int): The sequence, 1 to 9.
        motion (dict or MotionModel): The motion model (its
            configuration), with the odometry as its input.
        measurement (dict or MeasurementModel): The likelihood of the
            links, reading :obj:`features`.
        dt (float, optional): Step, seconds. (default: :obj:`0.5`)
        duration (float, optional): A window's length, seconds;
            :obj:`None` for the whole part. (default: :obj:`600.0`)
        start (float, optional): Where the first window starts, seconds
            into the part. (default: :obj:`0.0`)
        stride (float, optional): Seconds between windows; :obj:`None` for
            one window. (default: :obj:`None`)
        part (str, optional): One of :data:`~tg_nebp.datasets.mrclam_dataset.PARTS`. (default: :obj:`"all"`)
        features (tuple, optional): :obj:`("range", "bearing")` or
            :obj:`("range",)`. (default: both)
        odometry (bool, optional): The odometry as known inputs.
            (default: :obj:`True`)
        links (str, optional): :obj:`"all"`, :obj:`"landmarks"` or
            :obj:`"robots"`. (default: :obj:`"all"`)
        prior_std (float, optional): The prior's position standard
            deviation around the ground truth, metres. (default: :obj:`0.5`)
        heading_std (float, optional): The prior's heading standard
            deviation, radians. (default: :obj:`0.2`)
        description (str, optional): Free text, not part of the
            fingerprint. (default: :obj:`""`)
    """
    name: str
    sequence: int
    motion: Dict[str, Any]
    measurement: Dict[str, Any]
    dt: float = 0.5
    duration: Optional[float] = 600.0
    start: float = 0.0
    stride: Optional[float] = None
    part: str = 'all'
    features: Tuple[str, ...] = ('range', 'bearing')
    odometry: bool = True
    links: str = 'all'
    prior_std: float = 0.5
    heading_std: float = 0.2
    description: str = ''

    def __post_init__(self):
        fix = object.__setattr__  # frozen: normalize once
        for key in ('motion', 'measurement'):
            value = getattr(self, key)
            if isinstance(value, (MotionModel, MeasurementModel)):
                fix(self, key, value.config())
        if isinstance(self.features, (list, tuple)):
            fix(self, 'features', tuple(self.features))
        self._check()

    def _check(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"'name' must be a non-empty string, got "
                             f"{self.name!r}")
        if isinstance(self.sequence, bool) or self.sequence not in range(
                1, 10):
            raise ValueError(f"'sequence' must be one of 1 to 9, got "
                             f"{self.sequence!r}")
        for key in ('dt', 'duration', 'stride', 'prior_std', 'heading_std'):
            value = getattr(self, key)
            if value is None and key in ('duration', 'stride'):
                continue
            if isinstance(value, bool) or not isinstance(
                    value, (int, float)) or not math.isfinite(value) \
                    or value <= 0:
                raise ValueError(f"'{key}' must be a positive number, got "
                                 f"{value!r}")
        if isinstance(self.start, bool) or not isinstance(
                self.start, (int, float)) or not 0 <= self.start < math.inf:
            raise ValueError(f"'start' must be a non-negative number, got "
                             f"{self.start!r}")
        if self.part not in PARTS:
            raise ValueError(f"'part' must be one of {list(PARTS)}, got "
                             f"{self.part!r}")
        if self.features not in (('range', ), ('range', 'bearing')):
            raise ValueError(f"'features' must be ['range'] or ['range', "
                             f"'bearing'], got {self.features!r}")
        if not isinstance(self.odometry, bool):
            raise ValueError(f"'odometry' must be true or false, got "
                             f"{self.odometry!r}")
        if self.links not in LINKS:
            raise ValueError(f"'links' must be one of {list(LINKS)}, got "
                             f"{self.links!r}")
        motion, measurement = self.motion_model, self.measurement_model
        if len(measurement.features) != len(self.features):
            raise ValueError(
                f"'measurement' ({measurement.name}) reads the link features "
                f"{list(measurement.features)}, but 'features' is "
                f"{list(self.features)}")
        if motion.state_dim != 3:
            raise ValueError(f"'motion' ({motion.name}) must be a robot's "
                             f"[x, y, heading] model, with the odometry as "
                             f"its input")

    @classmethod
    def load(cls, name_or_path: Union[str, os.PathLike]
             ) -> 'MRCLAMScenario':
        r"""A scenario by name (:obj:`"mrclam-N"` with options, see the
        class) or from a JSON file of its fields."""
        text = str(name_or_path)
        match = _NAME.match(text)
        if match is not None and not text.endswith('.json'):
            fitted = _shipped()
            changes = dict(name=text, sequence=int(match.group(1)))
            rest = match.group(2)
            set_by: dict = {}  # each field by the option that set it
            while rest:
                token = next((t for t in sorted(_NAME_OPTIONS, key=len,
                                                reverse=True)
                              if rest.startswith('-' + t)
                              and rest[len(t) + 1:len(t) + 2] in ('', '-')),
                             None)
                if token is None:
                    raise ValueError(
                        f"scenario '{text}': unknown option "
                        f"'{rest[1:].split('-')[0]}'; the options of "
                        f"mrclam-N are {sorted(_NAME_OPTIONS)}")
                for field in _NAME_OPTIONS[token]:
                    if set_by.get(field) == token:
                        raise ValueError(f"scenario '{text}' gives the "
                                         f"option '{token}' twice")
                    if field in set_by:
                        # the last would win silently
                        raise ValueError(
                            f"scenario '{text}': the options "
                            f"'{set_by[field]}' and '{token}' contradict "
                            f"each other (both set '{field}'); give one")
                    set_by[field] = token
                changes.update(_NAME_OPTIONS[token])
                rest = rest[len(token) + 1:]
            if changes.get('features') == ('range', ):
                changes['measurement'] = range_part(
                    fitted.measurement_model).config()
            return fitted.replace(**changes)
        path = Path(name_or_path)
        if path.suffix != '.json':
            raise ValueError(f"unknown scenario '{text}'; a real sequence is "
                             f"mrclam-N (N = 1 to 9) with the options "
                             f"{sorted(_NAME_OPTIONS)}, or a .json file")
        if not path.is_file():
            raise ValueError(f"scenario file '{path}' does not exist")
        fields = read_json(path)
        return cls.from_fields(fields, str(path))

    __hash__ = RecordedScenarioFields.__hash__

    @property
    def position_dim(self) -> int:
        return 2

    @property
    def num_steps(self) -> Optional[int]:
        r"""The steps of a window; :obj:`None` before the sequence is read
        when the window is a whole part (:meth:`resolved`)."""
        if self.duration is None:
            return None
        return int(math.floor(self.duration / self.dt + 1e-9))

    def span(self, sequence) -> Tuple[float, float]:
        r"""The part's first and last time in the read :obj:`sequence`
        (:class:`~tg_nebp.datasets.MRCLAMSequence`)."""
        begin, end = sequence.start(), sequence.end()
        middle = 0.5 * (begin + end)
        return {'all': (begin, end), 'first-half': (begin, middle),
                'second-half': (middle, end)}[self.part]

    def resolved(self, sequence) -> 'MRCLAMScenario':
        r"""This scenario with the :obj:`duration` of a whole part filled
        in from the read :obj:`sequence` (itself otherwise)."""
        if self.duration is not None:
            return self
        begin, end = self.span(sequence)
        steps = int(math.floor((end - begin - self.start) / self.dt + 1e-9))
        if steps < 1:
            raise ValueError(f"scenario '{self.name}': the {self.part} part "
                             f"of sequence {self.sequence} holds no step "
                             f"of {self.dt} s after {self.start} s")
        return self.replace(duration=steps * self.dt)

    def window_starts(self, sequence) -> List[float]:
        r"""The start time of every window in the read :obj:`sequence`."""
        begin, end = self.span(sequence)
        length = self.resolved(sequence).num_steps * self.dt
        first = begin + self.start
        if first + length > end + 1e-6:
            raise ValueError(
                f"scenario '{self.name}': a window of {length:g} s from "
                f"{self.start:g} s into the {self.part} part does not fit "
                f"in sequence {self.sequence}'s {end - begin:.1f} s of it")
        if self.stride is None:
            return [first]
        count = int(math.floor((end - first - length) / self.stride
                               + 1e-9)) + 1
        return [first + k * self.stride for k in range(count)]

    def realization(self, sequence, start: float
                    ) -> Tuple[Realization, Dict[str, int]]:
        r"""The window of the read :obj:`sequence` that starts at time
        :obj:`start`, and what was dropped or merged
        (:func:`~tg_nebp.datasets.mrclam_realization`)."""
        resolved = self.resolved(sequence)
        return mrclam_realization(
            sequence, self.dt, resolved.num_steps * self.dt, start,
            self.features, self.odometry, self.links, self.prior_std,
            self.heading_std, self.measurement_model.negative_ranges)


def _check_odometry(data: Realization, sequence, scenario: 'MRCLAMScenario',
                    start: float) -> None:
    # the inputs that the odometry integrates to for each step, against
    # what the motion model represents: one that it does not is refused
    # naming the robot's file and the rows that made it (a corrupted row)
    control = getattr(data, 'control', None)
    if control is None:
        return
    motion = scenario.motion_model
    beyond = ~motion.representable(control)
    if not bool(beyond.any()):
        return
    robot, step = beyond.nonzero()[0].tolist()
    begin = start + step * scenario.dt
    times = sequence.odometry[robot][:, 0]
    first = max(int(np.searchsorted(times, begin, 'right')) - 1, 0)
    last = max(int(np.searchsorted(times, begin + scenario.dt, 'left')) - 1,
               first)
    distance, turn = control[robot, step].tolist()
    raise ValueError(
        f"'Robot{robot + 1}_Odometry.dat': data rows {first + 1} to "
        f"{last + 1} move the robot by {distance:.4g} m and {turn:.4g} rad "
        f"in the step from {begin:.3f} s, beyond the inputs the motion "
        f"model {motion} represents ({motion.input_limit})")


#: Where the reading of a real sequence is reported (what was kept,
#: dropped and merged): the command line prints it on standard error.
LOG = logging.getLogger('tg_nebp.datasets')


def reading_report(what: str, counts: List[Dict[str, int]],
                   links: List[int]) -> str:
    r"""One line on the reading of the windows of a real sequence
    (:obj:`what`): the links kept (:obj:`links`, per window) and the
    measurements dropped or merged (:obj:`counts`, per window, as
    :func:`~tg_nebp.datasets.mrclam_realization` gives them)."""
    total = {key: sum(c[key] for c in counts) for key in
             ('unknown_barcodes', 'repeated', 'outside')}
    plural = 's' * (len(links) != 1)
    return (f"{what}: {sum(links):,} links in {len(links)} window{plural}; "
            f"{total['unknown_barcodes']:,} measurement(s) of barcodes "
            f"that Barcodes.dat does not give a surveyed subject dropped, "
            f"{total['outside']:,} outside the window{plural} left out, "
            f"{total['repeated']:,} repeated within a step merged (the "
            f"latest kept)")


def range_part(model: MeasurementModel) -> MeasurementModel:
    r"""The range-only likelihood of a range-bearing :obj:`model`: the
    registered range model of the same noise family, with the parameters
    they share (:func:`~tg_nebp.models.model_like`); a range-only model
    itself."""
    if len(model.features) == 1:
        return model
    if model.name not in _RANGE_ONLY:
        raise ValueError(f"no range-only likelihood is known for "
                         f"'{model.name}': give 'measurement' in a scenario "
                         f"file")
    return model_like(_RANGE_ONLY[model.name], 'measurement', model)


def sequence_source(root: Union[str, os.PathLike], sequence: int,
                    download: bool = True, log: bool = True) -> Path:
    r"""Where sequence :obj:`sequence` lies in :obj:`root`: its zip
    :obj:`MRCLAM_DatasetN.zip` or, where there is none, its extracted
    folder :obj:`MRCLAM_DatasetN/`; where neither is there, the official
    zip (:data:`~tg_nebp.datasets.mrclam_dataset.MRCLAM_URL`) is downloaded into :obj:`root` first (with
    :obj:`download`; a :class:`ValueError` saying where it looked
    otherwise, or when the download fails, leaving no folder it made)."""
    zipped = Path(root) / f'MRCLAM_Dataset{sequence}.zip'
    folder = Path(root) / f'MRCLAM_Dataset{sequence}'
    if zipped.exists():
        return zipped
    if folder.is_dir():
        return folder
    url = MRCLAM_URL.format(sequence)
    if not download:
        raise ValueError(f"MRCLAM sequence {sequence} is not in '{root}' "
                         f"(neither {zipped.name} nor {folder.name}/); it is "
                         f"at {url}")
    from torch_geometric.data import download_url
    # the folders the download makes, removed again if it fails
    made = [p for p in [Path(root), *Path(root).parents] if not p.exists()]
    try:
        os.makedirs(root, exist_ok=True)
        return Path(download_url(url, str(root), log=log))
    except OSError as e:
        for path in made:  # the deepest first; only what stayed empty
            try:
                path.rmdir()
            except OSError:
                break
        raise ValueError(
            f"MRCLAM sequence {sequence} is not in '{root}' (neither "
            f"{zipped.name} nor {folder.name}/) and could not be "
            f"downloaded from {url}: {e}") from None


def fitted_scenario(source: Union[str, os.PathLike], sequence: int,
                    name: Optional[str] = None,
                    horizon: int = FIT_HORIZON
                    ) -> Tuple[MRCLAMScenario, Dict[str, Any]]:
    r"""The test protocol of :obj:`sequence` (named :obj:`name`,
    :obj:`"mrclam-N"` by default) with the noise models fitted
    (:func:`~tg_nebp.datasets.fit_models`, long-run variances over
    :obj:`horizon` steps) on its test protocol's
    realization, the sequence read from :obj:`source` (its zip or folder),
    and the fit's report: what :obj:`tg-nebp fit` writes and prints (a
    sequence shorter than the protocol's 600 s is fitted on all of it).
    The models of every :obj:`mrclam-N` name are these of sequence 6,
    shipped."""
    sequence_read = read_mrclam(source)
    span = sequence_read.end() - sequence_read.start()
    data, counts = mrclam_realization(sequence_read, duration=min(
        600.0, 0.5 * math.floor(span / 0.5)))
    LOG.info(reading_report(f"MRCLAM sequence {sequence} (the fit's window)",
                            [counts], [data.num_edges]))
    motion, measurement, report = fit_models(data, horizon=horizon)
    scenario = MRCLAMScenario(
        name=name or f'mrclam-{sequence}', sequence=sequence,
        motion=motion, measurement=measurement,
        description=(f'the test protocol of MRCLAM sequence {sequence}, the '
                     f'models fitted on its {report["links"]} links and '
                     f'{report["agent_steps"]} robot-steps of odometry '
                     f'(long-run variances over {horizon} steps)'))
    return scenario, report


def _shipped() -> MRCLAMScenario:
    # the test protocol of sequence 6 and the models fitted on it
    path = resources.files('tg_nebp.datasets') / _FITTED_FOLDER / _FITTED
    return MRCLAMScenario.from_fields(read_json(path), _FITTED)


class MRCLAM(InMemoryDataset):
    r"""The UTIAS Multi-Robot Cooperative Localization and Mapping dataset
    from the `"The UTIAS multi-robot cooperative localization and mapping
    dataset" <https://doi.org/10.1177/0278364911398404>`_ paper (Leung,
    Halpern, Barfoot and Liu, IJRR 2011): five robots with wheel odometry
    and a camera that measures range and bearing to 15 surveyed landmarks
    (the anchors) and to each other, with Vicon ground truth. Each item is
    one window of a sequence as a :class:`~tg_nebp.data.Realization`
    (robots first, then landmarks), under the test protocol of
    :func:`~tg_nebp.datasets.mrclam_realization`.

    The sequence is read from :obj:`root/MRCLAM_DatasetN.zip` or the
    extracted folder :obj:`root/MRCLAM_DatasetN/` (offline); where neither
    is there, the official zip is downloaded into :obj:`root` first.
    Reading a sequence takes seconds; nothing is written but the download.

    Args:
        root (str): The folder that holds the zip or the folder.
        scenario (str or MRCLAMScenario, optional): :obj:`"mrclam-N"` with
            options, a JSON file of an :class:`MRCLAMScenario`, or one.
            (default: :obj:`"mrclam-6"`)
        num_realizations (int, optional): The first windows only;
            :obj:`None` for all of them (more than there are is a
            :class:`ValueError`). (default: :obj:`None`)
        transform (callable, optional): Applied on every access.
            (default: :obj:`None`)
        log (bool, optional): Print while downloading. (default: :obj:`True`)

    Attributes:
        scenario (MRCLAMScenario): The scenario, its window length filled
            in.
        counts (list): Per window, the measurements dropped or merged
            (:obj:`"unknown_barcodes"`, :obj:`"repeated"`,
            :obj:`"outside"`).
        report (str): The links kept and the counts summed, one line
            (logged to :obj:`tg_nebp.datasets` at level INFO, which the
            command line prints). A sequence none of whose measurements
            names another robot or a surveyed landmark is refused when it
            is read; a window without links is read, and reported.

    **STATS** (sequence 6, the test protocol):

    .. list-table::
        :header-rows: 1

        * - #robots
          - #landmarks
          - #steps
          - #links
        * - 5
          - 15
          - 1,200
          - 8,164
    """
    def __init__(self, root: str,
                 scenario: Union[str, MRCLAMScenario] = 'mrclam-6',
                 num_realizations: Optional[int] = None,
                 transform: Optional[Callable] = None, log: bool = True):
        if isinstance(scenario, (str, os.PathLike)):
            scenario = MRCLAMScenario.load(scenario)
        if not isinstance(scenario, MRCLAMScenario):
            raise TypeError(f"'scenario' must be a name, a path or an "
                            f"MRCLAMScenario, got {scenario!r}")
        if num_realizations is not None:
            check_positive_int(num_realizations, 'num_realizations')
        if os.path.exists(root) and not os.path.isdir(root):
            raise ValueError(f"'root' = '{root}' is not a folder")
        self._sequence = scenario.sequence
        super().__init__(str(root), transform, log=log)
        sequence = read_mrclam(sequence_source(self.raw_dir,
                                               scenario.sequence))
        starts = scenario.window_starts(sequence)
        if num_realizations is not None:
            if num_realizations > len(starts):
                raise ValueError(
                    f"scenario '{scenario.name}' has {len(starts)} "
                    f"window{'s' * (len(starts) != 1)} in sequence "
                    f"{scenario.sequence}, not {num_realizations}: ask for "
                    f"at most {len(starts)} realizations (or give the "
                    f"scenario a stride)")
            starts = starts[:num_realizations]
        self.scenario = scenario.resolved(sequence)
        data_list, self.counts = [], []
        for start in starts:
            data, counts = scenario.realization(sequence, start)
            # a negative range was refused by row unless the model takes it
            check_realization(data, scenario.features, negative_ranges=True)
            _check_odometry(data, sequence, scenario, start)
            data_list.append(data)
            self.counts.append(counts)
        self.report = reading_report(
            f"MRCLAM sequence {scenario.sequence} ('{scenario.name}')",
            self.counts, [data.num_edges for data in data_list])
        self.data, self.slices = self.collate(data_list)
        # every command that reads a sequence says what it dropped
        LOG.info(self.report)

    @property
    def raw_dir(self) -> str:
        return self.root

    @property
    def raw_file_names(self) -> List[str]:
        return [f'MRCLAM_Dataset{self._sequence}.zip']

    @property
    def processed_file_names(self) -> List[str]:
        return []  # read in seconds: nothing is cached

    def _download(self):
        # PyG's looks for the zip alone; the extracted folder does too
        self.download()

    def download(self):
        sequence_source(self.raw_dir, self._sequence, log=self.log)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}({len(self)}, scenario='
                f'{self.scenario.name})')
