r"""Training NEBP (particle or Gaussian) and its checkpoints.

A checkpoint is a plain dictionary of tensors and Python primitives: the
model's :obj:`state_dict`, the tracker configuration, the optimizer state,
the training progress and a format version. It is read with
:obj:`torch.load(weights_only=True)`, so loading never executes code from the
file; a corrupt, foreign or mismatched file gets a :class:`ValueError`.

Training runs in one process or, under :obj:`torchrun`, data-parallel in
several (gradients summed over the ranks), with the same result up to float
rounding (see :func:`train`)."""
import math
from pathlib import Path
from typing import (Callable, Dict, Iterable, List, Optional, Sequence,
                    Tuple, Union)

import torch
import torch.distributed as dist
from torch import Tensor
from torch.utils.data.distributed import DistributedSampler
from torch_geometric.data import Batch

from tg_nebp.filters import (NEBP, FixedLagGaussianNEBP, GaussianNEBP,
                             StepOutput, Tracker)
from tg_nebp.data.realization import position_dim_of, scored_of
from tg_nebp.data.validation import check_number
from tg_nebp.io import atomic_write, one_line, read_tensors
from tg_nebp.utils import derive_seed, process_group

__all__ = ['train', 'train_epoch', 'steps_per_epoch', 'adam', 'step_loss',
           'position_loss', 'save_checkpoint', 'load_checkpoint',
           'nebp_from_checkpoint', 'gaussian_nebp_from_checkpoint',
           'tracker_from_checkpoint', 'checkpoint_path', 'checkpoint_base',
           'gaussian_step_loss', 'gaussian_window_loss', 'window_lag',
           'checkpoint_history', 'CHECKPOINT_VERSION', 'MAX_LR', 'BASES',
           'PRETRAINED']

#: The largest learning rate :func:`train` accepts.
MAX_LR = 1.0

CHECKPOINT_FORMAT = 'tg_nebp.nebp'
# 2: models stored as {'name': ..., 'params': ...}
#: The format version that :func:`save_checkpoint` writes.
CHECKPOINT_VERSION = 3
# version 2 differs only in lacking the NEBP variant (the paper's)
READABLE_VERSIONS = (2, 3)

#: The trackers a checkpoint holds, by the :obj:`base` of its
#: configuration (none: a particle NEBP, as every checkpoint before the
#: Gaussian one); a Gaussian one whose configuration has a :obj:`lag`
#: holds the correction inside a window
#: (:class:`~tg_nebp.filters.FixedLagGaussianNEBP`).
BASES = {'particle': NEBP, 'gaussian': GaussianNEBP}
#: The evaluation method of each base (:obj:`tg-nebp evaluate --method`).
_METHOD_OF_BASE = {'particle': 'nebp', 'gaussian': 'gnebp'}

#: The names of the checkpoints that ship with the package, Gaussian NEBP
#: trained on the paper's training network (:obj:`"paper"`), on its NLOS
#: variant with the Gaussian likelihood inside (:obj:`"nlos"`), on a mix of
#: the 2-D regimes (:obj:`"mix"`), on the 3-D training network
#: (:obj:`"box3d"`), on the simulated and the real robots (:obj:`"robots"`,
#: :obj:`"mrclam"`), and inside the window of 5 steps of fixed-lag Gaussian
#: BP on the paper's, sparse and wide-prior training networks
#: (:obj:`"window"`, a :class:`~tg_nebp.filters.FixedLagGaussianNEBP`) and
#: on the 3-D one (:obj:`"window3d"`), and on real UWB ranges (the first
#: half of the TIERS dataset's test3, :obj:`"tiers"`).
#: The commands that made them are in :obj:`tg_nebp/pretrained/README.md`.
PRETRAINED = ('paper', 'nlos', 'mix', 'box3d', 'robots', 'mrclam', 'window',
              'window3d', 'tiers')


def checkpoint_path(checkpoint: Union[str, Path]) -> Path:
    r"""The file of :obj:`checkpoint`: a name of :data:`PRETRAINED` (a
    string without a path separator or suffix) is the checkpoint shipped
    with the package; anything else is a path."""
    if isinstance(checkpoint, str) and checkpoint in PRETRAINED:
        return Path(__file__).parent / 'pretrained' / f'{checkpoint}.pt'
    return Path(checkpoint)


def base_of(config: dict) -> str:
    r"""The base of a checkpoint's configuration (:data:`BASES`)."""
    return config.get('base', 'particle')


def position_loss(mean, states, t, anchor, dim=None):
    r"""The paper's loss :math:`\sum_i \|\hat{\mathbf{p}}_i -
    \mathbf{p}_i\|^2` over the agents at time index :obj:`t`, the
    positions the first :obj:`dim` entries (the first half of a state by
    default); an agent without ground truth (its states NaN) is not
    scored."""
    dim = states.size(-1) // 2 if dim is None else dim
    agents = ~anchor & ~torch.isnan(states[:, t, :dim]).any(-1)
    return (mean[agents, :dim] - states[agents, t, :dim]).square().sum()


def gaussian_step_loss(step, batch: Batch) -> Tensor:
    r"""The loss of one time step that rewards accuracy and calibrated
    covariances together, the default of Gaussian NEBP's training: the
    negative log-likelihood of every agent's true position under its
    Gaussian belief (constant dropped) plus the squared error,

    .. math::
        \sum_i \tfrac{1}{2} \big(\mathbf{e}_i^\top
        \boldsymbol{\Sigma}_i^{-1} \mathbf{e}_i + \log |
        \boldsymbol{\Sigma}_i|\big) + \|\mathbf{e}_i\|^2, \quad
        \mathbf{e}_i = \hat{\mathbf{p}}_i - \mathbf{p}_i,

    with :math:`\boldsymbol{\Sigma}_i` the position block of the step's
    covariance. The negative log-likelihood alone rewards a wide
    covariance around a lost agent as much as finding it; the squared
    error keeps the estimate honest."""
    agents = scored_of(batch)
    dim = position_dim_of(batch)
    error = step.mean[agents, :dim] - batch.states[agents, step.t, :dim]
    cov = step.cov[agents, :dim, :dim]
    factor = torch.linalg.cholesky(cov)
    whitened = torch.linalg.solve_triangular(factor, error.unsqueeze(-1),
                                             upper=False)
    log_det = 2 * factor.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    nll = 0.5 * (whitened.square().sum((-1, -2)) + log_det)
    return (nll + error.square().sum(-1)).sum()


def gaussian_window_loss(step, batch: Batch) -> Tensor:
    r""":func:`gaussian_step_loss` of every step of the window that a
    windowed tracker's step holds (its :obj:`window_mean` and
    :obj:`window_cov`: the estimates of steps :math:`t - W + 1, \dots, t`
    after step :math:`t`), summed (so its value per agent-step is up to
    :math:`W` times a filter's): the loss that trains a correction
    through the window (:class:`~tg_nebp.filters.FixedLagGaussianNEBP`),
    which changes the past steps' estimates too. A step without a window:
    its own."""
    if step.window_mean is None:
        return gaussian_step_loss(step, batch)
    width = step.window_mean.size(1)
    return sum(gaussian_step_loss(StepOutput(
        step.t - width + 1 + k, step.window_mean[:, k],
        step.window_cov[:, k]), batch) for k in range(width))


def save_checkpoint(path: Union[str, Path], model: Tracker,
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
    state = read_tensors(path, 'tg_nebp checkpoint')
    if not isinstance(state, dict) or state.get('format') != CHECKPOINT_FORMAT:
        raise ValueError(f"'{path}' is not a tg_nebp NEBP checkpoint")
    if state.get('version') not in READABLE_VERSIONS:
        raise ValueError(f"checkpoint '{path}' has format version "
                         f"{state.get('version')}; this tg_nebp reads "
                         f"versions {', '.join(map(str, READABLE_VERSIONS))}")
    for key in ('config', 'model'):
        if not isinstance(state.get(key), dict):
            raise ValueError(f"checkpoint '{path}' lacks its '{key}'")
    for name, value in state['model'].items():
        # a network whose weights diverged tracks nothing but NaN
        if isinstance(value, torch.Tensor) and value.is_floating_point() \
                and not bool(value.isfinite().all()):
            raise ValueError(f"checkpoint '{path}': parameter {name!r} "
                             f"holds non-finite values")
    return state


def _load_base(path: Union[str, Path], base: Optional[str] = None) -> dict:
    # a checkpoint of a known base (of 'base' if given), or a ValueError
    # that names what it holds
    state = load_checkpoint(path)
    held = base_of(state['config'])
    if held not in BASES:
        raise ValueError(f"checkpoint '{path}' holds an NEBP of unknown base "
                         f"{held!r} (known: {', '.join(BASES)})")
    if base is not None and held != base:
        raise ValueError(f"checkpoint '{path}' holds a {held} NEBP, not a "
                         f"{base} one: evaluate it with --method "
                         f"{_METHOD_OF_BASE[held]}")
    return state


def window_lag(config: dict) -> Optional[int]:
    r"""The lag of the window a checkpoint's correction was trained in
    (:class:`~tg_nebp.filters.FixedLagGaussianNEBP`), from its
    configuration; :obj:`None` for a correction of one step."""
    return config.get('lag') if base_of(config) == 'gaussian' else None


def _rebuilt(path, state: dict, options: dict) -> Tracker:
    # the tracker of a checkpoint's base (the window's correction where it
    # has a lag), with its weights
    tracker = (BASES[base_of(state['config'])]
               if window_lag(state['config']) is None else
               FixedLagGaussianNEBP)
    try:
        model = tracker.from_config(state['config'], **options)
        model.load_state_dict(state['model'])
    except (TypeError, RuntimeError, KeyError) as e:
        raise ValueError(f"checkpoint '{path}' does not match the "
                         f"{tracker.__name__} model: {one_line(e)}") from None
    except ValueError as e:
        # a stored configuration out of range (a lag of 0), or a run-time
        # option given with it: named with the file, not as the user's flag
        raise ValueError(f"checkpoint '{path}' cannot be rebuilt as a "
                         f"{tracker.__name__} (its configuration"
                         f"{' with ' + ', '.join(options) if options else ''}"
                         f"): {one_line(e)}") from None
    return model


def nebp_from_checkpoint(path: Union[str, Path],
                         num_particles: Optional[int] = None,
                         compile: bool = False,
                         num_samples: Optional[Union[int, str]] = None
                         ) -> NEBP:
    r"""Rebuilds an :class:`~tg_nebp.filters.NEBP` tracker from a
    checkpoint (with :obj:`compile`, see :class:`~tg_nebp.filters.NEBP`).
    The paper variant's :math:`g_e` and :math:`g_v` are sized by :math:`K`,
    so a different :obj:`num_particles` is an error; the equivariant
    variant runs at any :math:`K`. A Gaussian NEBP's checkpoint is refused
    by name."""
    path = checkpoint_path(path)
    state = _load_base(path, 'particle')
    trained = state['config'].get('num_particles')
    variant = state['config'].get('variant', 'paper')
    if (num_particles is not None and num_particles != trained
            and variant == 'paper'):
        raise ValueError(f"'particles' = {num_particles} does not match the "
                         f"checkpoint '{path}', trained with K = {trained} "
                         f"(the paper variant's g_e and g_v are sized by K; "
                         f"train --variant equivariant for any K)")
    options = dict(compile=compile)
    if num_particles is not None:
        options['num_particles'] = num_particles
    if num_samples is not None:  # else the checkpoint's
        options['num_samples'] = num_samples
    return _rebuilt(path, state, options)


def gaussian_nebp_from_checkpoint(path: Union[str, Path], **options
                                  ) -> Union[GaussianNEBP,
                                             FixedLagGaussianNEBP]:
    r"""Rebuilds a :class:`~tg_nebp.filters.GaussianNEBP` tracker (a
    :class:`~tg_nebp.filters.FixedLagGaussianNEBP` where it was trained
    in a window) from a checkpoint: a path or a name of :data:`PRETRAINED`
    (:func:`checkpoint_path`). :obj:`options` replace entries that do not
    size the network (:obj:`num_iterations`, :obj:`tolerance`). A particle
    NEBP's checkpoint is refused by name."""
    path = checkpoint_path(path)
    return _rebuilt(path, _load_base(path, 'gaussian'), options)


def tracker_from_checkpoint(path: Union[str, Path]) -> Tracker:
    r"""The tracker of a checkpoint of either base (:data:`BASES`), as it
    was trained; a name of :data:`PRETRAINED` is the shipped one."""
    path = checkpoint_path(path)
    return _rebuilt(path, _load_base(path), {})


def checkpoint_base(path: Union[str, Path]) -> str:
    r"""The base (:data:`BASES`) of the checkpoint at :obj:`path` (a name
    of :data:`PRETRAINED` is the shipped one); an unknown base is a
    :class:`ValueError` naming it."""
    path = checkpoint_path(path)
    return base_of(_load_base(path)['config'])


def _sum_over_ranks(values: Sequence[float], device: str) -> List[float]:
    if process_group()[0] == 1:
        return list(values)
    # float64, as the Python floats that a single process sums
    summed = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(summed)
    return summed.tolist()


def _check_global_batches(num_realizations: int, batch_size: int,
                          world_size: int):
    r"""In distributed training, every global batch must split evenly over
    the ranks: a partial one would be padded with repeated realizations or
    leave a rank without a batch, hanging the gradient all-reduce."""
    if world_size == 1:
        return
    if batch_size % world_size != 0:
        raise ValueError(f"'batch_size' ({batch_size}) must be a multiple of "
                         f"the world size ({world_size}) in distributed "
                         f"training")
    if num_realizations % batch_size != 0:
        raise ValueError(f"the number of training realizations "
                         f"('train_set', {num_realizations}) must be a "
                         f"multiple of 'batch_size' ({batch_size}) in "
                         f"distributed training")


def _local_batches(dataset, batch_size: int, seed: int, epoch: int,
                   world_size: int = 1, rank: int = 0) -> List[List[int]]:
    r"""The dataset indices of this rank's batches of :obj:`epoch`: local
    batch :math:`b` of every rank together form global batch :math:`b` of
    :obj:`batch_size` realizations, the same as in a single process.

    :class:`~torch.utils.data.distributed.DistributedSampler` permutes the
    indices with a seed of :obj:`(seed, epoch)` alone (not the world size)
    and gives rank :math:`r` the positions :math:`r, r + W, r + 2W, \dots`
    of the permutation (no padding once :func:`_check_global_batches`
    passed). With the local batch size :math:`L = B / W`, local batch
    :math:`b` of rank :math:`r` holds the positions :math:`r + W j`,
    :math:`j \in [bL, bL + L)`; over all ranks these are exactly the
    positions :math:`[bB, bB + B)`, the single process's batch :math:`b`.
    """
    sampler = DistributedSampler(dataset, num_replicas=world_size, rank=rank,
                                 shuffle=True, seed=seed, drop_last=False)
    sampler.set_epoch(epoch)
    indices = list(sampler)
    local = batch_size // world_size
    return [indices[start:start + local]
            for start in range(0, len(indices), local)]


def _realization_generator(device: str, seed: int, tag: int,
                           index: int) -> torch.Generator:
    # one independent stream per (seed, epoch or -1, realization): a resumed
    # run, any batch and any rank draw what the uninterrupted run drew
    return torch.Generator(device).manual_seed(derive_seed(seed, tag, index))


def _batch(dataset, indices: List[int], device: str, seed: int,
           tag: int) -> Tuple[Batch, List[torch.Generator]]:
    r"""The realizations :obj:`indices` as one batch, and one generator per
    realization, seeded with :obj:`(seed, tag, index)`: a realization draws
    the same particles in any batch and on any rank."""
    batch = Batch.from_data_list([dataset[i] for i in indices]).to(device)
    return batch, [_realization_generator(device, seed, tag, i)
                   for i in indices]


def validation_loss(model: Tracker, dataset, batch_size: int, device: str,
                    seed: int, loss: Optional[Callable] = None) -> float:
    r"""Mean per-agent, per-step :obj:`loss` (of a step, as :func:`train`
    takes it; :func:`step_loss` if :obj:`None`) on :obj:`dataset` (no
    gradient). In
    distributed training, rank :math:`r` of :math:`W` tracks the
    realizations :math:`r, r + W, \dots` in batches of
    :obj:`batch_size // W` and the sums are all-reduced, so every rank
    returns the single-process value."""
    world_size, rank = process_group()
    shard = list(range(rank, len(dataset), world_size))
    local = max(batch_size // world_size, 1)
    total, count = 0.0, 0
    with torch.no_grad():
        for start in range(0, len(shard), local):
            batch, generators = _batch(dataset, shard[start:start + local],
                                       device, seed, -1)
            for step in model.steps(batch, generators):
                total += float((loss or step_loss)(step, batch))
                count += int((~batch.anchor).sum())
    total, count = _sum_over_ranks([total, count], device)
    return total / max(count, 1)


def _sum_gradients_over_ranks(model: torch.nn.Module):
    # every rank's gradient is that of its local loss sum: summed over the
    # ranks it is the gradient of the global batch's sum, as in a single
    # process (no wrapper module, so nothing depends on how the tracker
    # names its learnable parts)
    if process_group()[0] == 1:
        return
    for parameter in model.parameters():
        if parameter.grad is not None:
            dist.all_reduce(parameter.grad)


def adam(lr: float) -> Callable[[Iterable[torch.Tensor]],
                                torch.optim.Optimizer]:
    r"""The paper's optimizer, as the factory :func:`train` takes."""
    return lambda parameters: torch.optim.Adam(parameters, lr=lr)


def step_loss(step, batch: Batch) -> Tensor:
    r"""The paper's loss of one time step (:func:`position_loss` of the
    step's estimate), the default :obj:`loss` of :func:`train`."""
    return position_loss(step.mean, batch.states, step.t, batch.anchor,
                         position_dim_of(batch))


def _resume(checkpoint, model: Tracker, optimizer, settings: dict
            ) -> List[Dict]:
    # the history so far; the model and optimizer continue where they were
    if checkpoint is None or not Path(checkpoint).exists():
        raise ValueError(f"--resume needs an existing checkpoint, got "
                         f"'{checkpoint}'")
    state = load_checkpoint(checkpoint)
    # an older checkpoint resumes as what it meant (version 2: the paper
    # variant; before 3-D: positions in 2-D)
    if type(model).upgraded_config(state['config']) != model.config():
        raise ValueError(f"checkpoint '{checkpoint}' was written for "
                         f"another configuration: {state['config']}")
    history = checkpoint_history(state, checkpoint)
    saved = state['progress']
    for key, value in settings.items():
        if saved.get(key) != value:
            raise ValueError(f"checkpoint '{checkpoint}' was trained "
                             f"with {key} = {saved.get(key)}, not "
                             f"{value}: resuming would not continue "
                             f"the same run")
    if not isinstance(state.get('optimizer'), dict):
        raise ValueError(f"checkpoint '{checkpoint}' holds no optimizer "
                         f"state: it can be evaluated, not resumed")
    model.load_state_dict(state['model'])
    optimizer.load_state_dict(state['optimizer'])
    return history


def checkpoint_history(state: Union[dict, str, Path],
                       path: Optional[Union[str, Path]] = None
                       ) -> List[Dict]:
    r"""The training history of a checkpoint (a path, or the state that
    :func:`load_checkpoint` read from :obj:`path`): one
    :obj:`{"epoch", "train_loss", "val_loss"}` per finished epoch, checked,
    so that a damaged history is an error naming the checkpoint and the
    field rather than a :class:`KeyError` in a resumed run."""
    if not isinstance(state, dict):
        state, path = load_checkpoint(state), state
    progress = state.get('progress')
    history = progress.get('history', []) if isinstance(progress,
                                                         dict) else None
    if not isinstance(history, list):
        raise ValueError(f"checkpoint '{path}': its training history is not "
                         f"a list")
    for index, entry in enumerate(history):
        for field in ('epoch', 'train_loss', 'val_loss'):
            value = entry.get(field) if isinstance(entry, dict) else None
            if isinstance(value, bool) or not isinstance(value,
                                                         (int, float)):
                raise ValueError(f"checkpoint '{path}': epoch {index} of its "
                                 f"training history has no number "
                                 f"'{field}' ({entry!r})")
        if entry['epoch'] != index:
            raise ValueError(f"checkpoint '{path}': entry {index} of its "
                             f"training history is epoch {entry['epoch']}")
    return history


def steps_per_epoch(num_realizations: int, batch_size: int,
                    num_steps: int) -> int:
    r"""Optimizer steps in one epoch of :func:`train`: one per time step
    of every (global) batch, the last one possibly partial."""
    return -(-num_realizations // batch_size) * num_steps


def train_epoch(model: Tracker, train_set, optimizer: torch.optim.Optimizer,
                epoch: int, batch_size: int, seed: int, device: str,
                loss: Callable = step_loss,
                progress: Optional[Callable[[dict], None]] = None) -> float:
    r"""One epoch of :func:`train`: an optimizer step per time step of
    every batch; returns the mean loss per agent (over all ranks)."""
    world_size, rank = process_group()
    model.train()
    total, count, step_index = 0.0, 0, 0
    for indices in _local_batches(train_set, batch_size, seed, epoch,
                                  world_size, rank):
        batch, generators = _batch(train_set, indices, device, seed, epoch)
        agents = int(scored_of(batch).sum())
        for step in model.steps(batch, generators):
            value = loss(step, batch)
            optimizer.zero_grad()
            value.backward()
            _sum_gradients_over_ranks(model)
            optimizer.step()
            summed, summed_agents = _sum_over_ranks(
                [float(value.detach()), agents], device)
            total += summed
            count += summed_agents
            step_index += 1
            if progress is not None and rank == 0:
                progress(dict(epoch=epoch, step=step_index,
                              loss=summed / summed_agents))
    model.eval()
    return total / max(count, 1)


def train(model: Tracker, train_set, val_set=None, epochs: int = 10,
          batch_size: int = 2, lr: float = 1e-4, seed: int = 0,
          device: str = 'cpu', checkpoint: Optional[Union[str, Path]] = None,
          resume: bool = False,
          progress: Optional[Callable[[dict], None]] = None,
          optimizer: Optional[Callable] = None,
          loss: Callable = step_loss,
          on_epoch: Optional[Callable[[dict], None]] = None) -> List[Dict]:
    r"""Trains :obj:`model` as in the paper: Adam, one optimizer step per
    time step on :math:`\sum_i \|\hat{\mathbf{p}}_i - \mathbf{p}_i\|^2`
    summed over the batch's agents, resampling cutting the gradient. After
    every epoch the validation loss is computed and, if :obj:`checkpoint` is
    given, a checkpoint written atomically; :obj:`resume` continues from it
    and gives the same final parameters as an uninterrupted run (same seed,
    same device). Every realization draws its particles from its own
    generator, seeded with :obj:`(seed, epoch, index)`, so the result does
    not depend on how a batch is split. The pieces are replaceable: the
    optimizer (a factory), the loss of a time step, and the hooks
    :obj:`progress` (per step) and :obj:`on_epoch` (a
    :class:`~tg_nebp.training_log.TrainingLog` takes both);
    :func:`train_epoch` is one epoch on its own.

    **Distributed training.** Started by :obj:`torchrun` with an initialized
    process group of :math:`W > 1` processes (:obj:`tg-nebp train` does it:
    :obj:`torchrun --nproc_per_node=W -m tg_nebp train ...`; gloo on the
    CPU, NCCL on GPUs, with :obj:`device` the process's GPU), every global
    batch of :obj:`batch_size` realizations is split over the ranks
    (:obj:`batch_size // W` each, shuffled by a
    :class:`~torch.utils.data.distributed.DistributedSampler`), and after
    every backward pass the gradients of all learnable parameters are
    summed over the ranks: the gradient of the global batch's summed loss.
    The parameters, history and checkpoint equal single-process training
    with the same :obj:`batch_size` up to float rounding (the gradient sums
    run in another order). Resampling is discontinuous, so over many
    float32 steps such a rounding difference eventually changes one ancestor
    draw, after which the two runs are statistically, not numerically,
    equal (as runs on different thread counts); in float64 they agree far
    longer. :obj:`batch_size` must be a multiple of :math:`W` and
    :obj:`len(train_set)` of :obj:`batch_size`. Only rank 0 writes
    checkpoints and calls :obj:`progress` and :obj:`on_epoch` (all ranks
    read a checkpoint to resume, so it must be on a shared file system);
    every rank returns the same history.

    Args:
        model (NEBP): The tracker to train (moved to :obj:`device`).
        train_set (Dataset): Training realizations.
        val_set (Dataset, optional): Validation realizations.
            (default: :obj:`None`)
        epochs (int, optional): Passes over :obj:`train_set`.
            (default: :obj:`10`)
        batch_size (int, optional): Realizations per (global) batch.
            (default: :obj:`2`)
        lr (float, optional): Learning rate of the default optimizer
            (Adam). (default: :obj:`1e-4`)
        seed (int, optional): Seed of shuffling and particle draws.
            (default: :obj:`0`)
        device (str, optional): Device. (default: :obj:`"cpu"`)
        checkpoint (str, optional): Checkpoint path. (default: :obj:`None`)
        resume (bool, optional): Continue from :obj:`checkpoint`.
            (default: :obj:`False`)
        progress (callable, optional): The per-step hook, called after
            every optimizer step with :obj:`{"epoch", "step", "loss"}` (loss
            per agent of the global batch). (default: :obj:`None`)
        optimizer (callable, optional): Builds the optimizer from the
            parameters. (default: :obj:`adam(lr)`)
        loss (callable, optional): The loss of a time step from the
            tracker's :class:`~tg_nebp.filters.StepOutput` and
            the batch, a sum over the batch's agents.
            (default: :func:`step_loss`)
        on_epoch (callable, optional): Called after every epoch (and its
            checkpoint) with its history entry. (default: :obj:`None`)

    Returns:
        The history: one :obj:`{"epoch", "train_loss", "val_loss"}` per
        epoch.
    """
    if epochs < 1 or batch_size < 1:
        raise ValueError(f"'epochs' and 'batch_size' must be positive, got "
                         f"{epochs}, {batch_size}")
    # Adam's step is about lr per parameter: beyond MAX_LR the weights and
    # then the messages leave every meaningful range
    check_number(lr, 'lr', maximum=MAX_LR)
    world_size, rank = process_group()
    _check_global_batches(len(train_set), batch_size, world_size)
    model.to(device)
    optimizer = (optimizer or adam(lr))(model.parameters())
    settings = dict(seed=seed, batch_size=batch_size, lr=lr)
    history = (_resume(checkpoint, model, optimizer, settings)
               if resume else [])
    for epoch in range(len(history), epochs):
        train_loss = train_epoch(model, train_set, optimizer, epoch,
                                 batch_size, seed, device, loss, progress)
        history.append(dict(
            epoch=epoch, train_loss=train_loss,
            val_loss=(validation_loss(model, val_set, batch_size, device,
                                      seed, loss)
                      if val_set is not None else math.nan)))
        if checkpoint is not None:
            if rank == 0:
                save_checkpoint(checkpoint, model, optimizer,
                                dict(history=history, epochs=epochs,
                                     **settings))
            if world_size > 1:  # every rank returns with the file written
                dist.barrier()
        if on_epoch is not None and rank == 0:
            on_epoch(history[-1])
    return history
