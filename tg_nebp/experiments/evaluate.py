r"""One method on a scenario's test realizations: behind
:obj:`tg-nebp evaluate`. :func:`method_tracker` builds the tracker (or the
bound) of a method from its options, :func:`evaluate_scenario` generates
or loads the realizations, runs it and merges its entry into
:obj:`metrics.json`."""
import contextlib
import dataclasses
import os
import warnings
from pathlib import Path
from typing import Callable, Mapping, Optional, Tuple, Union

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.data.validation import check_positive_int
from tg_nebp.datasets import (MRCLAMScenario, RecordingScenario, Scenario,
                              load_datasets, load_scenario)
from tg_nebp.evaluation import evaluate_method
from tg_nebp.experiments.options import WHOLE_SEQUENCE, MethodOptions
from tg_nebp.filters import (HYBRID_RECOMMENDED, CentralizedIEKF,
                             CentralizedSmoother, FixedLagGaussianBP,
                             FixedLagGaussianNEBP, GaussianBP,
                             GroupExchange, GroupFlip, HybridBP,
                             IncrementalSmoother, LinkSearch,
                             NoiseAdaptation, ParticleBP,
                             ParticleTrajectorySearch, Smoothed, Tracker,
                             TrajectorySearch)
from tg_nebp.models import model_like
from tg_nebp.training import (PRETRAINED, gaussian_nebp_from_checkpoint,
                              nebp_from_checkpoint)
from tg_nebp.utils import check_device, process_group

__all__ = ['method_tracker',
           'tracker_measurement', 'evaluate_scenario', 'scenario_of',
           'check_run', 'realizations_of', 'checked_models',
           'SCENARIO_TYPES', 'REAL_SCENARIO_TYPES', 'WHOLE_SEQUENCE',
           'lag_key', 'escaping_smoother', 'ESCAPE_WINDOW']

#: The lag of the window whose smoothed estimates start the escaping
#: smoother beside the incremental smoother's (issue 64's window).
ESCAPE_WINDOW = 10


def escaping_smoother(motion, measurement, **options) -> CentralizedSmoother:
    r"""The full smoother that escapes its filter's basin (``--escape``,
    :obj:`"iekf-smoother-escape"`): started from the incremental
    smoother's last step and from the smoothed estimates of fixed-lag
    Gaussian BP over :obj:`ESCAPE_WINDOW` steps with the relocation with
    hindsight (the better optimum by the whole sequence's cost kept: on the
    validation realizations of ``paper_test_sparse`` each start's basin was
    the better in some), connected groups of agents taken from the other
    optimum where that costs more than 10 nats less
    (:class:`~tg_nebp.filters.GroupExchange`: each start can lose a
    different group), groups of agents that range to no anchor flipped
    across their outside neighbours' line where that costs more than 10
    nats less (:class:`~tg_nebp.filters.GroupFlip`: a group both starts
    put on its mirror), then every agent's trajectory searched for a
    better basin (:class:`~tg_nebp.filters.ParticleTrajectorySearch`);
    the models :obj:`motion` and :obj:`measurement` throughout and
    :obj:`options` of :class:`~tg_nebp.filters.CentralizedSmoother`."""
    models = dict(motion=motion, measurement=measurement)
    return CentralizedSmoother(
        None, **options, **models, start=(
            Smoothed(IncrementalSmoother(**models)),
            Smoothed(FixedLagGaussianBP.recommended(
                lag=ESCAPE_WINDOW, relocation=TrajectorySearch(),
                **models))),
        search=ParticleTrajectorySearch(), exchange=GroupExchange(),
        flip=GroupFlip())


def lag_key(lag) -> str:
    r"""The suffix of a smoother's :obj:`metrics.json` key:
    :obj:`"-lagL"` for a window of :obj:`lag` steps, :obj:`"-smoother"`
    for the whole sequence."""
    return '-smoother' if lag == WHOLE_SEQUENCE else f'-lag{lag}'


def tracker_measurement(scenario: Scenario, measurement: Optional[str]):
    r"""The likelihood inside a tracker: the scenario's own, or the model
    named :obj:`measurement` with the scenario's :obj:`sigma` and
    :obj:`max_range` (the model-mismatch experiments)."""
    if measurement is None:
        return scenario.measurement_model
    return model_like(measurement, 'measurement',
                      scenario.measurement_model)


#: The scenarios of a run, a simulated network or a real sequence.
SCENARIO_TYPES = (Scenario, MRCLAMScenario, RecordingScenario)
#: The scenarios of real data, whose realizations are what was recorded
#: (every window), the same for every seed.
REAL_SCENARIO_TYPES = (MRCLAMScenario, RecordingScenario)


def scenario_of(spec: Union[str, os.PathLike, Scenario, MRCLAMScenario],
                name: str = "'scenario'"
                ) -> Union[Scenario, MRCLAMScenario]:
    r"""The :class:`~tg_nebp.datasets.Scenario` or the real sequence's
    :class:`~tg_nebp.datasets.MRCLAMScenario` of a name, a JSON file or
    either object (itself) (:func:`~tg_nebp.datasets.load_scenario`),
    loaded before any data is made; another type is a :class:`TypeError`
    naming the argument :obj:`name`."""
    if isinstance(spec, SCENARIO_TYPES):
        return spec
    if isinstance(spec, (str, os.PathLike)):
        return load_scenario(spec)
    raise TypeError(f"{name} must be a scenario name, a JSON file, a "
                    f"Scenario or an MRCLAMScenario, got {spec!r}")


def realizations_of(scenario: Union[Scenario, MRCLAMScenario],
                    realizations: Optional[int], default: int
                    ) -> Optional[int]:
    r"""The realizations of a run on :obj:`scenario`: the number given;
    where none is given, :obj:`default` for a simulated network and
    :obj:`None` (every window) for a real sequence."""
    if realizations is not None:
        return realizations
    return None if isinstance(scenario, REAL_SCENARIO_TYPES) else default


def check_run(realizations: Optional[int], batch_size: int,
              device: str) -> None:
    r"""Checks the arguments of a run over test realizations that the data
    or torch would otherwise refuse only midway, or with an error that
    names none of them: positive integers :obj:`realizations` (or
    :obj:`None`: every window of a real sequence) and :obj:`batch_size`,
    and a :obj:`device` of this machine
    (:func:`~tg_nebp.utils.check_device`)."""
    if realizations is not None:
        check_positive_int(realizations, 'realizations')
    check_positive_int(batch_size, 'batch_size')
    check_device(device)


def checked_models(tracker: Tracker,
                   scenario: Union[Scenario, MRCLAMScenario],
                   checkpoint: str) -> Tracker:
    r"""A learned tracker from :obj:`checkpoint`, which tracks with the
    models it was trained with, checked against the data of
    :obj:`scenario`: another kind of state or input (another motion model)
    or other link features is a :class:`ValueError` naming both; other
    parameters or another likelihood of the same features (the
    model-mismatch experiments: trained on line-of-sight ranges, tested
    on NLOS ones) are used with a :class:`UserWarning` that names both."""
    motion, measurement = scenario.motion_model, scenario.measurement_model
    if (tracker.motion.name != motion.name
            or tracker.motion.state_dim != motion.state_dim
            or len(tracker.measurement.features) != len(
                measurement.features)):
        raise ValueError(
            f"checkpoint '{checkpoint}' was trained for {tracker.motion.name} "
            f"motion and the link features "
            f"{list(tracker.measurement.features)}, but the data of scenario "
            f"'{scenario.name}' are {motion.name} with "
            f"{list(measurement.features)}: train one on them (tg-nebp train "
            f"--scenario ...)")
    if (tracker.motion.config() != motion.config()
            or tracker.measurement.config() != measurement.config()):
        warnings.warn(
            f"checkpoint '{checkpoint}' tracks with the models it was "
            f"trained with ({tracker.motion}, {tracker.measurement}), not "
            f"those of scenario '{scenario.name}' ({motion}, "
            f"{measurement})", UserWarning, stacklevel=3)
    return tracker


def _given(**options) -> dict:
    # the options given, so that the others take the tracker's own default
    return {name: value for name, value in options.items()
            if value is not None}


def method_tracker(method: str, scenario: Scenario, *,
                   options: Optional[MethodOptions] = None, **given
                   ) -> Tuple[Union[Tracker, PosteriorCRB], str]:
    r"""The tracker of :obj:`method` (one of
    :data:`~tg_nebp.experiments.options.METHODS`) for the data of
    :obj:`scenario`, and its :obj:`metrics.json` key, with the
    :obj:`options` (a :class:`~tg_nebp.experiments.options.MethodOptions`
    or a mapping of its fields, or its fields as keywords :obj:`given`;
    both: the keywords replace the record's), checked once (:meth:`MethodOptions.check
    <tg_nebp.experiments.options.MethodOptions.check>`). The options left
    at :obj:`None` take each method's default: particle BP with 1,000
    particles, one iteration, receiver-only messages and the multinomial
    resampler; NEBP and Gaussian NEBP as their checkpoints say (for
    Gaussian NEBP a name of :data:`~tg_nebp.training.PRETRAINED` is the
    shipped checkpoint; :obj:`iterations` and :obj:`tolerance` replace its
    own);
    :meth:`GaussianBP.recommended() <tg_nebp.filters.GaussianBP.recommended>`
    (a :obj:`tolerance` of 0 runs every iteration; with :obj:`adapt_noise`
    its :class:`~tg_nebp.filters.NoiseAdaptation` at the defaults, as
    hybrid BP's); the IEKF with 5
    Gauss-Newton iterations. A given value is used or refused, never
    replaced: an option that :obj:`method` does not take
    (:data:`~tg_nebp.experiments.options.METHOD_OPTIONS`) is a
    :class:`ValueError`, and so is a count below one. Particle BP with
    more than one iteration and receiver-only messages is refused: the
    senders' beliefs already hold the receivers' information, and each
    iteration would count it again. With
    :obj:`no_control` the method ignores the realizations' known inputs
    (odometry): every step is the motion model's input-free prediction
    (:attr:`Tracker.use_control <tg_nebp.filters.Tracker.use_control>`).
    The bound takes :obj:`measurement` too: the floor of an estimator
    that reads only that likelihood's features (the range alone of a
    range-bearing link).

    With a :obj:`lag` :math:`L` (steps in the window, the newest counted)
    the method smooths: :obj:`gbp` is
    :class:`~tg_nebp.filters.FixedLagGaussianBP` (recommended otherwise),
    :obj:`iekf` the :class:`~tg_nebp.filters.CentralizedSmoother` and
    :obj:`pcrb` the smoothing bound at that lag (keys
    :obj:`"gbp-lagL"`, :obj:`"iekf-lagL"`, :obj:`"pcrb-lagL"`);
    :obj:`lag="all"` (:data:`~tg_nebp.experiments.options.WHOLE_SEQUENCE`)
    is the full smoother and its bound (:obj:`"iekf-smoother"`,
    :obj:`"pcrb-smoother"`).

    :obj:`hybrid` is :class:`~tg_nebp.filters.HybridBP`
    (:obj:`HYBRID_RECOMMENDED`, :obj:`particles` per agent) over Gaussian
    BP (recommended, with :obj:`iterations`, :obj:`inflation`,
    :obj:`tolerance`), over fixed-lag Gaussian BP with a :obj:`lag` of
    more than one step (its filtered estimates; key
    :obj:`"hybrid-lagL"`), or over the Gaussian NEBP of a
    :obj:`checkpoint` (key :obj:`"hybrid-gnebp"`)."""
    if options is None:
        options = MethodOptions.of(given)
    else:
        if isinstance(options, Mapping):  # the record's fields by name
            options = MethodOptions.of(options)
        if not isinstance(options, MethodOptions):
            raise TypeError(f"'options' must be a MethodOptions or a mapping "
                            f"of its fields, got {options!r}")
        options = dataclasses.replace(options, **given)
    options = options.check(method)
    tracker, key = _method_tracker(method, scenario, options)
    tracker.use_control = not options.no_control
    # its own metrics.json entry: the run with the inputs stays
    return tracker, key + ('-no-control' if options.no_control else '')


def _method_tracker(method: str, scenario, options: MethodOptions):
    # the tracker of a method and its checked options, and its key
    if not isinstance(scenario, SCENARIO_TYPES):
        raise TypeError(f"'scenario' must be a Scenario or an "
                        f"MRCLAMScenario, got {scenario!r}")
    lag, iterations = options.lag, options.iterations
    window = None if lag == WHOLE_SEQUENCE else lag
    models = dict(motion=scenario.motion_model,
                  measurement=tracker_measurement(scenario,
                                                  options.measurement))
    if method == 'pcrb':
        if lag is None:
            return PosteriorCRB(**models), 'pcrb'
        return PosteriorCRB(**models, lag=window), 'pcrb' + lag_key(lag)
    if method == 'iekf':
        if options.incremental:
            return IncrementalSmoother(
                **_given(num_iterations=iterations),
                **models), 'iekf-incremental'
        if options.escape:
            return escaping_smoother(
                **models, **_given(num_iterations=iterations)
            ), 'iekf-smoother-escape'
        if lag is not None:
            return CentralizedSmoother(
                window, **_given(num_iterations=iterations),
                **models), 'iekf' + lag_key(lag)
        tracker = CentralizedIEKF(**_given(num_iterations=iterations),
                                  marginal=options.marginal, **models)
        return tracker, 'iekf-marginal' if options.marginal else 'iekf'
    if method == 'gbp':
        given = _given(num_iterations=iterations,
                       inflation=options.inflation, ends=options.ends,
                       tolerance=options.tolerance,
                       report_inflation=options.report_inflation,
                       noise_adaptation=_adaptation(options))
        if given.get('tolerance') == 0:  # every iteration
            given['tolerance'] = None
        if lag is not None:
            return FixedLagGaussianBP.recommended(
                lag=lag, **given, compile=options.compile,
                **models), 'gbp' + lag_key(lag)
        return GaussianBP.recommended(**given, compile=options.compile,
                                      **models), 'gbp'
    checkpoint = options.checkpoint
    if method == 'gnebp':
        if checkpoint is None:
            raise ValueError(f"method 'gnebp' needs a checkpoint "
                             f"(--checkpoint PATH, or one shipped: "
                             f"{', '.join(PRETRAINED)})")
        given = _given(num_iterations=iterations,
                       tolerance=options.tolerance)
        if given.get('tolerance') == 0:  # every iteration
            given['tolerance'] = None
        tracker = checked_models(gaussian_nebp_from_checkpoint(
            checkpoint, **given), scenario, checkpoint)
        # the correction trained in a window: its filtered estimates
        return tracker, 'gnebp' + (lag_key(tracker.lag) if isinstance(
            tracker, FixedLagGaussianNEBP) else '')
    if method == 'hybrid':
        return _hybrid(scenario, models, checkpoint, options.particles, lag,
                       _given(num_iterations=iterations,
                              inflation=options.inflation,
                              tolerance=options.tolerance,
                              report_inflation=options.report_inflation,
                              noise_adaptation=_adaptation(options)),
                       options.measurement)
    if method == 'nebp':
        if checkpoint is None:
            raise ValueError("method 'nebp' needs a checkpoint (--checkpoint "
                             "PATH)")
        return checked_models(nebp_from_checkpoint(
            checkpoint, options.particles, compile=options.compile,
            num_samples=options.samples), scenario, checkpoint), 'nebp'
    # receiver-only messages are particle BP's default
    if iterations is not None and iterations > 1 and options.ends in (
            None, 'receiver'):
        raise ValueError(
            f"--iterations {iterations} with --ends receiver counts the "
            f"receivers' own information again at every iteration (the "
            f"senders' beliefs already hold it); use --ends both, whose "
            f"iterations send extrinsic messages")
    given = _given(num_particles=options.particles,
                   num_iterations=iterations, resampler=options.resampler,
                   num_samples=options.samples,
                   regularize=options.regularize,
                   ess_threshold=options.ess_threshold, ends=options.ends,
                   report_inflation=options.report_inflation)
    return ParticleBP(**given, compile=options.compile, **models), 'bp'


def _adaptation(options: MethodOptions) -> Optional[NoiseAdaptation]:
    # the noise adaptation of --adapt-noise, at its defaults
    return NoiseAdaptation() if options.adapt_noise else None


def _hybrid(scenario, models: dict, checkpoint: Optional[str],
            particles: Optional[int], lag, given: dict,
            measurement: Optional[str]) -> Tuple[HybridBP, str]:
    # hybrid BP over Gaussian BP, a window of it, or a Gaussian NEBP
    # checkpoint, and its metrics.json key
    if given.get('tolerance') == 0:  # every iteration
        given['tolerance'] = None
    if checkpoint is not None:
        for name, value in (('lag', lag), ('inflation',
                                           given.get('inflation')),
                            ('report_inflation',
                             given.get('report_inflation')),
                            ('adapt_noise', given.get('noise_adaptation')),
                            ('measurement', measurement)):
            if value is not None:
                raise ValueError(
                    f"'{name}' and 'checkpoint': hybrid BP over a Gaussian "
                    f"NEBP checkpoint runs it as trained (one step, its "
                    f"learned inflation, its likelihood)")
        gaussian = checked_models(gaussian_nebp_from_checkpoint(
            checkpoint, **given), scenario, checkpoint)
        if isinstance(gaussian, FixedLagGaussianNEBP):
            raise ValueError(
                f"checkpoint '{checkpoint}' holds the correction inside a "
                f"window of {gaussian.lag}: hybrid BP runs over a Gaussian "
                f"NEBP of one step (evaluate it with --method gnebp)")
        gaussian = gaussian.relocate_with(LinkSearch())
        key = 'hybrid-gnebp'
    elif lag is not None and lag > 1:
        gaussian = FixedLagGaussianBP.recommended(
            lag=lag, relocation=LinkSearch(), **given, **models)
        key = 'hybrid' + lag_key(lag)
    else:
        gaussian = GaussianBP.recommended(relocation=LinkSearch(), **given,
                                          **models)
        key = 'hybrid'
    return HybridBP(gaussian, **{**HYBRID_RECOMMENDED,
                                 **_given(num_particles=particles)}), key


def evaluate_scenario(method: str,
                      scenario: Union[str, Scenario, MRCLAMScenario],
                      realizations: Optional[int] = None, seed: int = 0,
                      root: str = 'datasets', out: str = 'results',
                      batch_size: int = 1, device: str = 'cpu',
                      progress_factory: Optional[Callable] = None,
                      options: Optional[MethodOptions] = None,
                      **given) -> dict:
    r"""Generates (or loads) :obj:`realizations` test realizations of
    :obj:`scenario` from :obj:`seed` under :obj:`root` (10 by default; a
    real sequence's windows read from :obj:`root`, every one by default),
    runs
    :func:`method_tracker(method, ..., options=options, **given)
    <method_tracker>` on
    them and merges its entry into :obj:`out/metrics.json`
    (:func:`~tg_nebp.evaluation.evaluate_method`). Under :obj:`torchrun`
    the realizations are sharded over the processes and rank 0 writes.
    The arguments and options are checked (:func:`check_run`,
    :func:`method_tracker`) before any data is made.

    Args:
        progress_factory (callable, optional): :obj:`(total, description)`
            to a context manager whose :obj:`update(n)` is called after
            every time step (a progress bar); :obj:`total` counts this
            process's steps. (default: :obj:`None`)

    A smoother with a window (:obj:`lag` :math:`L`) writes two entries:
    its filtered estimates (the newest step of each window) under its key
    and its smoothed ones (each step's as it leaves the window,
    :class:`~tg_nebp.filters.Smoothed`) under the key with
    :obj:`"-smoothed"`; each is tracked on its own. The tracks of the first
    realization, true, filtered and smoothed, are drawn to
    :obj:`out/tracks-KEY.png` (:func:`~tg_nebp.plot.plot_tracks`; its path
    under :obj:`"tracks"`).

    Returns:
        The result of :func:`~tg_nebp.evaluation.evaluate_method`, its
        :obj:`metrics.json` entry under :obj:`"entry"` and the method's
        key under :obj:`"key"`; every entry written, in order, under
        :obj:`"entries"` (key, entry).
    """
    check_run(realizations, batch_size, device)
    scenario = scenario_of(scenario)
    realizations = realizations_of(scenario, realizations, 10)
    tracker, key = method_tracker(method, scenario, options=options,
                                  **given)
    world_size, rank = process_group()
    dataset, = load_datasets(root, (scenario, realizations, seed))
    share = len(range(rank, len(dataset), world_size))
    runs = [(key, tracker)]
    if isinstance(tracker, IncrementalSmoother) or getattr(
            tracker, 'lag', None) is not None and isinstance(
                tracker, Tracker) and tracker.lag > 1:
        runs.append((key + '-smoothed', Smoothed(tracker)))
    particles = getattr(tracker, 'num_particles', None)
    bar = (progress_factory(share * dataset.scenario.num_steps * len(runs),
                            key + (f' K={particles}' if particles else ''))
           if progress_factory is not None else contextlib.nullcontext())
    entries, tracks = [], {}
    with bar:
        for name, method in runs:
            result = evaluate_method(name, method.to(device).eval(), dataset,
                                     batch_size, device, seed, Path(out),
                                     progress=getattr(bar, 'update', None))
            entries.append((name, result['entry']))
            tracks[name] = result.get('first_mean')
    first = result if len(runs) == 1 else dict(result, entry=entries[0][1])
    first.update(key=key, entries=entries)
    if len(runs) > 1 and process_group()[1] == 0:
        from tg_nebp.plot import plot_tracks
        first['tracks'] = Path(out) / f'tracks-{key}.png'
        plot_tracks(result['first_states'], tracks, result['first_anchor'],
                    first['tracks'])
    return first
