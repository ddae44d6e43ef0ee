r"""One table of every method against the bound: the posterior Cramér-Rao
bound, the centralized iterated EKF (Gaussian and Student-t likelihoods;
joint and marginals-only), Gaussian BP, particle BP (the paper's
configuration and the recommended one) and NEBP from checkpoints, on the
same realizations with the same prior particle draws, with the same metrics,
per-realization spreads and seconds per realization.

Behind :obj:`tg-nebp compare`, which writes :obj:`compare.json` after every
method (an interrupted run resumes where it stopped, and a run with more
checkpoints adds their rows), :obj:`compare.md` and :obj:`compare.png`."""
import contextlib
import hashlib
import os
import time
from pathlib import Path
from typing import (Callable, Dict, Iterable, List, Optional, Sequence,
                    Tuple, Union)

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.data.validation import check_positive_int
from tg_nebp.datasets import MRCLAMScenario, Scenario, load_datasets
from tg_nebp.evaluation import (bound_dataset, spread, summarize_result,
                                track_dataset)
from tg_nebp.experiments.evaluate import (SCENARIO_TYPES, check_run,
                                          escaping_smoother, lag_key,
                                          realizations_of, scenario_of)
from tg_nebp.experiments.options import WHOLE_SEQUENCE
from tg_nebp.filters import (HYBRID_RECOMMENDED, CentralizedIEKF,
                             CentralizedSmoother, FixedLagGaussianBP,
                             GaussianBP, HybridBP, IncrementalSmoother,
                             LinkSearch, ParticleBP, Smoothed, Tracker)
from tg_nebp.io import Number, read_resumable, write_json, write_text
from tg_nebp.models import model_like

__all__ = ['compare_methods', 'run_compare', 'compare', 'compare_table',
           'compare_points', 'floor_ratios', 'floor_row', 'row_schema',
           'COMPARE_VERSION', 'COMPARE_SCENARIOS', 'BOUND',
           'CHECKPOINT_ROWS', 'SMOOTHED']

#: The format version of :obj:`compare.json`.
COMPARE_VERSION = 1
#: The scenarios of the default table, the paper's test network and the
#: same with NLOS links.
COMPARE_SCENARIOS = ('paper_test', 'paper_test_nlos')
#: The key of the bound's row.
BOUND = 'pcrb'
#: The end of the first word of a smoother's row of smoothed estimates.
SMOOTHED = '-smoothed'
#: The suffix of the full smoother's row that escapes its filter's basin
#: (two starts, :class:`~tg_nebp.filters.GroupExchange` and
#: :class:`~tg_nebp.filters.ParticleTrajectorySearch`).
ESCAPE = '-escape'
#: The suffix of a bound of the ranges alone (a scenario with bearings)
RANGE_ONLY = '-range-only'
#: The first word of a checkpoint's row, by the checkpoint's base.
CHECKPOINT_ROWS = {'particle': 'nebp', 'gaussian': 'gnebp'}

Method = Union[Tracker, PosteriorCRB]


def _file_hash(path: Union[str, Path]) -> str:
    digest = hashlib.sha256()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 20), b''):
            digest.update(block)
    return digest.hexdigest()[:10]


def compare_methods(scenario: Scenario,
                    checkpoints: Sequence[Union[str, Path]] = (),
                    lag: Optional[int] = None
                    ) -> Dict[str, Tuple[str, Callable[[], Method]]]:
    r"""The rows of the table on :obj:`scenario`, in order, each a
    description and a function that builds the method: the bound
    (:obj:`"pcrb"`), the centralized IEKF with the Gaussian, the Student-t
    and (where it is another) the scenario's own likelihood, joint
    (:obj:`"iekf ..."`) and marginals-only (:obj:`"iekf-marginal ..."`),
    Gaussian BP with the same likelihoods, recommended (:obj:`"gbp ..."`,
    :meth:`GaussianBP.recommended <tg_nebp.filters.GaussianBP.recommended>`)
    and without inflation (:obj:`"gbp-plain ..."`), particle BP in the
    paper's configuration at :math:`K = 1000`
    (:obj:`"bp-paper ..."`), hybrid BP over Gaussian BP
    (:obj:`"hybrid ..."`, :meth:`HybridBP.recommended
    <tg_nebp.filters.HybridBP.recommended>`) and the recommended one
    (:obj:`"bp-recommended ..."`, :meth:`ParticleBP.recommended
    <tg_nebp.filters.ParticleBP.recommended>`), both with the scenario's
    likelihood, and NEBP from every checkpoint, particle
    (:obj:`"nebp <file> <hash>"`) or Gaussian (:obj:`"gnebp <file>
    <hash>"`, and hybrid BP over it, :obj:`"hybrid-gnebp <file>
    <hash>"`; one trained in a window of :math:`L` steps,
    :class:`~tg_nebp.filters.FixedLagGaussianNEBP`, as a smoother's two
    rows, :obj:`"gnebp-lagL <file> <hash>"` and :obj:`"gnebp-lagL-smoothed
    <file> <hash>"`; a name of :data:`~tg_nebp.training.PRETRAINED` is the
    shipped checkpoint): the file's hash is part of the key, so a changed
    checkpoint is a new row.

    With a :obj:`lag` :math:`L \geq 2` the smoothers join the table, each
    as two rows, its filtered estimates and its smoothed ones (the key's
    first word ending in :obj:`"-smoothed"`): the smoothing bounds at lag
    :math:`L` (:obj:`"pcrb-lagL"`; on a scenario with bearings, that of
    the ranges alone too, :obj:`"pcrb-lagL-range-only"`, the floor of the
    range-only rows) and of the whole sequence
    (:obj:`"pcrb-smoother"`), the centralized fixed-lag smoother with the
    scenario's likelihood (:obj:`"iekf-lagL ..."`), the full one
    (:obj:`"iekf-smoother ..."`; :obj:`"iekf-smoother-escape ..."`,
    :func:`~tg_nebp.experiments.evaluate.escaping_smoother`: from the
    better of the incremental smoother's last step and a window's
    smoothed estimates, groups exchanged between both, groups flipped
    across their outside neighbours' line, with the search of better
    basins) and the
    incremental one (:obj:`"iekf-incremental ..."`, filtered and
    smoothed), and fixed-lag Gaussian BP with every
    likelihood of Gaussian BP (:obj:`"gbp-lagL ..."`,
    :class:`~tg_nebp.filters.FixedLagGaussianBP`, recommended), and
    hybrid BP over it (:obj:`"hybrid-lagL ..."`, filtered)."""
    from tg_nebp.training import (checkpoint_base, checkpoint_path,
                                  load_checkpoint, tracker_from_checkpoint,
                                  window_lag)

    motion, own = scenario.motion_model, scenario.measurement_model
    methods = {BOUND: ('the posterior CRB: the floor, and an efficient '
                       "estimator's outage",
                       lambda: PosteriorCRB(motion, own))}
    if 'bearing' in own.features:
        # the robust variant, and the range alone (the bearing's worth)
        likelihoods = ['range-bearing', 'student-t-range-bearing',
                       'gaussian']
        range_only = model_like('gaussian', 'measurement', own)
        methods[f'{BOUND}{RANGE_ONLY}'] = (
            'the posterior CRB of the ranges alone (no bearing)',
            lambda: PosteriorCRB(motion, range_only))
    elif len(own.features) > 1:
        # a likelihood that reads more than the range (each link's sensor,
        # StudentTRangeBySensor's): no one-scale alternative describes its
        # links, so its own rows alone
        likelihoods = []
    else:
        likelihoods = ['gaussian', 'student-t']
    if own.name not in likelihoods:
        likelihoods.append(own.name)
    suffix = None if lag is None else lag_key(lag)
    if lag is not None:
        methods[BOUND + suffix] = (
            f'the smoothing bound at lag {lag} (the measurements up to '
            f't + {lag - 1})',
            lambda: PosteriorCRB(motion, own, lag=lag))
        methods[BOUND + lag_key(WHOLE_SEQUENCE)] = (
            'the smoothing bound of the whole sequence',
            lambda: PosteriorCRB(motion, own, lag=None))
        if 'bearing' in own.features:
            methods[f'{BOUND}{suffix}{RANGE_ONLY}'] = (
                f'the smoothing bound at lag {lag} of the ranges alone',
                lambda: PosteriorCRB(motion, range_only, lag=lag))
    shown = {likelihood: likelihood for likelihood in likelihoods}
    if 'bearing' in own.features:
        shown['gaussian'] = 'gaussian range-only'
    # a motion model with known inputs: the rows without them (what the
    # odometry is worth). No bound beside them: without its inputs the
    # model's prediction (a random walk for odometry) is not the data's
    # motion, so its bound is no floor of these data
    blind = [] if motion.control_dim == 0 else [
        (f'iekf-no-odometry {own.name}', 'centralized IEKF without odometry',
         lambda: CentralizedIEKF(motion=motion, measurement=own)),
        (f'gbp-no-odometry {own.name}',
         'Gaussian BP, recommended, without odometry',
         lambda: GaussianBP.recommended(motion=motion, measurement=own)),
        (f'bp-recommended-no-odometry {own.name}',
         'particle BP, recommended, without odometry',
         lambda: ParticleBP.recommended(motion=motion, measurement=own))]
    for marginal in (False, True):
        name = 'iekf-marginal' if marginal else 'iekf'
        what = ('centralized IEKF, marginals only (the distributed ideal)'
                if marginal else 'centralized IEKF')
        for likelihood in likelihoods:
            measurement = model_like(likelihood, 'measurement', own)
            methods[f'{name} {likelihood}'] = (
                f'{what}, {shown[likelihood]} likelihood',
                lambda m=measurement, marginal=marginal: CentralizedIEKF(
                    motion=motion, measurement=m, marginal=marginal))
    if lag is not None:
        methods[f'iekf{suffix} {own.name}'] = (
            f'centralized fixed-lag smoother (window {lag}), filtered',
            lambda: CentralizedSmoother(lag, motion=motion, measurement=own))
        methods[f'iekf{suffix}{SMOOTHED} {own.name}'] = (
            f'centralized fixed-lag smoother (window {lag}), smoothed',
            lambda: Smoothed(CentralizedSmoother(lag, motion=motion,
                                                 measurement=own)))
        methods[f'iekf-incremental {own.name}'] = (
            'centralized incremental smoother (iSAM2-like), filtered: each '
            "step's newest states, the past relinearized",
            lambda: IncrementalSmoother(motion=motion, measurement=own))
        methods[f'iekf-incremental{SMOOTHED} {own.name}'] = (
            'centralized incremental smoother (iSAM2-like), smoothed',
            lambda: Smoothed(IncrementalSmoother(motion=motion,
                                                 measurement=own)))
        methods[f'iekf{lag_key(WHOLE_SEQUENCE)} {own.name}'] = (
            'centralized full smoother (Gauss-Newton over all steps)',
            lambda: CentralizedSmoother(None, motion=motion,
                                        measurement=own))
        methods[f'iekf{lag_key(WHOLE_SEQUENCE)}{ESCAPE} {own.name}'] = (
            "centralized full smoother from the better of the incremental "
            "smoother's last step and a window's smoothed estimates, groups "
            "of agents exchanged between both optima (GroupExchange), groups "
            "that range to no anchor flipped across their outside "
            "neighbours' line (GroupFlip), every agent's trajectory searched "
            "for a better basin "
            "(ParticleTrajectorySearch)",
            lambda: escaping_smoother(motion, own))
    for likelihood in likelihoods:
        measurement = model_like(likelihood, 'measurement', own)
        methods[f'gbp {likelihood}'] = (
            f'Gaussian BP, recommended (inflation 1.5, reported 2.5), '
            f'{shown[likelihood]} likelihood',
            lambda m=measurement: GaussianBP.recommended(
                motion=motion, measurement=m))
        methods[f'gbp-plain {likelihood}'] = (
            f'Gaussian BP without inflation, {shown[likelihood]} likelihood',
            lambda m=measurement: GaussianBP.recommended(
                inflation=1.0, report_inflation=1.0, motion=motion,
                measurement=m))
    for likelihood in likelihoods if lag is not None else ():
        measurement = model_like(likelihood, 'measurement', own)
        methods[f'gbp{suffix} {likelihood}'] = (
            f'fixed-lag Gaussian BP (window {lag}), recommended, filtered, '
            f'{shown[likelihood]} likelihood',
            lambda m=measurement: FixedLagGaussianBP.recommended(
                lag=lag, motion=motion, measurement=m))
        methods[f'gbp{suffix}{SMOOTHED} {likelihood}'] = (
            f'fixed-lag Gaussian BP (window {lag}), recommended, smoothed, '
            f'{shown[likelihood]} likelihood',
            lambda m=measurement: Smoothed(FixedLagGaussianBP.recommended(
                lag=lag, motion=motion, measurement=m)))
    methods[f'hybrid {own.name}'] = (
        'hybrid BP over Gaussian BP, recommended (K = 50)',
        lambda: HybridBP.recommended(motion=motion, measurement=own))
    if lag is not None:
        methods[f'hybrid{suffix} {own.name}'] = (
            f'hybrid BP over fixed-lag Gaussian BP (window {lag}), '
            f'filtered',
            lambda: HybridBP.recommended(lag=lag, motion=motion,
                                         measurement=own))
    methods[f'bp-paper {own.name}'] = (
        "particle BP, the paper's configuration (K = 1,000, M = 1)",
        lambda: ParticleBP(1000, motion=motion, measurement=own))
    methods[f'bp-recommended {own.name}'] = (
        'particle BP, recommended (K = 500, M = 32, regularized)',
        lambda: ParticleBP.recommended(motion=motion, measurement=own))
    for key, what, build in blind:
        methods[key] = (what, lambda build=build: _without_control(build()))
    for path in checkpoints:
        path = checkpoint_path(path)
        if not path.is_file():
            raise ValueError(f"the NEBP checkpoint '{path}' does not exist")
        base = checkpoint_base(path)
        kind = CHECKPOINT_ROWS[base]
        window = window_lag(load_checkpoint(path)['config'])
        if window is not None:
            # the correction inside a window: a smoother's two rows, and
            # the smoothing bound at its own lag that divides the smoothed
            # one (where the table's lag is another, or none)
            name = f'{kind}{lag_key(window)}'
            methods.setdefault(BOUND + lag_key(window), (
                f'the smoothing bound at lag {window} (the measurements up '
                f'to t + {window - 1})',
                lambda window=window: PosteriorCRB(motion, own,
                                                   lag=window)))
            methods[f'{name} {path.name} {_file_hash(path)}'] = (
                f'Gaussian NEBP in a window of {window} from {path}, '
                f'filtered', lambda path=path: tracker_from_checkpoint(path))
            methods[f'{name}{SMOOTHED} {path.name} {_file_hash(path)}'] = (
                f'Gaussian NEBP in a window of {window} from {path}, '
                f'smoothed',
                lambda path=path: Smoothed(tracker_from_checkpoint(path)))
            continue
        methods[f'{kind} {path.name} {_file_hash(path)}'] = (
            f'{"Gaussian " if base == "gaussian" else ""}NEBP from {path}',
            lambda path=path: tracker_from_checkpoint(path))
        if base == 'gaussian':  # the learned correction inside hybrid BP
            methods[f'hybrid-{kind} {path.name} {_file_hash(path)}'] = (
                f'hybrid BP over Gaussian NEBP from {path}',
                lambda path=path: HybridBP(tracker_from_checkpoint(
                    path).relocate_with(LinkSearch()), **HYBRID_RECOMMENDED))
    return methods


def _without_control(method: Method) -> Method:
    method.use_control = False
    return method


_PROBABILITY, _NON_NEGATIVE = Number(0.0, 1.0), Number(0.0)


def row_schema(realizations: int, bound: bool = False) -> dict:
    r"""What every row of :obj:`compare.json` made with :obj:`realizations`
    realizations holds, as the table and the figure read it, values
    included (:func:`~tg_nebp.io.read_resumable`): probabilities in
    :math:`[0, 1]`, finite non-negative RMSEs, deviations and seconds, and
    one :obj:`[P_out(1 m), P(accept 0.95), RMSE]` per realization
    (:func:`~tg_nebp.evaluation.spread`). The :obj:`bound`'s RMSEs per
    realization are the floors that divide the others'
    (:func:`floor_ratios`): positive."""
    probabilities = dict(mean=_PROBABILITY, std=_NON_NEGATIVE)
    realization = [_PROBABILITY, _PROBABILITY, Number(0.0, positive=bound)]
    return dict(method=str, rmse=_NON_NEGATIVE,
                seconds_per_realization=_NON_NEGATIVE,
                outage={'0.5': _PROBABILITY, '1.0': _PROBABILITY,
                        '2.0': _PROBABILITY},
                accept={'0.95': _PROBABILITY, '0.99': _PROBABILITY},
                spread={'realizations': [realization] * realizations,
                        'outage_1m': probabilities,
                        'accept_0.95': probabilities,
                        'rmse': dict(mean=_NON_NEGATIVE, std=_NON_NEGATIVE)})


def _settings(datasets, seed: int, device: str) -> dict:
    # what every row of one file shares; a scenario is its fingerprint (every
    # generation parameter), not its name
    return dict(version=COMPARE_VERSION, realizations=len(datasets[0]),
                seed=seed, device=device,
                scenarios={d.scenario.name: d.scenario.fingerprint()
                           for d in datasets})


def _run_one(method: Method, dataset, seed: int, device: str,
             batch_size: int, progress: Optional[Callable]) -> dict:
    load = os.getloadavg()[0]
    method = method.to(device).eval()
    start = time.perf_counter()
    if isinstance(method, PosteriorCRB):
        result = bound_dataset(method, dataset, batch_size, device, seed,
                               progress)
    else:
        result = track_dataset(method, dataset, batch_size, device, seed,
                               progress)
    seconds = time.perf_counter() - start
    entry = summarize_result(result)
    entry.update(spread=spread(result), seconds=round(seconds, 3),
                 seconds_per_realization=round(seconds / len(dataset), 4),
                 load_average=round(load, 2))
    return entry


def run_compare(root: str = 'datasets',
                scenarios: Sequence[Union[str, Scenario, MRCLAMScenario]
                                    ] = COMPARE_SCENARIOS,
                realizations: Optional[int] = None, seed: int = 0,
                out: Union[str, Path] = 'results/compare',
                checkpoints: Sequence[Union[str, Path]] = (),
                device: str = 'cpu', batch_size: int = 1,
                methods: Optional[Sequence[str]] = None,
                progress: Optional[Callable] = None,
                log: Callable = print, lag: Optional[int] = None) -> dict:
    r"""Runs every method of :func:`compare_methods` on
    :obj:`realizations` realizations of every scenario (seed
    :obj:`seed`) and returns the content of :obj:`out/compare.json`,
    written after every method.

    Every method sees the same realizations and, through
    :func:`~tg_nebp.evaluation.track_dataset` with :obj:`seed`, the same
    prior particle draws. Rows already in the file are skipped (resuming,
    or adding checkpoints), unless their method's description has changed
    since (the method is then another: its row is run again), as long as
    it was made with the same
    realizations, seed, device and scenarios (compared by their
    :meth:`~tg_nebp.datasets.Scenario.fingerprint`, so a scenario file
    changed under the same name is not mixed in); another file is an
    error, and so is a damaged one (every row is checked against
    :func:`row_schema`). Each row holds the accuracy
    (:func:`~tg_nebp.evaluation.summarize_result`), its spread over the
    realizations (:func:`~tg_nebp.evaluation.spread`), the seconds per
    realization and the load average when it started. The scenarios and
    their rows are in the order of :obj:`scenarios` and
    :func:`compare_methods`, in the result and in the file, also after a
    resume; rows of checkpoints not given this time follow.

    Before any work, the arguments are checked: two scenarios of one
    name (the file's rows are keyed by name), a prefix of :obj:`methods`
    that selects no row, a checkpoint whose row it leaves out, one value
    where a list belongs (a string is not a list of its letters) and the
    arguments of :func:`~tg_nebp.experiments.evaluate.check_run` are
    errors.

    Args:
        root (str, optional): Dataset root. (default: :obj:`"datasets"`)
        scenarios (sequence, optional): Scenario names, files or
            :class:`~tg_nebp.datasets.Scenario` objects, of distinct names;
            real sequences (:obj:`"mrclam-6"`,
            :class:`~tg_nebp.datasets.MRCLAMScenario`) are read from
            :obj:`root`. (default: :obj:`COMPARE_SCENARIOS`)
        realizations (int, optional): Realizations per scenario: 20 by
            default, every window of a real sequence; all scenarios must
            hold as many. (default: :obj:`None`)
        seed (int, optional): Seed of the data and the particle draws.
            (default: :obj:`0`)
        out (str or Path, optional): Folder of :obj:`compare.json`.
            (default: :obj:`"results/compare"`)
        checkpoints (sequence, optional): NEBP checkpoints, one row each.
            (default: :obj:`()`)
        device (str, optional): Device. (default: :obj:`"cpu"`)
        batch_size (int, optional): Realizations tracked together.
            (default: :obj:`1`)
        methods (sequence of str, optional): Run only the rows whose key
            starts with one of these (for example :obj:`["pcrb", "iekf"]`);
            all if :obj:`None`. (default: :obj:`None`)
        progress (callable, optional): Called with the number of
            realization-steps done. (default: :obj:`None`)
        log (callable, optional): Receives one line per row.
            (default: :obj:`print`)
        lag (int, optional): With a window of :math:`L \geq 2` steps, the
            smoothers' rows (:func:`compare_methods`). (default: :obj:`None`)
    """
    scenarios = _listed(scenarios, 'scenarios',
                        (str, os.PathLike) + SCENARIO_TYPES,
                        'a scenario name, a JSON file or a Scenario')
    checkpoints = _listed(checkpoints, 'checkpoints', (str, os.PathLike),
                          'a path')
    if methods is not None:
        methods = _listed(methods, 'methods', (str, ), 'a str')
    check_run(realizations, batch_size, device)
    if lag is not None and check_positive_int(lag, 'lag') < 2:
        raise ValueError(f"'lag' must be at least 2 (a window of one step "
                         f"is the filter), got {lag}")
    if not scenarios:
        raise ValueError("'scenarios' is empty: name at least one")
    if methods == []:
        raise ValueError("'methods' is empty: give the prefixes of the rows "
                         "to run, or None for all")
    loaded = [scenario_of(spec) for spec in scenarios]
    _check_names(scenarios, loaded)
    # every row of every scenario, in order; the selected ones are built
    # (their options and checkpoints checked) before the first one runs
    rows = {s.name: compare_methods(s, checkpoints, lag) for s in loaded}
    if methods is not None:
        _check_methods(methods, rows, checkpoints)
    plan = [(name, key, what, build()) for name, table in rows.items()
            for key, (what, build) in table.items()
            if methods is None or any(key.startswith(m) for m in methods)]
    order = {name: list(table) for name, table in rows.items()}
    datasets = load_datasets(root, *((s, realizations_of(s, realizations,
                                                         20), seed)
                                     for s in loaded))
    realizations = len(datasets[0])
    uneven = next((d for d in datasets if len(d) != realizations), None)
    if uneven is not None:
        raise ValueError(
            f"the scenarios of one table must hold as many realizations: "
            f"{datasets[0].scenario.name} has {realizations}, "
            f"{uneven.scenario.name} {len(uneven)} (give --realizations)")
    path = Path(out) / 'compare.json'
    settings = _settings(datasets, seed, device)
    result = read_resumable(
        path, settings, 'results', 'a comparison',
        lambda key: row_schema(realizations, bound=floor_row(key) == key),
        depth=2)
    stranger = next((name for name in result['results']
                     if name not in settings['scenarios']), None)
    if stranger is not None:
        raise ValueError(f"'{path}' is damaged: 'results'[{stranger!r}] is "
                         f"no scenario of its settings; remove the file to "
                         f"start again")
    result['results'] = _in_order(result['results'], order)
    by_name = {d.scenario.name: d for d in datasets}
    for name, key, what, method in plan:
        dataset = by_name[name]
        steps = len(dataset) * dataset.scenario.num_steps
        stored = result['results'].get(name, {}).get(key)
        if stored is not None and stored.get('method', what) == what:
            if progress is not None:
                progress(steps)
            continue
        if stored is not None:
            log(f"{name}: {key}: the method has changed since its row was "
                f"written ({stored['method']!r}): run again")
        entry = _run_one(method, dataset, seed, device, batch_size, progress)
        entry['method'] = what
        result['results'].setdefault(name, {})[key] = entry
        result['results'] = _in_order(result['results'], order)
        # the keys in the table's order: JSON readers keep it
        write_json(path, result, sort_keys=False)
        log(f"{name}: {key}: P_out(1 m) {entry['outage']['1.0']:.4f}, "
            f"P(accept 0.95) {entry['accept']['0.95']:.3f}, RMSE "
            f"{entry['rmse']:.3f} m, {entry['seconds_per_realization']:.2f} "
            f"s per realization")
    return result


def _listed(value, name: str, kinds: tuple, what: str) -> list:
    # one value where a list belongs would be iterated item by item (a
    # string letter by letter): refused, as is an item of another type
    if (isinstance(value, (str, bytes, os.PathLike) + SCENARIO_TYPES)
            or not isinstance(value, Iterable)):
        raise TypeError(f"'{name}' must be a list, each item {what}, got "
                        f"{value!r}")
    items = list(value)
    for i, item in enumerate(items):
        if not isinstance(item, kinds):
            raise TypeError(f"'{name}'[{i}] must be {what}, got {item!r}")
    return items


def _check_names(specs: list, scenarios: List[Scenario]) -> None:
    # compare.json keys the rows by scenario name: a second scenario of a
    # name would be skipped as done, under the first one's numbers
    first = {}
    for spec, scenario in zip(specs, scenarios):
        given = ('a Scenario' if isinstance(spec, SCENARIO_TYPES)
                 else f"'{spec}'")
        if scenario.name in first:
            raise ValueError(
                f"the scenarios {first[scenario.name]} and {given} are both "
                f"named '{scenario.name}' (compare.json keys its rows by "
                f"scenario name): give each scenario its own name")
        first[scenario.name] = given


def _check_methods(methods: List[str], rows: Dict[str, dict],
                   checkpoints: list) -> None:
    # every prefix selects a row of some scenario, and every checkpoint's
    # row is selected: a value given is used or refused
    keys = [key for table in rows.values() for key in table]
    for i, prefix in enumerate(methods):
        if any(key.startswith(prefix) for key in keys):
            continue
        if not checkpoints and any(kind.startswith(prefix)
                                   or prefix.startswith(kind)
                                   for kind in CHECKPOINT_ROWS.values()):
            raise ValueError(f"'methods'[{i}] = {prefix!r} selects NEBP's "
                             f"rows, which need a checkpoint ('checkpoints',"
                             f" --checkpoint PATH)")
        known = list(dict.fromkeys(key.split(' ')[0] for key in keys))
        raise ValueError(
            f"'methods'[{i}] = {prefix!r} selects no row of any scenario; "
            f"the rows start with {', '.join(known)}"
            + ('' if checkpoints else ' (and nebp or gnebp, with a '
                                      'checkpoint)'))
    unused = next((key for key in keys
                   if key.split(' ')[0] in CHECKPOINT_ROWS.values()
                   and not any(key.startswith(m) for m in methods)), None)
    if unused is not None:
        raise ValueError(f"the checkpoint of the row '{unused}' was given, "
                         f"but 'methods' does not select its row: add "
                         f"'{unused.split(' ')[0]}' or leave the checkpoint "
                         f"out")


def _in_order(results: Dict[str, dict],
              order: Dict[str, List[str]]) -> Dict[str, dict]:
    # the scenarios in their given order and the rows of each in that of
    # compare_methods: a resumed file's new rows where they belong, not at
    # its end, and a file of sorted keys (as earlier versions wrote it) in
    # order again; rows the plan does not know (of checkpoints not given
    # this time) stay, after them
    ordered = {}
    for name in [*order, *results]:
        if name in results and name not in ordered:
            rows = results[name]
            known = [key for key in order.get(name, ()) if key in rows]
            ordered[name] = {key: rows[key] for key in
                             known + [k for k in rows if k not in known]}
    return ordered


def floor_row(key: str) -> str:
    r"""The key of the bound row that a row's RMSE is divided by: a
    smoother's smoothed estimates (:obj:`"...-lagL-smoothed ..."`) by the
    smoothing bound at its lag (:obj:`"pcrb-lagL"`), the full smoother
    (:obj:`"iekf-smoother ..."`) and the incremental smoother's smoothed
    row (:obj:`"iekf-incremental-smoothed ..."`), and the full smoother
    with its search (:obj:`"iekf-smoother-escape ..."`) by that of the whole
    sequence (:obj:`"pcrb-smoother"`), a smoothing bound by itself, every other row
    (filters, and the smoothers' filtered estimates) by the filtering
    bound (:data:`BOUND`)."""
    first = key.split(' ')[0]
    whole = lag_key(WHOLE_SEQUENCE)
    if first.startswith(BOUND + '-lag') or first == BOUND + whole:
        return first
    if first.endswith(whole) or first.endswith(whole + ESCAPE):
        return BOUND + whole
    if first.endswith(SMOOTHED):
        window = first[:-len(SMOOTHED)]
        if '-lag' not in window:  # the incremental smoother's: every step
            return BOUND + whole
        return BOUND + window[window.rindex('-lag'):]
    return BOUND


def floor_ratios(rows: Dict[str, dict]) -> Dict[str, Tuple[float, float]]:
    r"""Each row's RMSE as a multiple of its bound's floor on the same
    realizations (:func:`floor_row`: the filtering bound, or a smoothed
    row's smoothing bound; on a scenario with bearings, the rows of the
    range-only likelihood by the same bound of the ranges alone,
    :obj:`"pcrb-range-only"` and :obj:`"pcrb-lagL-range-only"`, where the
    table holds it): the mean and sample standard deviation over
    the realizations of RMSE / floor (the rows of one scenario of
    :obj:`compare.json`; a row whose bound's row is missing has none).
    Rows of other realization counts than their bound's, or a floor that
    is not positive, are a :class:`ValueError` naming the row (a ratio of
    other realizations would be silently wrong)."""
    ratios = {}
    for key, entry in rows.items():
        bound = floor_row(key)
        # the range-only likelihood of a scenario with bearings reads the
        # ranges alone: its floor is theirs (where the table has it)
        if key.partition(' ')[2] == 'gaussian' and \
                bound + RANGE_ONLY in rows:
            bound += RANGE_ONLY
        if bound not in rows:
            continue
        floors = [r[2] for r in rows[bound]['spread']['realizations']]
        if not floors or not all(f > 0 for f in floors):
            raise ValueError(f"the bound's row ('{bound}') needs a positive "
                             f"floor for every realization, got {floors}")
        realizations = entry['spread']['realizations']
        if len(realizations) != len(floors):
            raise ValueError(f"the row '{key}' holds {len(realizations)} "
                             f"realizations, the bound's ('{bound}') "
                             f"{len(floors)}")
        per = [r[2] / f for r, f in zip(realizations, floors)]
        mean = sum(per) / len(per)
        var = (sum((p - mean)**2 for p in per) / (len(per) - 1)
               if len(per) > 1 else 0.0)
        ratios[key] = (mean, var**0.5)
    return ratios


def compare_table(compare: dict) -> str:
    r"""The rows of :obj:`compare.json` as one Markdown table per
    scenario, in the order of :func:`compare_methods`."""
    settings = compare['settings']
    lines = [f"{settings['realizations']} realizations per scenario, seed "
             f"{settings['seed']}, {settings['device']}. P_out and "
             f"P(accept) pool every agent and time step; 'per real.' is the "
             f"mean ± standard deviation over the realizations; RMSE / "
             f"floor divides each realization's RMSE by the bound's floor "
             f"on the same realization (a smoother's smoothed rows, "
             f"'-smoothed' and 'iekf-smoother', by the smoothing bound of "
             f"their lag, 'pcrb-lagL' and 'pcrb-smoother'). The bound's "
             f"P(accept) is that of an efficient estimator: the confidence "
             f"level.", '']
    for name, rows in compare['results'].items():
        ratios = floor_ratios(rows)
        lines += [f'### `{name}`', '',
                  '| method | P_out 0.5 / 1 / 2 m | P(accept 0.95 / 0.99) | '
                  'RMSE [m] | RMSE / floor | P_out(1 m) per real. | '
                  'P(accept) per real. | s per real. |',
                  '| --- ' * 8 + '|']
        for key, e in rows.items():
            o, s = e['outage'], e['spread']
            ratio = ratios.get(key)
            lines.append(
                f"| `{key}` | {o['0.5']:.3f} / {o['1.0']:.4f} / "
                f"{o['2.0']:.4f} | {e['accept']['0.95']:.3f} / "
                f"{e['accept']['0.99']:.3f} | "
                f"{e['rmse']:.3f} | "
                + (f'{ratio[0]:.2f} ± {ratio[1]:.2f}' if ratio else '')
                + f" | {s['outage_1m']['mean']:.4f} ± "
                f"{s['outage_1m']['std']:.4f} | "
                f"{s['accept_0.95']['mean']:.3f} ± "
                f"{s['accept_0.95']['std']:.3f} | "
                f"{e['seconds_per_realization']:.2f} |")
        lines.append('')
    return '\n'.join(lines)


def compare_points(compare: dict) -> Dict[str, List[dict]]:
    r"""Per scenario, what :func:`~tg_nebp.plot.plot_compare` draws of
    every row: its key, seconds per realization, P_out(1 m),
    P(accept 0.95) and RMSE / floor, each with its spread over the
    realizations."""
    points = {}
    for name, rows in compare['results'].items():
        ratios = floor_ratios(rows)
        points[name] = [dict(
            key=key, seconds=e['seconds_per_realization'],
            outage=(e['outage']['1.0'], e['spread']['outage_1m']['std']),
            accept=(e['accept']['0.95'], e['spread']['accept_0.95']['std']),
            floor_ratio=ratios.get(key)) for key, e in rows.items()]
    return points


def compare(out: Union[str, Path] = 'results/compare',
            progress_factory: Optional[Callable] = None,
            log: Callable = print, **options) -> dict:
    r"""Behind :obj:`tg-nebp compare`: :func:`run_compare` with
    :obj:`out` and :obj:`options` (its other arguments by name), then the
    table :obj:`out/compare.md` (:func:`compare_table`) and the figure
    :obj:`out/compare.png` (:func:`~tg_nebp.plot.plot_compare`).

    Args:
        progress_factory (callable, optional): :obj:`(total, description)`
            to a context manager (a progress bar; :obj:`total` is
            :obj:`None`) whose :obj:`update(n)` is called after every time
            step and whose :obj:`write`, when it has one, replaces
            :obj:`log`. (default: :obj:`None`)

    Returns:
        The content of :obj:`out/compare.json`.
    """
    from tg_nebp.plot import plot_compare

    bar = (progress_factory(None, 'compare')
           if progress_factory is not None else None)
    with (bar if bar is not None else contextlib.nullcontext()):
        result = run_compare(out=out, progress=getattr(bar, 'update', None),
                             log=getattr(bar, 'write', log), **options)
    out = Path(out)
    write_text(out / 'compare.md', compare_table(result))
    plot_compare(compare_points(result), out / 'compare.png')
    return result
