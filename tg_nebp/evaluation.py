r"""Running a tracker over a dataset and summarizing its accuracy and
consistency, shared by the CLI, the notebooks and the benchmarks."""
import time
from pathlib import Path
from typing import Callable, Dict, Optional, Sequence

import torch
import torch.distributed as dist
from torch_geometric.data import Batch

from tg_nebp import metrics
from tg_nebp.filters import ParticleBP
from tg_nebp.io import read_json, write_json
from tg_nebp.utils import derive_seed, process_group

__all__ = ['track_dataset', 'summarize', 'evaluate_method',
           'OUTAGE_THRESHOLDS', 'CONFIDENCE']

#: The error thresholds in metres of the reported outage
#: probabilities.
OUTAGE_THRESHOLDS = (0.5, 1.0, 2.0)
#: The confidence levels of the reported P(accept H0).
CONFIDENCE = (0.50, 0.95, 0.99)


def track_dataset(tracker: ParticleBP, dataset: Sequence,
                  batch_size: int = 1, device: str = 'cpu', seed: int = 0,
                  progress: Optional[Callable] = None
                  ) -> Dict[str, torch.Tensor]:
    r"""Tracks every realization of :obj:`dataset` and returns the agents'
    position errors and NEES values (:obj:`"errors"`, :obj:`"nees"`), the
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
    world_size, rank = process_group()
    mine = list(range(rank, len(dataset), world_size))
    tracked, first = {}, {}  # realization -> (errors, nees); realization 0
    with torch.no_grad():
        for start in range(0, len(mine), batch_size):
            indices = mine[start:start + batch_size]
            batch = Batch.from_data_list(
                [dataset[r] for r in indices]).to(device)
            generator = [torch.Generator(device).manual_seed(
                derive_seed(seed, r)) for r in indices]
            agents = ~batch.anchor
            holds_first = indices[0] == 0  # its estimates go to the plots
            errors, nees, means = [], [], []
            for step in tracker.steps(batch, generator):
                truth = batch.states[:, step.t, :2]
                est = step.mean[:, :2]
                errors.append(metrics.position_errors(est, truth)[agents])
                nees.append(
                    metrics.nees(est, step.cov[:, :2, :2], truth)[agents])
                if holds_first:
                    means.append(step.mean)
                if progress is not None:  # realization-steps
                    progress(batch.num_graphs)
            # [agents, T]: row-major flattening is agent, then time step
            errors = torch.stack(errors, 1).cpu()
            nees = torch.stack(nees, 1).cpu()
            owner = batch.batch[agents].cpu()
            for g, r in enumerate(indices):
                tracked[r] = (errors[owner == g].flatten(),
                              nees[owner == g].flatten())
            if holds_first:
                nodes = slice(0, int(batch.ptr[1]))
                first = {
                    'first_mean': torch.stack(means, 1)[nodes].cpu(),
                    'first_states': batch.states[nodes].cpu(),
                    'first_anchor': batch.anchor[nodes].cpu(),
                }
    if world_size > 1:
        shares = [None] * world_size
        dist.all_gather_object(shares, (tracked, first))
        tracked = {r: v for share, _ in shares for r, v in share.items()}
        first = shares[0][1]  # rank 0 tracked realization 0
    order = sorted(tracked)
    return dict(
        errors=torch.cat([tracked[r][0] for r in order]),
        nees=torch.cat([tracked[r][1] for r in order]),
        realization=torch.cat([torch.full_like(tracked[r][0], r,
                                               dtype=torch.long)
                               for r in order]),
        **first)


def summarize(errors: torch.Tensor, nees: torch.Tensor,
              thresholds: Sequence[float] = OUTAGE_THRESHOLDS,
              confidence: Sequence[float] = CONFIDENCE) -> dict:
    r"""The :obj:`metrics.json` entry of a method: RMSE, outage
    probabilities keyed by threshold (:obj:`"0.5"`, ...) and
    :math:`\mathbb{P}(\text{accept } H_0)` keyed by confidence level
    (:obj:`"0.95"`, ...)."""
    outage = metrics.outage_from_errors(errors, thresholds)
    accept = metrics.consistency_curve(nees, confidence)
    return {
        'rmse': metrics.rmse_from_errors(errors),
        'outage': {f'{t:.1f}': float(p) for t, p in zip(thresholds, outage)},
        'accept': {f'{c:.2f}': float(p) for c, p in zip(confidence, accept)},
    }


def evaluate_method(method: str, tracker: ParticleBP, dataset,
                    batch_size: int, device: str, seed: int, out: Path,
                    progress: Optional[Callable] = None) -> dict:
    r"""Tracks :obj:`dataset`, merges the :obj:`method`'s entry into
    :obj:`out/metrics.json` and returns the raw errors and NEES. Under
    :obj:`torchrun` the realizations are sharded over the processes (see
    :func:`track_dataset`) and rank 0 alone writes the file."""
    start = time.perf_counter()
    result = track_dataset(tracker, dataset, batch_size, device, seed,
                           progress=progress)
    entry = summarize(result['errors'], result['nees'])
    entry.update(particles=tracker.num_particles, realizations=len(dataset),
                 seconds=round(time.perf_counter() - start, 3),
                 device=device, seed=seed,
                 iterations=tracker.num_iterations,
                 measurement=tracker.measurement.config(),
                 samples=tracker.num_samples,
                 regularize=tracker.regularize,
                 ess_threshold=tracker.ess_threshold,
                 scenario=getattr(getattr(dataset, 'scenario', None), 'name',
                                  None))
    result['entry'] = entry
    if process_group()[1] > 0:
        return result
    path = out / 'metrics.json'
    everything = read_json(path) if path.exists() else {}
    everything[method] = entry  # BP and NEBP share one file
    write_json(path, everything)
    return result
