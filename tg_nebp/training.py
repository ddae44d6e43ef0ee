r"""Training NEBP and its checkpoints.

A checkpoint is a plain dictionary of tensors and Python primitives: the
model's :obj:`state_dict`, the tracker configuration, the optimizer state,
the training progress and a format version. It is read with
:obj:`torch.load(weights_only=True)`, so loading never executes code from the
file; a corrupt, foreign or mismatched file gets a :class:`ValueError`."""
import math
from pathlib import Path
from typing import Callable, Dict, List, Optional, Union

import torch
from torch_geometric.data import Batch

from tg_nebp.filters import NEBP
from tg_nebp.io import atomic_write

__all__ = ['train', 'position_loss', 'save_checkpoint', 'load_checkpoint',
           'nebp_from_checkpoint', 'CHECKPOINT_VERSION']

CHECKPOINT_FORMAT = 'tg_nebp.nebp'
CHECKPOINT_VERSION = 1


def position_loss(mean, states, t, anchor):
    r"""The paper's loss :math:`\sum_i \|\hat{\mathbf{p}}_i -
    \mathbf{p}_i\|^2` over the agents at time index :obj:`t`."""
    agents = ~anchor
    return (mean[agents, :2] - states[agents, t, :2]).square().sum()


def _generator(seed: int, *parts: int) -> torch.Generator:
    # one independent stream per (seed, epoch, batch): a resumed run draws
    # exactly what the uninterrupted run drew
    value = seed
    for part in parts:
        value = (value * 1_000_003 + part) % (2**63 - 1)
    return torch.Generator().manual_seed(value)


def save_checkpoint(path: Union[str, Path], model: NEBP,
                    optimizer: Optional[torch.optim.Optimizer] = None,
                    progress: Optional[dict] = None):
    r"""Writes a checkpoint atomically (temporary file, then rename)."""
    state = dict(format=CHECKPOINT_FORMAT, version=CHECKPOINT_VERSION,
                 config=model.config(),
                 model={k: v.detach().cpu()
                        for k, v in model.state_dict().items()},
                 optimizer=optimizer.state_dict() if optimizer else None,
                 progress=progress or {})
    atomic_write(path, lambda tmp: torch.save(state, tmp))


def load_checkpoint(path: Union[str, Path]) -> dict:
    r"""Reads and checks a checkpoint (never executes code from it)."""
    try:
        state = torch.load(path, map_location='cpu', weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"checkpoint '{path}' does not exist") from None
    except Exception as e:  # the unpickler raises many kinds on bad input
        raise ValueError(f"'{path}' is not a readable tg_nebp checkpoint "
                         f"(corrupt, foreign, or holding objects other than "
                         f"tensors and primitives): {e}") from None
    if not isinstance(state, dict) or state.get('format') != CHECKPOINT_FORMAT:
        raise ValueError(f"'{path}' is not a tg_nebp NEBP checkpoint")
    if state.get('version') != CHECKPOINT_VERSION:
        raise ValueError(f"checkpoint '{path}' has format version "
                         f"{state.get('version')}; this tg_nebp reads "
                         f"version {CHECKPOINT_VERSION}")
    for key in ('config', 'model'):
        if not isinstance(state.get(key), dict):
            raise ValueError(f"checkpoint '{path}' lacks its '{key}'")
    return state


def nebp_from_checkpoint(path: Union[str, Path],
                         num_particles: Optional[int] = None,
                         compile: bool = False) -> NEBP:
    r"""Rebuilds an :class:`NEBP` tracker from a checkpoint (with
    :obj:`compile`, see :class:`NEBP`). The paper's :math:`g_e` and
    :math:`g_v` are sized by :math:`K`, so a different :obj:`num_particles`
    is an error."""
    state = load_checkpoint(path)
    trained = state['config'].get('num_particles')
    if num_particles is not None and num_particles != trained:
        raise ValueError(f"'particles' = {num_particles} does not match the "
                         f"checkpoint '{path}', trained with K = {trained} "
                         f"(g_e and g_v are sized by K)")
    try:
        model = NEBP.from_config(state['config'], compile=compile)
        model.load_state_dict(state['model'])
    except (TypeError, RuntimeError, KeyError) as e:
        raise ValueError(f"checkpoint '{path}' does not match the NEBP "
                         f"model: {e}") from None
    return model


def _batches(dataset, batch_size: int, generator: torch.Generator):
    order = torch.randperm(len(dataset), generator=generator).tolist()
    for start in range(0, len(order), batch_size):
        yield Batch.from_data_list(
            [dataset[i] for i in order[start:start + batch_size]])


def validation_loss(model: NEBP, dataset, batch_size: int, device: str,
                    seed: int) -> float:
    r"""Mean per-agent, per-step loss on :obj:`dataset` (no gradient)."""
    total, count = 0.0, 0
    with torch.no_grad():
        for b, batch in enumerate(_batches(dataset, batch_size,
                                           _generator(seed, -1))):
            batch = batch.to(device)
            generator = _device_generator(device, seed, -1, b)
            for step in model.steps(batch, generator):
                total += float(position_loss(step.mean, batch.states, step.t,
                                             batch.anchor))
                count += int((~batch.anchor).sum())
    return total / max(count, 1)


def _device_generator(device: str, seed: int, *parts: int):
    base = _generator(seed, *parts).initial_seed()
    return torch.Generator(device).manual_seed(base)


def train(model: NEBP, train_set, val_set=None, epochs: int = 10,
          batch_size: int = 2, lr: float = 1e-4, seed: int = 0,
          device: str = 'cpu', checkpoint: Optional[Union[str, Path]] = None,
          resume: bool = False,
          progress: Optional[Callable[[dict], None]] = None) -> List[Dict]:
    r"""Trains :obj:`model` as in the paper: Adam, one optimizer step per
    time step on :math:`\sum_i \|\hat{\mathbf{p}}_i - \mathbf{p}_i\|^2`
    summed over the batch's agents, resampling cutting the gradient. After
    every epoch the validation loss is computed and, if :obj:`checkpoint` is
    given, a checkpoint written atomically; :obj:`resume` continues from it
    and gives the same final parameters as an uninterrupted run (same seed,
    same device).

    Args:
        model (NEBP): The tracker to train (moved to :obj:`device`).
        train_set (Dataset): Training realizations.
        val_set (Dataset, optional): Validation realizations.
            (default: :obj:`None`)
        epochs (int, optional): Passes over :obj:`train_set`.
            (default: :obj:`10`)
        batch_size (int, optional): Realizations per batch.
            (default: :obj:`2`)
        lr (float, optional): Adam learning rate. (default: :obj:`1e-4`)
        seed (int, optional): Seed of shuffling and particle draws.
            (default: :obj:`0`)
        device (str, optional): Device. (default: :obj:`"cpu"`)
        checkpoint (str, optional): Checkpoint path. (default: :obj:`None`)
        resume (bool, optional): Continue from :obj:`checkpoint`.
            (default: :obj:`False`)
        progress (callable, optional): Called after every optimizer step
            with :obj:`{"epoch", "step", "loss"}` (loss per agent).
            (default: :obj:`None`)

    Returns:
        The history: one :obj:`{"epoch", "train_loss", "val_loss"}` per
        epoch.
    """
    if epochs < 1 or batch_size < 1 or not lr > 0:
        raise ValueError(f"'epochs' and 'batch_size' must be positive and "
                         f"'lr' > 0, got {epochs}, {batch_size}, {lr}")
    model.to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    history, start_epoch = [], 0
    if resume:
        if checkpoint is None or not Path(checkpoint).exists():
            raise ValueError(f"--resume needs an existing checkpoint, got "
                             f"'{checkpoint}'")
        state = load_checkpoint(checkpoint)
        if state['config'] != model.config():
            raise ValueError(f"checkpoint '{checkpoint}' was written for "
                             f"another configuration: {state['config']}")
        saved = state['progress']
        for key, value in (('seed', seed), ('batch_size', batch_size),
                           ('lr', lr)):
            if saved.get(key) != value:
                raise ValueError(f"checkpoint '{checkpoint}' was trained "
                                 f"with {key} = {saved.get(key)}, not "
                                 f"{value}: resuming would not continue "
                                 f"the same run")
        model.load_state_dict(state['model'])
        optimizer.load_state_dict(state['optimizer'])
        history = list(state['progress'].get('history', []))
        start_epoch = len(history)
    for epoch in range(start_epoch, epochs):
        model.train()
        total, count, step_index = 0.0, 0, 0
        for b, batch in enumerate(_batches(train_set, batch_size,
                                           _generator(seed, epoch))):
            batch = batch.to(device)
            generator = _device_generator(device, seed, epoch, b)
            agents = int((~batch.anchor).sum())
            for step in model.steps(batch, generator):
                loss = position_loss(step.mean, batch.states, step.t,
                                     batch.anchor)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                total += float(loss.detach())
                count += agents
                step_index += 1
                if progress is not None:
                    progress(dict(epoch=epoch, step=step_index,
                                  loss=float(loss.detach()) / agents))
        model.eval()
        record = dict(epoch=epoch, train_loss=total / max(count, 1),
                      val_loss=(validation_loss(model, val_set, batch_size,
                                                device, seed)
                                if val_set is not None else math.nan))
        history.append(record)
        if checkpoint is not None:
            save_checkpoint(checkpoint, model, optimizer,
                            dict(history=history, epochs=epochs, seed=seed,
                                 batch_size=batch_size, lr=lr))
    return history
