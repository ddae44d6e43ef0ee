r"""NEBP trained on a scenario's realizations: behind :obj:`tg-nebp train`.
:func:`train_scenario` generates (or loads) the training and validation
realizations, builds the NEBP tracker, trains it with a checkpoint after
every epoch and, optionally, a training log."""
import contextlib
from pathlib import Path
from typing import Callable, List, NamedTuple, Optional, Union

import torch

from tg_nebp.datasets import Scenario, load_datasets
from tg_nebp.experiments.evaluate import tracker_measurement
from tg_nebp.filters import NEBP
from tg_nebp.training import checkpoint_history, steps_per_epoch, train
from tg_nebp.training_log import TrainingLog
from tg_nebp.utils import check_device, process_group

__all__ = ['train_scenario', 'TrainedScenario']


class TrainedScenario(NamedTuple):
    r"""What :func:`train_scenario` returns: the trained :obj:`model`, the
    :obj:`history` (one dict per epoch), the :obj:`checkpoint` path, and
    the :obj:`log` it wrote (:obj:`None` without a log folder, and on ranks
    other than 0)."""
    model: NEBP
    history: List[dict]
    checkpoint: Path
    log: Optional[TrainingLog]


def train_scenario(scenario: Union[str, Scenario], out: str,
                   variant: str = 'paper', particles: int = 1000,
                   iterations: int = 1, realizations: int = 100,
                   val_realizations: int = 10, epochs: int = 10,
                   batch_size: int = 2, lr: float = 1e-4, seed: int = 1,
                   measurement: Optional[str] = None,
                   samples: Union[int, str] = 1,
                   regularize: Union[float, str, None] = None,
                   ess_threshold: Optional[float] = None,
                   resume: bool = False, log_dir: Optional[str] = None,
                   root: str = 'datasets', device: str = 'cpu',
                   compile: bool = False,
                   progress_factory: Optional[Callable] = None,
                   description: str = 'train') -> TrainedScenario:
    r"""Trains NEBP (:obj:`variant` :obj:`'paper'` or
    :obj:`'equivariant'`) on :obj:`realizations` realizations of
    :obj:`scenario` drawn from :obj:`seed`, validated on
    :obj:`val_realizations` drawn from :obj:`seed + 1`, and writes
    :obj:`out/nebp.pt` after every epoch (:func:`~tg_nebp.training.train`);
    :obj:`resume` continues from it. :obj:`log_dir` adds a
    :class:`~tg_nebp.training_log.TrainingLog` (rank 0 writes it under
    :obj:`torchrun`). The GNN's initial weights are drawn from
    :obj:`seed`.

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
    rank = process_group()[1]
    train_set, val_set = load_datasets(
        root, (scenario, realizations, seed),
        (scenario, val_realizations, seed + 1))
    scenario = train_set.scenario
    torch.manual_seed(seed)  # the GNN's initial weights
    model = NEBP(particles, iterations, motion=scenario.motion_model,
                 measurement=tracker_measurement(scenario, measurement),
                 compile=compile, num_samples=samples,
                 regularize=regularize, ess_threshold=ess_threshold,
                 variant=variant, position_dim=scenario.position_dim)
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
                        on_epoch=log.epoch if log is not None else None)
    return TrainedScenario(model, history, checkpoint, log)
