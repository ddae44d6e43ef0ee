import dataclasses
import hashlib
import json
import math
import numbers
import re
from importlib import resources
from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Union

import torch

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import is_integer, magnitude_limit
from tg_nebp.io import read_json, write_text
from tg_nebp.utils import free_memory_bytes
from tg_nebp.models import (ConstantVelocityDrag, GaussianRange,
                            MeasurementModel, Model, MotionModel,
                            model_from_config, resolve_models, wrap_angle)

__all__ = ['Scenario', 'RecordedScenarioFields', 'ScenarioModels']

_FILE_NAME = re.compile(r'[A-Za-z0-9_+-][A-Za-z0-9_.+-]*\Z')


def scenario_from_fields(cls, fields: Any, where: str):
    r"""The scenario dataclass :obj:`cls` built from the fields of a JSON
    object; a value that is not an object, an unknown or missing field and
    a field the class refuses are each a :class:`ValueError` that names
    :obj:`where` (the file) and the field."""
    if not isinstance(fields, dict):
        raise ValueError(f"scenario '{where}' must be a JSON object of "
                         f"fields")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(fields) - known
    if unknown:
        raise ValueError(f"scenario '{where}' has unknown fields "
                         f"{sorted(unknown)}")
    missing = sorted(f.name for f in dataclasses.fields(cls)
                     if f.name not in fields
                     and f.default is dataclasses.MISSING
                     and f.default_factory is dataclasses.MISSING)
    if missing:
        raise ValueError(f"scenario '{where}' lacks the fields {missing}")
    try:
        return cls(**fields)
    except (TypeError, ValueError) as e:
        raise ValueError(f"scenario '{where}': {e}") from None


class ScenarioModels:
    r"""The models of a scenario (simulated or of real data) built from its
    :obj:`motion` and :obj:`measurement` configurations."""

    @property
    def motion_model(self) -> MotionModel:
        r"""The scenario's motion model, built from :obj:`motion`."""
        return model_from_config(self.motion, 'motion')

    @property
    def measurement_model(self) -> MeasurementModel:
        r"""The scenario's measurement model, built from
        :obj:`measurement`."""
        return model_from_config(self.measurement, 'measurement')


class RecordedScenarioFields(ScenarioModels):
    r"""What the scenarios of real data (:class:`~tg_nebp.datasets.MRCLAMScenario`,
    :class:`~tg_nebp.datasets.RecordingScenario`, frozen dataclasses of
    JSON fields) share: their JSON object, file, copies and fingerprint. A
    subclass keeps ``__hash__ = RecordedScenarioFields.__hash__`` in its own
    body (a frozen dataclass would otherwise hash its dict fields)."""

    @classmethod
    def from_fields(cls, fields: Any, where: str):
        r"""A scenario from the fields of a JSON object, every problem a
        :class:`ValueError` that names :obj:`where` and the field, as
        :meth:`Scenario.from_fields
        <tg_nebp.datasets.Scenario.from_fields>`."""
        return scenario_from_fields(cls, fields, where)

    def to_fields(self) -> dict:
        r"""The fields as a JSON object (:meth:`from_fields` reads it;
        tuples as lists)."""
        return {key: list(value) if isinstance(value, tuple) else value
                for key, value in dataclasses.asdict(self).items()}

    def save(self, path: Union[str, Path]) -> None:
        r"""Writes the fields to the JSON file :obj:`path` (written whole
        or not at all)."""
        write_text(path, json.dumps(self.to_fields(), indent=2) + '\n')

    def replace(self, **changes):
        r"""A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def __hash__(self) -> int:  # the model configurations are dicts
        return hash(self.fingerprint())

    def fingerprint(self) -> str:
        r"""A short hash of every field but the description."""
        fields = self.to_fields()
        del fields['description']
        blob = json.dumps(fields, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:10]


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_sequence(value) -> bool:
    return isinstance(value, (list, tuple))


@dataclasses.dataclass(frozen=True)
class Scenario(ScenarioModels):
    r"""The definition of a cooperative-localization network, from which
    :meth:`~tg_nebp.datasets.Scenario.generate` draws realizations. The
    paper's networks are JSON files in the repository's top-level
    :obj:`datasets/` folder (:obj:`"paper_train"`: 25 agents, 5 anchors;
    :obj:`"paper_test"`: 100 agents, 13 anchors), loaded with
    :meth:`load`.

    A scenario's dimension :math:`D` (2 or 3) follows its anchors: anchor
    positions of three coordinates make a 3-D scenario, whose states are
    :math:`[\mathbf{p}, \mathbf{v}]` of 6 entries.

    Args:
        name (str): Name (part of the processed file name).
        num_agents (int): Mobile agents :math:`I`.
        anchor_positions (tuple): Anchor positions :math:`(A, D)` in metres.
        agent_start_low (float or tuple): Agents start uniformly in the box
            :math:`[\mathrm{low}, \mathrm{high}]` (a number for every axis
            alike, or one per axis).
        agent_start_high (float or tuple): See :obj:`agent_start_low`.
        num_steps (int, optional): Time steps :math:`T`. (default: :obj:`50`)
        sigma_v0 (float, optional): Std of the initial velocity.
            (default: :obj:`0.1`)
        motion (dict or MotionModel, optional): The motion model, as a
            configuration :obj:`{"name": ..., "params": {...}}` or a model
            (stored as its configuration). (default: the paper's
            :class:`~tg_nebp.models.ConstantVelocityDrag`)
        measurement (dict or MeasurementModel, optional): The measurement
            model that draws the graph and the link features.
            (default: the paper's :class:`~tg_nebp.models.GaussianRange`)
        prior_var (tuple, optional): Diagonal of the prior covariance
            :math:`\boldsymbol{\Sigma}_0`, one entry per state entry
            (:math:`2D` for :math:`[\mathbf{p}, \mathbf{v}]`: positions,
            then velocities; 3 for a robot's :math:`[x, y, \theta]`).
            (default: :obj:`(10.0, 10.0, 0.01, 0.01)`)
        drive (dict, optional): For a motion model that takes known inputs
            (:class:`~tg_nebp.models.UnicycleOdometry`), how the robots are
            driven: every agent keeps a forward distance per step drawn
            uniformly in :obj:`[speed_low, speed_high]` metres, and turns
            by a smooth random amount, an autoregressive sequence of
            standard deviation :obj:`turn_sigma` radians per step and
            correlation :obj:`turn_correlation` between steps; a robot
            outside the start box turns back toward its centre by at most
            :obj:`turn_back` radians per step. The motion model's
            :meth:`~tg_nebp.models.MotionModel.measure` turns the true
            inputs into the recorded odometry (:obj:`control`). Headings
            start uniform; :obj:`sigma_v0` is unused.
            (default: :obj:`None`, for a model without inputs)
        description (str, optional): Free text, not part of the
            fingerprint. (default: :obj:`""`)
    """
    name: str
    num_agents: int
    anchor_positions: Tuple[Tuple[float, ...], ...]
    agent_start_low: Union[float, Tuple[float, ...]]
    agent_start_high: Union[float, Tuple[float, ...]]
    num_steps: int = 50
    sigma_v0: float = 0.1
    motion: Dict[str, Any] = dataclasses.field(
        default_factory=lambda: ConstantVelocityDrag().config())
    measurement: Dict[str, Any] = dataclasses.field(
        default_factory=lambda: GaussianRange().config())
    prior_var: Tuple[float, ...] = (10.0, 10.0, 0.01, 0.01)
    drive: Optional[Dict[str, float]] = None
    description: str = ''

    def __post_init__(self):
        self._check_types()
        fix = object.__setattr__  # frozen: normalize lists to tuples once
        fix(self, 'anchor_positions',
            tuple(tuple(float(c) for c in p) for p in self.anchor_positions))
        fix(self, 'prior_var', tuple(float(v) for v in self.prior_var))
        for key in ('agent_start_low', 'agent_start_high'):
            value = getattr(self, key)
            fix(self, key, tuple(float(v) for v in value)
                if _is_sequence(value) else float(value))
        # a model is stored as its configuration; building it checks it
        for role in ('motion', 'measurement'):
            value = getattr(self, role)
            if isinstance(value, Model):
                value = value.config()
            fix(self, role, model_from_config(value, role).config())
        for key in ('num_agents', 'num_steps'):
            if int(getattr(self, key)) < 1:
                raise ValueError(f"'{key}' must be at least 1, got "
                                 f"{getattr(self, key)}")
        dim = self.position_dim
        if dim not in (2, 3) or any(len(p) != dim
                                    for p in self.anchor_positions):
            raise ValueError("'anchor_positions' must be a list of [x, y] "
                             "or of [x, y, z], every anchor alike")
        low, high = self.start_box()
        if not bool((low < high).all()):
            raise ValueError(f"'agent_start_low' ({self.agent_start_low}) "
                             f"must be below 'agent_start_high' "
                             f"({self.agent_start_high}) on every axis")
        size = self.state_size
        if len(self.prior_var) != size or any(
                not (math.isfinite(v) and v > 0) for v in self.prior_var):
            raise ValueError(f"'prior_var' must hold {size} positive "
                             f"variances (one per state entry: {dim}-D "
                             f"positions first), got {self.prior_var}")
        self._check_drive()
        if not self.sigma_v0 >= 0:
            raise ValueError(f"'sigma_v0' must be non-negative, got "
                             f"{self.sigma_v0}")

    #: The keys of :obj:`drive`.
    DRIVE_KEYS = ('speed_low', 'speed_high', 'turn_sigma',
                  'turn_correlation', 'turn_back')

    def _check_drive(self):
        takes_inputs = self.motion_model.control_dim > 0
        if self.drive is None:
            if takes_inputs:
                raise ValueError(f"the motion model {self.motion_model} "
                                 f"takes known inputs: the scenario needs a "
                                 f"'drive' {{{', '.join(self.DRIVE_KEYS)}}}")
            return
        if not takes_inputs:
            raise ValueError(f"'drive' is for a motion model that takes "
                             f"known inputs; {self.motion_model} takes none")
        if not isinstance(self.drive, dict) or \
                set(self.drive) != set(self.DRIVE_KEYS) or not all(
                    _is_real(v) and math.isfinite(v) and v >= 0
                    for v in self.drive.values()):
            raise ValueError(f"'drive' must map {list(self.DRIVE_KEYS)} to "
                             f"non-negative numbers, got {self.drive!r}")
        if not (self.drive['speed_low'] <= self.drive['speed_high']
                and self.drive['turn_correlation'] < 1):
            raise ValueError(f"'drive' needs speed_low <= speed_high and "
                             f"turn_correlation < 1, got {self.drive!r}")

    def _check_types(self):
        # JSON gives any type: a wrong one must name its field, not fail
        # deep inside the generator
        if not isinstance(self.name, str):
            raise TypeError(f"'name' must be a string, got {self.name!r}")
        if not _FILE_NAME.match(self.name):
            raise ValueError(f"'name' must be a plain file name (letters, "
                             f"digits, '_', '-', '.', '+'; not starting "
                             f"with '.'), got {self.name!r}")
        if not isinstance(self.description, str):
            raise TypeError(f"'description' must be a string, got "
                            f"{self.description!r}")
        for key in ('agent_start_low', 'agent_start_high'):
            value = getattr(self, key)
            values = value if _is_sequence(value) else [value]
            if not values or not all(_is_real(v) for v in values):
                raise TypeError(f"'{key}' must be a number or a list of one "
                                f"number per axis, got {value!r}")
            if not all(math.isfinite(v) for v in values):
                raise ValueError(f"'{key}' must be finite, got {value}")
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.type is int and not is_integer(value):
                raise TypeError(f"'{field.name}' must be an integer, got "
                                f"{value!r}")
            if field.type is float and not _is_real(value):
                raise TypeError(f"'{field.name}' must be a number, got "
                                f"{value!r}")
            if field.type is float and not math.isfinite(value):
                raise ValueError(f"'{field.name}' must be finite, got "
                                 f"{value}")
        if not _is_sequence(self.anchor_positions) or not all(
                _is_sequence(p) and all(_is_real(c) for c in p)
                for p in self.anchor_positions):
            raise TypeError(f"'anchor_positions' must be a list of [x, y] or "
                            f"[x, y, z] coordinates, got "
                            f"{self.anchor_positions!r}")
        if not all(math.isfinite(c) for p in self.anchor_positions
                   for c in p):
            raise ValueError(f"'anchor_positions' must be finite, got "
                             f"{self.anchor_positions!r}")
        if not _is_sequence(self.prior_var) or not all(
                _is_real(v) for v in self.prior_var):
            raise TypeError(f"'prior_var' must be a list of numbers, got "
                            f"{self.prior_var!r}")

    @classmethod
    def load(cls, name_or_path: Union[str, Path]) -> 'Scenario':
        r"""Loads a scenario by name (:obj:`"paper_train"`,
        :obj:`"paper_test"`) or from a JSON file."""
        path = Path(name_or_path)
        if path.suffix != '.json':
            folder = resources.files('tg_nebp.datasets') / 'scenarios'
            path = folder / f'{name_or_path}.json'
            if not path.is_file():
                known = sorted(p.name[:-5] for p in folder.iterdir()
                               if p.name.endswith('.json'))
                raise ValueError(f"unknown scenario '{name_or_path}'; known: "
                                 f"{known} or a path to a .json file")
        elif not path.is_file():
            raise ValueError(f"scenario file '{path}' does not exist")
        return cls.from_fields(read_json(path), str(path))

    @classmethod
    def from_fields(cls, fields: Any, where: str) -> 'Scenario':
        r"""A scenario from the fields of a JSON object; a value that is
        not an object, an unknown or missing field and a field the class
        refuses are each a :class:`ValueError` that names :obj:`where`
        (the file) and the field."""
        return scenario_from_fields(cls, fields, where)

    def replace(self, **changes) -> 'Scenario':
        r"""A copy with some parameters changed."""
        return dataclasses.replace(self, **changes)

    def grown(self, num_agents: int) -> 'Scenario':
        r"""This network scaled to :obj:`num_agents` agents at the same
        density of agents and anchors: with :math:`s =
        \sqrt{\mathrm{num\_agents} / I}`, the agents' start square scales by
        :math:`s` and the anchor layout is tiled over the grown area, taken
        as :math:`[0, \mathrm{low} + \mathrm{high}]^2` (the agents' square
        centred in it, as in both paper networks). For benchmarks of large
        networks: :obj:`grown(10_000)` of :obj:`"paper_test"` spans
        :math:`[0, 1000]^2` with 1,300 anchors. A 3-D network grows on the
        horizontal plane (x, y); its heights stay."""
        if int(num_agents) < 1:
            raise ValueError(f"'num_agents' must be at least 1, got "
                             f"{num_agents}")
        scale = math.sqrt(num_agents / self.num_agents)
        low, high = self.start_box()
        side_x, side_y = (low + high).tolist()[:2]
        tiles = math.ceil(scale - 1e-9)
        anchors = tuple(
            (p[0] + a * side_x, p[1] + b * side_y, *p[2:])
            for a in range(tiles) for b in range(tiles)
            for p in self.anchor_positions
            if p[0] + a * side_x <= side_x * scale
            and p[1] + b * side_y <= side_y * scale)

        def grow(value):
            if not _is_sequence(value):
                return value * scale
            return tuple(v * scale if axis < 2 else v
                         for axis, v in enumerate(value))

        return self.replace(
            name=f'{self.name}-{num_agents}agents', num_agents=num_agents,
            anchor_positions=anchors,
            agent_start_low=grow(self.agent_start_low),
            agent_start_high=grow(self.agent_start_high),
            description=f'{self.name} grown to {num_agents} agents')

    def __hash__(self) -> int:  # the model configurations are dicts
        return hash(self.fingerprint())

    def fingerprint(self) -> str:
        r"""A short hash of every generation parameter."""
        params = dataclasses.asdict(self)
        del params['description']
        if params['drive'] is None:  # the fingerprints from before drives
            del params['drive']
        blob = json.dumps(params, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:10]

    @property
    def num_anchors(self) -> int:
        return len(self.anchor_positions)

    @property
    def position_dim(self) -> int:
        r"""The dimension :math:`D` of the positions: the anchors'
        coordinates (a per-axis start box without anchors; 2 otherwise)."""
        if self.anchor_positions:
            return len(self.anchor_positions[0])
        for value in (self.agent_start_low, self.agent_start_high):
            if _is_sequence(value):
                return len(value)
        return 2

    def start_box(self) -> Tuple[torch.Tensor, torch.Tensor]:
        r"""The agents' start box, its lower and upper corners :math:`(D)`
        (float64)."""
        dim = self.position_dim
        corners = []
        for value in (self.agent_start_low, self.agent_start_high):
            corner = torch.tensor(value if _is_sequence(value) else
                                  [value] * dim, dtype=torch.float64)
            if corner.numel() != dim:
                raise ValueError(f"'agent_start_low' and 'agent_start_high' "
                                 f"need one value per axis ({dim}), got "
                                 f"{value!r}")
            corners.append(corner)
        return corners[0], corners[1]

    @property
    def state_size(self) -> int:
        r"""The size :math:`S` of a state: the motion model's where it
        declares one (a robot's 3), else :math:`2D`."""
        return self.motion_model.state_dim or 2 * self.position_dim

    def realization_bytes(self) -> int:
        r"""A lower estimate of the memory one realization takes while it is
        generated: the true states of every node and step in float64 (the
        simulation) and float32 (what is stored), the prior, and one link
        per agent and step (a network within range has more)."""
        nodes, steps = self.num_agents + self.num_anchors, self.num_steps
        size = self.state_size
        states = nodes * steps * size * (8 + 4)
        prior = nodes * (size + size * size) * (8 + 4)
        links = self.num_agents * steps * (2 * 8 + 4 + 8)
        return states + prior + links

    def check_memory(self, free: Optional[int] = None) -> None:
        r"""Refuses, with a :class:`ValueError` naming the sizes, a scenario
        whose realization (:meth:`realization_bytes`) does not fit in the
        free memory (or :obj:`free` bytes), before any work starts."""
        needed = self.realization_bytes()
        free = free_memory_bytes('cpu') if free is None else free
        if needed > free:
            raise ValueError(
                f"scenario '{self.name}': one realization of {self.num_agents}"
                f" agents over {self.num_steps} steps needs at least "
                f"{needed / 2**30:.3g} GiB, but {free / 2**30:.3g} GiB are "
                f"free: lower 'num_agents' or 'num_steps'")

    def generate(self, generator: Optional[torch.Generator] = None
                 ) -> Realization:
        r"""Draws one realization (agents first, then anchors): true tracks,
        range measurements within :obj:`max_range` at every time step, and
        the prior :math:`\boldsymbol{\mu}_{i,0} \sim
        \mathcal{N}(\mathbf{x}_{i,0}, \boldsymbol{\Sigma}_0)`. Simulated in
        float64 on the CPU, stored in float32."""
        self.check_memory()
        f64 = dict(dtype=torch.float64, generator=generator)
        num_agents, num_anchors = self.num_agents, self.num_anchors
        motion, measurement = resolve_models(self.motion_model,
                                             self.measurement_model)
        dim = self.position_dim
        low, high = self.start_box()

        agent_pos = low + (high - low) * torch.rand(num_agents, dim, **f64)
        anchors = torch.tensor(self.anchor_positions,
                               dtype=torch.float64).view(-1, dim)
        if self.drive is None:  # [p, v]
            agent_rest = self.sigma_v0 * torch.randn(num_agents, dim, **f64)
            anchor_rest = torch.zeros_like(anchors)
        else:  # a robot's heading (a landmark's is 0 and never read)
            agent_rest = math.pi - 2 * math.pi * torch.rand(num_agents, 1,
                                                            **f64)
            anchor_rest = anchors.new_zeros(num_anchors,
                                            self.state_size - dim)
        initial = torch.cat([torch.cat([agent_pos, agent_rest], dim=1),
                             torch.cat([anchors, anchor_rest], dim=1)])
        anchor = torch.arange(num_agents + num_anchors) >= num_agents

        prior_std = torch.tensor(self.prior_var, dtype=torch.float64).sqrt()
        prior_mean = initial + prior_std * torch.randn(initial.shape, **f64)
        prior_mean[anchor] = initial[anchor]
        prior_cov = torch.diag_embed(prior_std.square().expand_as(initial))
        prior_cov[anchor] = 0.0
        limit = magnitude_limit(torch.float32)
        if not bool((initial.abs() <= limit).all() and
                    (prior_mean.abs() <= limit).all()):
            raise ValueError(f"scenario '{self.name}': 'sigma_v0' "
                             f"({self.sigma_v0}) or 'prior_var' "
                             f"({self.prior_var}) draw initial states beyond "
                             f"{limit:.2g}, which float32 cannot hold")

        # per-link state over the realization (e.g. NLOS pairs); models
        # without one draw nothing
        links = measurement.sample_links(num_agents + num_anchors, generator)
        states, edge_index, edge_attr, edge_time = [], [], [], []
        layout = motion.layout(self.state_size)
        driver = None if self.drive is None else _Driver(
            self.drive, low, high, num_agents, generator)
        controls = []
        state = initial
        for t in range(self.num_steps):
            if t > 0:
                links = measurement.step_links(links, generator)
            if driver is None:
                moved = motion.sample(state, generator=generator)
            else:  # driven by the true inputs, the odometry recorded
                true = driver.inputs(state[:num_agents])
                moved = torch.cat([motion.mean(state[:num_agents],
                                               control=true),
                                   state[num_agents:]])
                controls.append(torch.cat([
                    motion.measure(true, generator),
                    true.new_full((num_anchors, true.size(1)), math.nan)]))
            state = torch.where(anchor.view(-1, 1), state, moved)
            # the model's parameters are to blame, not the data checks later
            if not bool((state.abs() <= limit).all()):
                raise ValueError(f"scenario '{self.name}': the motion model "
                                 f"{motion} drives the states beyond "
                                 f"{limit:.2g} by step {t + 1}; check its "
                                 f"parameters and 'sigma_v0'")
            edges = measurement.connect_states(state, receiver=~anchor)
            # the true angles stored wrapped (the simulation goes on in
            # the lift: nothing else changes)
            states.append(layout.wrap(state))
            edge_index.append(edges)
            edge_attr.append(measurement.sample_features(
                state[edges[0]], state[edges[1]], links, edges, generator))
            edge_time.append(torch.full((edges.size(1), ), t))

        extra = {}
        if driver is not None:
            extra['control'] = torch.stack(controls, dim=1).float()
        size = self.state_size
        if motion.layout(size).position_dim != size // 2:
            extra['position_dim'] = dim
        return Realization(
            **extra,
            states=torch.stack(states, dim=1).float(),
            edge_index=torch.cat(edge_index, dim=1),
            edge_attr=torch.cat(edge_attr).float().view(
                -1, len(measurement.generated_features)),
            edge_time=torch.cat(edge_time),
            anchor=anchor,
            prior_mean=prior_mean.float(),
            prior_cov=prior_cov.float(),
            num_steps=self.num_steps,
            num_nodes=num_agents + num_anchors,
        )


class _Driver:
    # the true inputs of driven robots (Scenario.drive): a speed per
    # agent, an autoregressive turn, and a turn back toward the start box's
    # centre for a robot outside the box
    def __init__(self, drive: Dict[str, float], low: torch.Tensor,
                 high: torch.Tensor, num_agents: int,
                 generator: Optional[torch.Generator]):
        self.drive, self.generator = drive, generator
        self.low, self.high = low, high
        f64 = dict(dtype=torch.float64, generator=generator)
        self.speed = drive['speed_low'] + (
            drive['speed_high'] - drive['speed_low']) * torch.rand(
                num_agents, **f64)
        self.turn = drive['turn_sigma'] * torch.randn(num_agents, **f64)

    def inputs(self, states: torch.Tensor) -> torch.Tensor:
        drive = self.drive
        rho = drive['turn_correlation']
        self.turn = rho * self.turn + math.sqrt(1 - rho**2) * \
            drive['turn_sigma'] * torch.randn(
                self.turn.shape, dtype=torch.float64,
                generator=self.generator)
        pos = states[:, :2]
        outside = ((pos < self.low[:2]) | (pos > self.high[:2])).any(-1)
        to_centre = 0.5 * (self.low[:2] + self.high[:2]) - pos
        back = wrap_angle(torch.atan2(to_centre[:, 1], to_centre[:, 0]) -
                          states[:, 2]).clamp(-drive['turn_back'],
                                              drive['turn_back'])
        turn = torch.where(outside, back, self.turn)
        return torch.stack([self.speed, turn], -1)

