r"""Running a tracker, or the bound, over a dataset and summarizing its
accuracy and consistency, shared by the CLI, the compare table, the
notebooks and the benchmarks."""
import time
from pathlib import Path
from typing import Callable, Dict, Optional, Sequence, Union

import torch
import torch.distributed as dist
from torch_geometric.data import Batch

from tg_nebp import metrics
from tg_nebp.bounds import PosteriorCRB
from tg_nebp.data.realization import position_dim_of, scored_of
from tg_nebp.data.validation import check_positive_int
from tg_nebp.filters import Tracker
from tg_nebp.filters.tracker import with_control
from tg_nebp.io import read_json, write_json
from tg_nebp.utils import check_device, derive_seed, process_group

__all__ = ['track_dataset', 'bound_dataset', 'summarize', 'summarize_bound',
           'summarize_result', 'spread', 'evaluate_method',
           'OUTAGE_THRESHOLDS', 'CONFIDENCE', 'OUTAGE_KEY', 'CONFIDENCE_KEY']

#: The error thresholds in metres of the reported outage
#: probabilities.
OUTAGE_THRESHOLDS = (0.5, 1.0, 2.0)
#: The confidence levels of the reported P(accept H0).
CONFIDENCE = (0.50, 0.95, 0.99)
#: The :obj:`metrics.json` keys that rank methods: P_out(1 m) (lower is
#: better) and P(accept H0) at the 0.95 level, whose ideal is 0.95 (a
#: filter that accepts more often is overly conservative, not better).
OUTAGE_KEY, CONFIDENCE_KEY = '1.0', '0.95'


def _realization_batches(dataset: Sequence, batch_size: int, device: str):
    # this process's realizations (r, r + W, ... under torchrun), batched:
    # (their indices, the batch)
    check_positive_int(batch_size, 'batch_size')
    check_device(device)
    world_size, rank = process_group()
    mine = list(range(rank, len(dataset), world_size))
    for start in range(0, len(mine), batch_size):
        indices = mine[start:start + batch_size]
        yield indices, Batch.from_data_list(
            [dataset[r] for r in indices]).to(device)


def _gathered(tracked: dict, first: dict):
    # every rank's {realization: values} and rank 0's first-realization
    # estimates, on every rank (one process: as they are)
    world_size = process_group()[0]
    if world_size > 1:
        shares = [None] * world_size
        dist.all_gather_object(shares, (tracked, first))
        tracked = {r: v for share, _ in shares for r, v in share.items()}
        first = shares[0][1]  # rank 0 tracked realization 0
    return tracked, first


def track_dataset(tracker: Tracker, dataset: Sequence,
                  batch_size: int = 1, device: str = 'cpu', seed: int = 0,
                  progress: Optional[Callable] = None
                  ) -> Dict[str, torch.Tensor]:
    r"""Tracks every realization of :obj:`dataset` and returns the agents'
    position errors and NEES values (:obj:`"errors"`, :obj:`"nees"`; its
    degrees of freedom, the position dimension, :obj:`"dof"`), the
    index of the realization each value belongs to (:obj:`"realization"`),
    plus the estimates of the first realization (:obj:`"first_mean"`,
    :obj:`"first_states"`, :obj:`"first_anchor"`) for plots. The values are
    flattened in one order, whatever the batches and processes: by
    realization, then agent, then time step.

    Realization :math:`r` draws its particles from its own generator,
    seeded with :obj:`derive_seed(seed, r)`, so two trackers run with the
    same :obj:`seed` see the same prior particle draws, and the result does
    not depend on :obj:`batch_size`.

    **Sharded evaluation.** Under an initialized process group of
    :math:`W > 1` processes (:obj:`torchrun --nproc_per_node=W -m tg_nebp
    evaluate ...`; gloo on the CPU, NCCL on GPUs), rank :math:`r` tracks
    the realizations :math:`r, r + W, \dots` in batches of
    :obj:`batch_size`, and every rank returns the gathered result, equal
    to one process's.

    Args:
        tracker (ParticleBP): The tracker (BP or NEBP).
        dataset (sequence): Realizations with true :obj:`states`.
        batch_size (int, optional): Realizations tracked together as one
            disjoint graph (per process). (default: :obj:`1`)
        device (str, optional): Device. (default: :obj:`"cpu"`)
        seed (int, optional): Seed of the particle draws. (default: :obj:`0`)
        progress (callable, optional): Called after each time step with
            the number of realization-steps it did (the batch's
            realizations), so a bar of :obj:`len(dataset) * T` (of this
            process's share under :obj:`torchrun`) ends full for any
            :obj:`batch_size`. (default: :obj:`None`)
    """
    tracked, first = {}, {}  # realization -> (errors, nees); realization 0
    dof = 2
    with torch.no_grad():
        for indices, batch in _realization_batches(dataset, batch_size,
                                                   device):
            generator = [torch.Generator(device).manual_seed(
                derive_seed(seed, r)) for r in indices]
            agents = scored_of(batch)
            holds_first = indices[0] == 0  # its estimates go to the plots
            errors, nees, means, headings = [], [], [], []
            dim = dof = position_dim_of(batch)
            angles = list(tracker.motion.layout(batch.states.size(-1)).angles)
            for step in tracker.steps(batch, generator):
                truth = batch.states[:, step.t, :dim]
                est = step.mean[:, :dim]
                errors.append(metrics.position_errors(est, truth)[agents])
                nees.append(
                    metrics.nees(est, step.cov[:, :dim, :dim], truth)[agents])
                if angles:
                    headings.append(metrics.angle_errors(
                        step.mean[:, angles],
                        batch.states[:, step.t, angles])[agents])
                if holds_first:
                    means.append(step.mean)
                if progress is not None:  # realization-steps
                    progress(batch.num_graphs)
            # [agents, T]: row-major flattening is agent, then time step
            errors = torch.stack(errors, 1).cpu()
            nees = torch.stack(nees, 1).cpu()
            # [agents, T, angles]: the errors of the angles (headings)
            headings = (torch.stack(headings, 1).cpu() if angles else
                        errors.new_zeros(errors.shape + (0, )))
            owner = batch.batch[agents].cpu()
            for g, r in enumerate(indices):
                tracked[r] = (errors[owner == g].flatten(),
                              nees[owner == g].flatten(),
                              headings[owner == g].flatten(0, 1))
            if holds_first:
                nodes = slice(0, int(batch.ptr[1]))
                first = {
                    'first_mean': torch.stack(means, 1)[nodes].cpu(),
                    'first_states': batch.states[nodes].cpu(),
                    'first_anchor': batch.anchor[nodes].cpu(),
                }
    tracked, first = _gathered(tracked, first)
    out = _by_realization(tracked, ('errors', 'nees', 'angle_errors'))
    if out['angle_errors'].size(-1) == 0:  # no angle in the state
        del out['angle_errors']
    return dict(out, dof=dof, **first)


def _by_realization(tracked: Dict[int, tuple], names: Sequence[str]
                    ) -> Dict[str, torch.Tensor]:
    # the per-realization tensors of 'tracked' {r: (one per name)}
    # concatenated in realization order, and the realization of each row
    order = sorted(tracked)
    out = {name: torch.cat([tracked[r][k] for r in order])
           for k, name in enumerate(names)}
    out['realization'] = torch.cat([
        torch.full((len(tracked[r][0]), ), r, dtype=torch.long)
        for r in order])
    return out


def summarize(errors: torch.Tensor, nees: torch.Tensor,
              thresholds: Sequence[float] = OUTAGE_THRESHOLDS,
              confidence: Sequence[float] = CONFIDENCE,
              dof: int = 2,
              angle_errors: Optional[torch.Tensor] = None) -> dict:
    r"""The :obj:`metrics.json` entry of a method: RMSE, the median and
    the largest error (:obj:`"median_error"`, :obj:`"max_error"`: one lost
    agent-step shows here before it moves the RMSE), outage
    probabilities keyed by threshold (:obj:`"0.5"`, ...) and
    :math:`\mathbb{P}(\text{accept } H_0)` keyed by confidence level
    (:obj:`"0.95"`, ...), the NEES tested with :obj:`dof` degrees of
    freedom (the position dimension); with the errors of a state's angles
    :obj:`angle_errors` :math:`(V, A)` (wrapped, radians), their RMSE
    :obj:`"heading_rmse"` (over all angles)."""
    outage = metrics.outage_from_errors(errors, thresholds)
    accept = metrics.consistency_curve(nees, confidence, dof=dof)
    entry = {
        'rmse': metrics.rmse_from_errors(errors),
        'median_error': float(errors.double().median()),
        'max_error': float(errors.double().max()),
        'outage': {f'{t:.1f}': float(p) for t, p in zip(thresholds, outage)},
        'accept': {f'{c:.2f}': float(p) for c, p in zip(confidence, accept)},
    }
    if angle_errors is not None:
        entry['heading_rmse'] = metrics.rmse_from_errors(angle_errors)
    return entry


def bound_dataset(bound: PosteriorCRB, dataset: Sequence,
                  batch_size: int = 1, device: str = 'cpu', seed: int = 0,
                  progress: Optional[Callable] = None,
                  thresholds: Sequence[float] = OUTAGE_THRESHOLDS
                  ) -> Dict[str, torch.Tensor]:
    r"""The posterior Cramér-Rao bound of every realization of
    :obj:`dataset`, as :func:`track_dataset` reports a tracker: per agent
    and time step (in the same order: realization, agent, time step) the
    bound on the mean squared position error, the trace of the position
    block of the bound covariance (:obj:`"squared_error"`), and the outage
    at each of the :obj:`thresholds` of an efficient estimator, whose error
    is Gaussian with that covariance (:obj:`"outage"` :math:`(V, R)`,
    :func:`~tg_nebp.metrics.gaussian_outage`), with :obj:`"realization"`.
    Sharded under :obj:`torchrun` as :func:`track_dataset`; :obj:`seed`
    seeds realization :math:`r`'s generator (used only by measurement
    models whose Fisher information is a Monte Carlo)."""
    tracked = {}
    with torch.no_grad():
        for indices, batch in _realization_batches(dataset, batch_size,
                                                   device):
            generator = torch.Generator(device).manual_seed(
                derive_seed(seed, indices[0]))
            agents = ~batch.anchor
            dim = position_dim_of(batch)
            angles = list(bound.motion.layout(batch.states.size(-1)).angles)
            squared, outage, angle_var = [], [], []
            for step in bound.steps(batch, generator):
                cov = step.cov[agents, :dim, :dim]
                squared.append(cov.diagonal(dim1=-2, dim2=-1).sum(-1))
                outage.append(metrics.gaussian_outage(cov, thresholds))
                angle_var.append(step.cov[agents][:, angles, angles])
                if progress is not None:
                    progress(batch.num_graphs)
            squared = torch.stack(squared, 1).cpu()  # [agents, T]
            outage = torch.stack(outage, 1).cpu()  # [agents, T, R]
            angle_var = torch.stack(angle_var, 1).cpu()  # [agents, T, A]
            owner = batch.batch[agents].cpu()
            for g, r in enumerate(indices):
                tracked[r] = (squared[owner == g].flatten(),
                              outage[owner == g].flatten(0, 1),
                              angle_var[owner == g].flatten(0, 1))
    tracked, _ = _gathered(tracked, {})
    out = _by_realization(tracked, ('squared_error', 'outage',
                                    'angle_squared_error'))
    if out['angle_squared_error'].size(-1) == 0:  # no angle in the state
        del out['angle_squared_error']
    return out


def summarize_bound(squared_error: torch.Tensor, outage: torch.Tensor,
                    thresholds: Sequence[float] = OUTAGE_THRESHOLDS,
                    confidence: Sequence[float] = CONFIDENCE,
                    angle_squared_error: Optional[torch.Tensor] = None
                    ) -> dict:
    r"""The :obj:`metrics.json` entry of the bound, with the fields of
    :func:`summarize`: :obj:`"rmse"` is the RMSE floor
    :math:`\sqrt{\operatorname{mean} \operatorname{tr} \mathbf{B}}`,
    :obj:`"outage"` the mean outage of an efficient estimator, and
    :obj:`"accept"` its :math:`\mathbb{P}(\text{accept } H_0)`: the
    confidence level itself (its NEES is :math:`\chi^2`-distributed)."""
    mean_outage = outage.double().mean(0)
    entry = {
        'rmse': float(squared_error.double().mean().sqrt()),
        'outage': {f'{t:.1f}': float(p)
                   for t, p in zip(thresholds, mean_outage)},
        'accept': {f'{c:.2f}': float(c) for c in confidence},
    }
    if angle_squared_error is not None:  # the floor of the angles' RMSE
        entry['heading_rmse'] = float(
            angle_squared_error.double().mean().sqrt())
    return entry


def summarize_result(result: Dict[str, torch.Tensor]) -> dict:
    r"""The :obj:`metrics.json` entry of a result of
    :func:`track_dataset` (:func:`summarize`) or of :func:`bound_dataset`
    (:func:`summarize_bound`)."""
    if 'errors' in result:
        return summarize(result['errors'], result['nees'],
                         dof=result.get('dof', 2),
                         angle_errors=result.get('angle_errors'))
    return summarize_bound(result['squared_error'], result['outage'],
                           angle_squared_error=result.get(
                               'angle_squared_error'))


def _select(result: Dict[str, torch.Tensor], mask: torch.Tensor) -> dict:
    selected = {key: result[key][mask]
                for key in ('errors', 'nees', 'squared_error', 'outage',
                            'angle_errors', 'angle_squared_error')
                if key in result}
    if 'dof' in result:
        selected['dof'] = result['dof']
    return selected


def spread(result: Dict[str, torch.Tensor], level: float = 1.0) -> dict:
    r"""How the headline figures vary over the realizations of a result of
    :func:`track_dataset` or :func:`bound_dataset`: each realization's
    :math:`P_\mathrm{out}` at :obj:`level` metres, P(accept :math:`H_0`)
    at the 0.95 level and RMSE (:obj:`"realizations"`, one row
    each), and their mean, sample standard deviation, minimum and maximum
    (:obj:`"outage_1m"`, :obj:`"accept_0.95"`, :obj:`"rmse"`)."""
    per = []
    for r in result['realization'].unique().tolist():
        entry = summarize_result(_select(result, result['realization'] == r))
        per.append([entry['outage'][f'{level:.1f}'],
                    entry['accept']['0.95'], entry['rmse']])
    per = torch.tensor(per, dtype=torch.float64)
    std = per.std(0) if len(per) > 1 else torch.zeros(3,
                                                      dtype=torch.float64)
    out = {'realizations': per.tolist()}
    for column, key in enumerate(('outage_1m', 'accept_0.95', 'rmse')):
        out[key] = dict(mean=float(per[:, column].mean()),
                        std=float(std[column]),
                        min=float(per[:, column].min()),
                        max=float(per[:, column].max()))
    return out


def evaluate_method(method: str, tracker: Union[Tracker, PosteriorCRB],
                    dataset, batch_size: int, device: str, seed: int,
                    out: Path, progress: Optional[Callable] = None) -> dict:
    r"""Tracks :obj:`dataset` (or, for a
    :class:`~tg_nebp.bounds.PosteriorCRB`, computes the bound of its
    realizations), merges the :obj:`method`'s entry into
    :obj:`out/metrics.json` (the accuracy, the tracker's
    :meth:`~tg_nebp.filters.Tracker.settings`, the realizations, seed,
    device, scenario and seconds) and returns the raw result
    (:func:`track_dataset`, :func:`bound_dataset`) with the entry under
    :obj:`"entry"`. Under :obj:`torchrun` the realizations are sharded
    over the processes and rank 0 alone writes the file."""
    start = time.perf_counter()
    if isinstance(tracker, PosteriorCRB):
        result = bound_dataset(tracker, dataset, batch_size, device, seed,
                               progress=progress)
        settings = dict(measurement=tracker.measurement.config())
    else:
        result = track_dataset(tracker, dataset, batch_size, device, seed,
                               progress=progress)
        settings = tracker.settings()
    settings = with_control(tracker, settings)
    entry = summarize_result(result)
    entry.update(settings, realizations=len(dataset),
                 seconds=round(time.perf_counter() - start, 3),
                 device=device, seed=seed,
                 scenario=getattr(getattr(dataset, 'scenario', None), 'name',
                                  None))
    result['entry'] = entry
    if process_group()[1] > 0:
        return result
    path = out / 'metrics.json'
    everything = read_json(path) if path.exists() else {}
    everything[method] = entry  # the methods share one file
    write_json(path, everything)
    return result
