r"""NEBP trained on a scenario's realizations: behind :obj:`tg-nebp train`.
:func:`train_scenario` generates (or loads) the training and validation
realizations (of one scenario, or a mix of several), builds the NEBP
tracker (particle or Gaussian), trains it with a checkpoint after every
epoch and, optionally, a training log."""
import contextlib
from pathlib import Path
from typing import Callable, List, NamedTuple, Optional, Sequence, Union

import torch

from tg_nebp.data.validation import check_positive_int
from tg_nebp.datasets import MRCLAMScenario, Scenario, load_datasets
from tg_nebp.experiments.evaluate import (REAL_SCENARIO_TYPES,
                                          realizations_of, scenario_of,
                                          tracker_measurement)
from tg_nebp.filters import (NEBP, FixedLagGaussianNEBP, GaussianNEBP,
                             Tracker)
from tg_nebp.training import (BASES, checkpoint_history, gaussian_step_loss,
                              gaussian_window_loss, step_loss,
                              steps_per_epoch, train)
from tg_nebp.training_log import TrainingLog
from tg_nebp.utils import check_device, process_group

__all__ = ['train_scenario', 'TrainedScenario', 'MixedRealizations']

# the options of particle NEBP alone, at their defaults, and Gaussian
# NEBP's embedding size
_PARTICLE_OPTIONS = dict(variant='paper', particles=None, samples=1,
                         regularize=None, ess_threshold=None, compile=False)
_GAUSSIAN_HIDDEN_DIM = 32


class MixedRealizations(torch.utils.data.Dataset):
    r"""The realizations of several datasets (of scenarios with the same
    motion model and position dimension) as one, each with the link
    features :obj:`features` only (the leading columns the tracker's
    measurement model reads), so that realizations of different scenarios
    (an NLOS one carries its true NLOS flags) batch together."""
    def __init__(self, datasets: Sequence, features: int):
        self.datasets = list(datasets)
        self.features = features
        self.index = [(d, i) for d, dataset in enumerate(self.datasets)
                      for i in range(len(dataset))]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, index: int):
        which, item = self.index[index]
        data = self.datasets[which][item].clone()
        data.edge_attr = data.edge_attr[:, :self.features]
        return data


def _mixed(datasets: List, features: int):
    # one dataset as it is; several mixed, after checking what they share
    first = datasets[0].scenario
    for dataset in datasets:
        width = dataset[0].edge_attr.size(1) if len(dataset) else features
        if width < features:
            raise ValueError(f"the realizations of {dataset.scenario.name} "
                             f"hold {width} link features, but the "
                             f"tracker's likelihood reads {features}")
    for dataset in datasets[1:]:
        other = dataset.scenario
        if other.motion_model != first.motion_model:
            raise ValueError(f"the scenarios of a mix must share the motion "
                             f"model: {first.name} has {first.motion_model}, "
                             f"{other.name} {other.motion_model}")
        if other.num_steps != first.num_steps:
            raise ValueError(f"the scenarios of a mix must share the number "
                             f"of steps (a batch has one): {first.name} has "
                             f"{first.num_steps}, {other.name} "
                             f"{other.num_steps}")
        if other.position_dim != first.position_dim:
            raise ValueError(f"the scenarios of a mix must share the "
                             f"position dimension: {first.name} is "
                             f"{first.position_dim}-D, {other.name} "
                             f"{other.position_dim}-D")
    if len(datasets) == 1:
        return datasets[0]
    return MixedRealizations(datasets, features)


class TrainedScenario(NamedTuple):
    r"""What :func:`train_scenario` returns: the trained :obj:`model`, the
    :obj:`history` (one dict per epoch), the :obj:`checkpoint` path, and
    the :obj:`log` it wrote (:obj:`None` without a log folder, and on ranks
    other than 0)."""
    model: Tracker
    history: List[dict]
    checkpoint: Path
    log: Optional[TrainingLog]


def train_scenario(scenario: Union[str, Scenario, Sequence], out: str,
                   variant: str = 'paper', particles: Optional[int] = None,
                   iterations: Optional[int] = None,
                   realizations: Optional[int] = None,
                   val_realizations: Optional[int] = None,
                   epochs: int = 10,
                   batch_size: int = 2, lr: float = 1e-4, seed: int = 1,
                   measurement: Optional[str] = None,
                   samples: Union[int, str] = 1,
                   regularize: Union[float, str, None] = None,
                   ess_threshold: Optional[float] = None,
                   resume: bool = False, log_dir: Optional[str] = None,
                   root: str = 'datasets', device: str = 'cpu',
                   compile: bool = False,
                   progress_factory: Optional[Callable] = None,
                   description: str = 'train', base: str = 'particle',
                   hidden_dim: int = _GAUSSIAN_HIDDEN_DIM,
                   val_scenario: Union[str, Scenario, Sequence,
                                       None] = None,
                   lag: Optional[int] = None) -> TrainedScenario:
    r"""Trains NEBP on :obj:`realizations` realizations of
    :obj:`scenario` drawn from :obj:`seed` (100 by default), validated on
    :obj:`val_realizations` (10 by default) drawn from :obj:`seed + 1` of
    the same scenario or of :obj:`val_scenario` (one or a list), and
    writes
    :obj:`out/nebp.pt` after every epoch (:func:`~tg_nebp.training.train`);
    :obj:`resume` continues from it. :obj:`log_dir` adds a
    :class:`~tg_nebp.training_log.TrainingLog` (rank 0 writes it under
    :obj:`torchrun`). The GNN's initial weights are drawn from
    :obj:`seed`.

    With :obj:`base="particle"` the tracker is
    :class:`~tg_nebp.filters.NEBP` (:obj:`variant` :obj:`'paper'` or
    :obj:`'equivariant'`, :obj:`particles` :math:`K`, default 1,000;
    :obj:`iterations` default
    1), trained on the paper's squared error; with :obj:`base="gaussian"`
    it is :class:`~tg_nebp.filters.GaussianNEBP` (embeddings of
    :obj:`hidden_dim`; :obj:`iterations` default 20), trained on
    :func:`~tg_nebp.training.gaussian_step_loss`, and the particle options
    are refused; with a :obj:`lag` it is the correction inside the window
    of fixed-lag Gaussian BP
    (:class:`~tg_nebp.filters.FixedLagGaussianNEBP`, the window's
    recommended inflation under the learned ones), trained on
    :func:`~tg_nebp.training.gaussian_window_loss`. :obj:`scenario` may
    be a list: the realizations of every scenario (:obj:`realizations`
    and :obj:`val_realizations` of each) are mixed
    (:class:`MixedRealizations`), and the tracker takes the first's
    models.

    A real sequence (:class:`~tg_nebp.datasets.MRCLAMScenario`) gives its
    windows (all of them by default), the same ones for every seed: its
    validation windows come from :obj:`val_scenario` (other windows of
    the sequence, or another), which it needs.

    Args:
        progress_factory (callable, optional): :obj:`(total, description)`
            to a context manager with :obj:`update(n)` and
            :obj:`set_postfix(**values)`, called after every optimizer
            step (a progress bar); a resumed run starts it at the finished
            epochs' steps. (default: :obj:`None`)
        description (str, optional): The progress bar's description.
            (default: :obj:`"train"`)

    Returns:
        A :class:`TrainedScenario`.
    """
    check_device(device)  # before any data is made
    if base not in BASES:
        raise ValueError(f"'base' must be one of {', '.join(BASES)}, got "
                         f"{base!r}")
    given = dict(variant=variant, particles=particles, samples=samples,
                 regularize=regularize, ess_threshold=ess_threshold,
                 compile=compile)
    for name, value in given.items():
        if base == 'gaussian' and value != _PARTICLE_OPTIONS[name]:
            raise ValueError(f"'{name}' (--{name.replace('_', '-')}) is "
                             f"for the particle base, not the gaussian one")
    for name, given in (('hidden_dim', hidden_dim != _GAUSSIAN_HIDDEN_DIM),
                        ('lag', lag is not None)):
        if base == 'particle' and given:
            raise ValueError(f"'{name}' (--{name.replace('_', '-')}) is for "
                             f"the gaussian base, not the particle one")
    for name, value in (('particles', particles), ('iterations', iterations),
                        ('hidden_dim', hidden_dim), ('lag', lag)):
        if value is not None:
            check_positive_int(value, name)
    scenarios = ([scenario_of(s) for s in scenario]
                 if isinstance(scenario, (list, tuple)) else
                 [scenario_of(scenario)])
    if not scenarios:
        raise ValueError("'scenario' is an empty list")
    if val_scenario is None:
        real = next((s for s in scenarios
                     if isinstance(s, REAL_SCENARIO_TYPES)), None)
        if real is not None:
            raise ValueError(
                f"the windows of the real sequence '{real.name}' are the "
                f"same for every seed: give validation windows elsewhere "
                f"('val_scenario', --val-scenario)")
        val_scenarios = scenarios
    else:
        val_scenarios = ([scenario_of(s) for s in val_scenario]
                         if isinstance(val_scenario, (list, tuple)) else
                         [scenario_of(val_scenario)])
    rank = process_group()[1]
    datasets = load_datasets(
        root, *[(s, realizations_of(s, realizations, 100), seed)
                for s in scenarios],
        *[(s, realizations_of(s, val_realizations, 10), seed + 1)
          for s in val_scenarios])
    first = datasets[0].scenario
    inside = tracker_measurement(first, measurement)
    features = len(inside.features)
    train_set = _mixed(datasets[:len(scenarios)], features)
    val_set = _mixed(datasets[len(scenarios):], features)
    scenario = first
    torch.manual_seed(seed)  # the GNN's initial weights
    if base == 'gaussian' and lag is not None:
        model = FixedLagGaussianNEBP.recommended(
            lag=lag, motion=first.motion_model, measurement=inside,
            hidden_dim=hidden_dim, position_dim=first.position_dim,
            **({} if iterations is None else
               dict(num_iterations=iterations)))
        loss = gaussian_window_loss
    elif base == 'gaussian':
        model = GaussianNEBP(20 if iterations is None else iterations,
                             motion=first.motion_model,
                             measurement=inside, hidden_dim=hidden_dim,
                             position_dim=first.position_dim)
        loss = gaussian_step_loss
    else:
        model = NEBP(1000 if particles is None else particles,
                     1 if iterations is None else iterations,
                     motion=first.motion_model, measurement=inside,
                     compile=compile, num_samples=samples,
                     regularize=regularize, ess_threshold=ess_threshold,
                     variant=variant, position_dim=first.position_dim)
        loss = step_loss
    checkpoint = Path(out) / 'nebp.pt'
    steps = steps_per_epoch(len(train_set), batch_size, scenario.num_steps)
    done = (checkpoint_history(checkpoint)
            if resume and checkpoint.exists() else [])
    log = (TrainingLog(log_dir, steps, done)
           if log_dir is not None and rank == 0 else None)
    bar = (progress_factory(steps * epochs, description)
           if progress_factory is not None else None)
    with (bar if bar is not None else contextlib.nullcontext()), \
            (log or contextlib.nullcontext()):

        def progress(info):
            if bar is not None:
                bar.set_postfix(epoch=info['epoch'],
                                loss=f"{info['loss']:.4f}")
                bar.update(1)
            if log is not None:
                log.step(info)

        if bar is not None:
            bar.update(min(len(done), epochs) * steps)
        history = train(model, train_set, val_set, epochs, batch_size, lr,
                        seed, device, checkpoint, resume, progress,
                        loss=loss,
                        on_epoch=log.epoch if log is not None else None)
    return TrainedScenario(model, history, checkpoint, log)
