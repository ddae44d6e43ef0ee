r"""One method on a scenario's test realizations: behind
:obj:`tg-nebp evaluate`. :func:`method_tracker` builds the tracker (or the
bound) of a method from its options, :func:`evaluate_scenario` generates
or loads the realizations, runs it and merges its entry into
:obj:`metrics.json`."""
import contextlib
from pathlib import Path
from typing import Callable, Optional, Tuple, Union

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.datasets import Scenario, load_datasets
from tg_nebp.evaluation import evaluate_method
from tg_nebp.filters import CentralizedIEKF, GaussianBP, ParticleBP, Tracker
from tg_nebp.models import model_like
from tg_nebp.training import nebp_from_checkpoint
from tg_nebp.utils import process_group

__all__ = ['METHODS', 'method_tracker', 'tracker_measurement',
           'evaluate_scenario']

#: The methods of :func:`method_tracker`, by their :obj:`metrics.json` key
#: stem: particle BP, NEBP from a checkpoint, Gaussian BP, the centralized
#: IEKF and the posterior CRB.
METHODS = ('bp', 'nebp', 'gbp', 'iekf', 'pcrb')


def tracker_measurement(scenario: Scenario, measurement: Optional[str]):
    r"""The likelihood inside a tracker: the scenario's own, or the model
    named :obj:`measurement` with the scenario's :obj:`sigma` and
    :obj:`max_range` (the model-mismatch experiments)."""
    if measurement is None:
        return scenario.measurement_model
    return model_like(measurement, 'measurement',
                      scenario.measurement_model)


def method_tracker(method: str, scenario: Scenario,
                   measurement: Optional[str] = None,
                   particles: Optional[int] = None,
                   iterations: Optional[int] = None,
                   samples: Union[int, str, None] = None,
                   resampler: str = 'multinomial',
                   regularize: Union[float, str, None] = None,
                   ess_threshold: Optional[float] = None,
                   ends: Optional[str] = None, marginal: bool = False,
                   inflation: Optional[float] = None,
                   tolerance: Optional[float] = None,
                   checkpoint: Optional[str] = None,
                   compile: bool = False
                   ) -> Tuple[Union[Tracker, PosteriorCRB], str]:
    r"""The tracker of :obj:`method` (one of :data:`METHODS`) for the data
    of :obj:`scenario`, and its :obj:`metrics.json` key. The options left
    at :obj:`None` take each method's default: particle BP with 1,000
    particles, one iteration and receiver-only messages; NEBP as its
    checkpoint says; :meth:`GaussianBP.recommended()
    <tg_nebp.filters.GaussianBP.recommended>` (a :obj:`tolerance` of 0
    runs every iteration); the IEKF with 5 Gauss-Newton iterations.
    Particle BP with more than one iteration and receiver-only messages is
    refused: the senders' beliefs already hold the receivers' information,
    and each iteration would count it again."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got "
                         f"'{method}'")
    models = dict(motion=scenario.motion_model,
                  measurement=tracker_measurement(scenario, measurement))
    if method == 'pcrb':
        return PosteriorCRB(scenario.motion_model,
                            scenario.measurement_model), 'pcrb'
    if method == 'iekf':
        tracker = CentralizedIEKF(iterations or 5, marginal=marginal,
                                  **models)
        return tracker, 'iekf-marginal' if marginal else 'iekf'
    if method == 'gbp':
        given = dict(num_iterations=iterations, inflation=inflation,
                     ends=ends, tolerance=tolerance)
        options = {k: v for k, v in given.items() if v is not None}
        if options.get('tolerance') == 0:  # every iteration
            options['tolerance'] = None
        return GaussianBP.recommended(**options, **models), 'gbp'
    if method == 'nebp':
        if checkpoint is None:
            raise ValueError("method 'nebp' needs a checkpoint")
        return nebp_from_checkpoint(checkpoint, particles, compile=compile,
                                    num_samples=samples), 'nebp'
    iterations, ends = iterations or 1, ends or 'receiver'
    if iterations > 1 and ends == 'receiver':
        raise ValueError(
            f"--iterations {iterations} with --ends receiver counts the "
            f"receivers' own information again at every iteration (the "
            f"senders' beliefs already hold it); use --ends both, whose "
            f"iterations send extrinsic messages")
    return ParticleBP(particles or 1000, iterations, resampler=resampler,
                      compile=compile, num_samples=samples or 1,
                      regularize=regularize, ess_threshold=ess_threshold,
                      ends=ends, **models), 'bp'


def evaluate_scenario(method: str, scenario: Union[str, Scenario],
                      realizations: int, seed: int = 0,
                      root: str = 'datasets', out: str = 'results',
                      batch_size: int = 1, device: str = 'cpu',
                      progress_factory: Optional[Callable] = None,
                      **options) -> dict:
    r"""Generates (or loads) :obj:`realizations` test realizations of
    :obj:`scenario` from :obj:`seed` under :obj:`root`, runs
    :func:`method_tracker(method, ..., **options) <method_tracker>` on
    them and merges its entry into :obj:`out/metrics.json`
    (:func:`~tg_nebp.evaluation.evaluate_method`). Under :obj:`torchrun`
    the realizations are sharded over the processes and rank 0 writes.

    Args:
        progress_factory (callable, optional): :obj:`(total, description)`
            to a context manager whose :obj:`update(n)` is called after
            every time step (a progress bar); :obj:`total` counts this
            process's steps. (default: :obj:`None`)

    Returns:
        The result of :func:`~tg_nebp.evaluation.evaluate_method`, its
        :obj:`metrics.json` entry under :obj:`"entry"` and the method's
        key under :obj:`"key"`.
    """
    world_size, rank = process_group()
    dataset, = load_datasets(root, (scenario, realizations, seed))
    tracker, key = method_tracker(method, dataset.scenario, **options)
    share = len(range(rank, len(dataset), world_size))
    particles = getattr(tracker, 'num_particles', None)
    bar = (progress_factory(share * dataset.scenario.num_steps,
                            key + (f' K={particles}' if particles else ''))
           if progress_factory is not None else contextlib.nullcontext())
    with bar:
        result = evaluate_method(key, tracker.to(device).eval(), dataset,
                                 batch_size, device, seed, Path(out),
                                 progress=getattr(bar, 'update', None))
    result['key'] = key
    return result
