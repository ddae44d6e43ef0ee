r"""Tests of :mod:`tg_nebp.experiments.evaluate`: the tracker each method's
options build, and one evaluation written as the command line writes it."""
import json

import pytest

from tg_nebp import NEBP
from tg_nebp.bounds import PosteriorCRB
from tg_nebp.cli import main
from tg_nebp.datasets import Scenario, load_scenario
from tg_nebp.experiments.evaluate import evaluate_scenario, method_tracker
from tg_nebp.experiments.options import METHOD_OPTIONS, METHODS, MethodOptions
from tg_nebp.filters import (RESAMPLERS, CentralizedIEKF,
                             FixedLagGaussianBP, FixedLagGaussianNEBP,
                             GaussianBP, GaussianNEBP, GroupExchange,
                             GroupFlip, IncrementalSmoother, ParticleBP,
                             ParticleTrajectorySearch, TrajectorySearch)
from tg_nebp.models import StudentTRange
from tg_nebp.training import save_checkpoint


@pytest.fixture(scope='module')
def scenario():
    return Scenario.load('paper_test')


def test_method_tracker_builds_each_method(scenario):
    made = {m: method_tracker(m, scenario) for m in METHODS
            if m not in ('nebp', 'gnebp')}
    assert isinstance(made['bp'][0], ParticleBP)
    assert made['bp'][0].num_particles == 1000 and made['bp'][1] == 'bp'
    assert isinstance(made['gbp'][0], GaussianBP)
    assert made['gbp'][0].settings() == GaussianBP.recommended().settings()
    assert isinstance(made['iekf'][0], CentralizedIEKF)
    assert isinstance(made['pcrb'][0], PosteriorCRB)
    tracker, key = method_tracker('iekf', scenario, marginal=True,
                                  measurement='student-t')
    assert key == 'iekf-marginal'
    escape, escape_key = method_tracker('iekf', scenario, lag='all',
                                        escape=True)
    assert escape_key == 'iekf-smoother-escape'
    incremental, window = escape.starts
    assert isinstance(incremental.tracker, IncrementalSmoother)
    assert window.tracker.settings() == FixedLagGaussianBP.recommended(
        lag=10, relocation=TrajectorySearch()).settings()
    assert escape.search == ParticleTrajectorySearch()
    assert escape.exchange == GroupExchange()
    assert escape.flip == GroupFlip()
    assert isinstance(tracker.measurement, StudentTRange)
    # the scenario's sigma and range are kept
    assert tracker.measurement.sigma == scenario.measurement_model.sigma


def test_method_tracker_options(scenario):
    gbp, _ = method_tracker('gbp', scenario, iterations=3, tolerance=0,
                            inflation=1.0, ends='receiver')
    assert (gbp.num_iterations, gbp.tolerance, gbp.inflation) == (3, None,
                                                                  1.0)
    bp, _ = method_tracker('bp', scenario, particles=50, iterations=2,
                           ends='both', samples=4)
    assert (bp.num_particles, bp.num_iterations) == (50, 2)


def test_method_tracker_refusals(scenario):
    with pytest.raises(ValueError, match='counts the receivers'):
        method_tracker('bp', scenario, iterations=2)
    with pytest.raises(ValueError, match='needs a checkpoint'):
        method_tracker('nebp', scenario)
    with pytest.raises(ValueError, match=r"method 'gnebp' needs a "
                       r"checkpoint .*one shipped: paper, nlos, mix"):
        method_tracker('gnebp', scenario)
    with pytest.raises(ValueError, match="one of bp, nebp"):
        method_tracker('ukf', scenario)
    with pytest.raises(TypeError, match="'scenario' must be a Scenario"):
        method_tracker('bp', 'paper_test')


# a value of every option, for the methods that do not take it
GIVEN = dict(checkpoint='nebp.pt', particles=8, samples=2, compile=True,
             resampler='systematic', regularize=0.2, ess_threshold=0.5,
             measurement='student-t', iterations=2, ends='both',
             marginal=True, inflation=1.2, tolerance=0.0, no_control=True,
             lag=3, incremental=True, escape=True, report_inflation=2.0,
             adapt_noise=True)


def test_an_option_is_refused_by_the_methods_that_do_not_take_it(scenario):
    assert sorted(METHOD_OPTIONS) == sorted(GIVEN)
    for name, takers in METHOD_OPTIONS.items():
        flag = '--' + name.replace('_', '-')
        for method in set(METHODS) - set(takers):
            with pytest.raises(ValueError, match=(
                    f"'{name}' \\({flag}\\) is for method "
                    f"{' or '.join(takers)}, not {method}")):
                method_tracker(method, scenario, **{name: GIVEN[name]})


def test_a_given_value_is_used_or_refused_never_replaced(scenario,
                                                         tmp_path):
    checkpoint = tmp_path / 'k8.pt'
    save_checkpoint(checkpoint, NEBP(num_particles=8))
    # 0 used to become the default (5 iterations, 1,000 particles, M = 1)
    for method, name, value, error, message in [
            ('iekf', 'iterations', 0, ValueError, 'must be positive'),
            ('gbp', 'iterations', 0, ValueError, 'must be positive'),
            ('bp', 'iterations', 0, ValueError, 'must be positive'),
            ('bp', 'iterations', 'x', TypeError, 'must be an integer'),
            ('bp', 'particles', 0, ValueError, 'must be positive'),
            ('bp', 'samples', 0, ValueError, 'must be positive'),
            # NEBP's loader blamed the checkpoint for these
            ('nebp', 'particles', 2.5, TypeError, 'must be an integer'),
            ('nebp', 'samples', 'x', TypeError, 'must be an integer')]:
        extra = dict(checkpoint=checkpoint) if method == 'nebp' else {}
        with pytest.raises(error, match=f"'{name}' {message}"):
            method_tracker(method, scenario, **{name: value}, **extra)
    iekf, _ = method_tracker('iekf', scenario, iterations=3)
    assert iekf.num_iterations == 3
    bp, _ = method_tracker('bp', scenario, samples=4,
                           resampler='systematic')
    assert (bp.num_samples, bp.resampler) == (4, RESAMPLERS['systematic'])
    plain, _ = method_tracker('bp', scenario)
    assert plain.resampler is RESAMPLERS['multinomial']
    nebp, _ = method_tracker('nebp', scenario, checkpoint=checkpoint,
                             samples=2)
    assert nebp.num_samples == 2


def test_evaluate_scenario_checks_before_any_data(tmp_path):
    root = tmp_path / 'data'
    common = dict(method='bp', scenario='paper_train', realizations=1,
                  root=str(root), out=str(tmp_path / 'out'))
    for changes, message in [
            (dict(realizations=0), "'realizations' must be positive"),
            (dict(batch_size=0), "'batch_size' must be positive"),
            # without CUDA, or without a 100th GPU
            (dict(device='cuda:99'), "'device' is 'cuda:99', but"),
            (dict(device='tpu'), "'device' must be 'cpu', 'cuda'"),
            (dict(seed=-1), "'seed' must be non-negative"),
            (dict(method='iekf', resampler='systematic'),
             "'resampler' .* not iekf")]:
        with pytest.raises(ValueError, match=message):
            evaluate_scenario(**{**common, **changes})
        assert not root.exists() and not (tmp_path / 'out').exists()


def test_evaluate_scenario_equals_the_command_line(tmp_path):
    api = evaluate_scenario('bp', 'paper_train', 2, seed=3,
                            root=str(tmp_path / 'data'),
                            out=str(tmp_path / 'api'), particles=40)
    assert main(['evaluate', '--scenario', 'paper_train', '--realizations',
                 '2', '--seed', '3', '--particles', '40', '--root',
                 str(tmp_path / 'data'), '--out', str(tmp_path / 'cli'),
                 '--quiet', '--threads', '1']) == 0
    cli = json.loads((tmp_path / 'cli' / 'metrics.json').read_text())['bp']
    written = json.loads((tmp_path / 'api' / 'metrics.json').read_text())
    assert api['key'] == 'bp' and written['bp'] == api['entry']
    for field in ('rmse', 'outage', 'accept'):
        assert cli[field] == api['entry'][field]


@pytest.mark.parametrize('driver', ['frontier', 'train', 'reproduce'])
def test_every_driver_refuses_a_device_it_lacks_before_any_data(tmp_path,
                                                                driver):
    from tg_nebp.experiments.frontier import frontier
    from tg_nebp.experiments.reproduce import reproduce
    from tg_nebp.experiments.train import train_scenario
    root, out = str(tmp_path / 'data'), str(tmp_path / 'out')
    run = dict(
        frontier=lambda: frontier([10], [1], realizations=1, root=root,
                                  out=out, device='cuda:99'),
        train=lambda: train_scenario('paper_train', out, realizations=1,
                                     root=root, device='cuda:99'),
        reproduce=lambda: reproduce('quick', 'cuda:99', out, root))[driver]
    with pytest.raises(ValueError, match="'device' is 'cuda:99', but"):
        run()
    assert list(tmp_path.iterdir()) == []


def test_gnebp_loads_a_checkpoint_with_its_run_time_options(scenario,
                                                            tmp_path):
    checkpoint = tmp_path / 'g.pt'
    save_checkpoint(checkpoint, GaussianNEBP(num_iterations=7,
                                             hidden_dim=4))
    tracker, key = method_tracker('gnebp', scenario, checkpoint=checkpoint)
    assert key == 'gnebp' and isinstance(tracker, GaussianNEBP)
    assert (tracker.num_iterations, tracker.tolerance) == (7, 0.01)
    tracker, _ = method_tracker('gnebp', scenario, checkpoint=checkpoint,
                                iterations=3, tolerance=0)
    assert (tracker.num_iterations, tracker.tolerance) == (3, None)
    # a particle checkpoint is refused by name, and the other way round
    particle = tmp_path / 'p.pt'
    save_checkpoint(particle, NEBP(num_particles=8))
    with pytest.raises(ValueError, match='with --method nebp'):
        method_tracker('gnebp', scenario, checkpoint=particle)
    with pytest.raises(ValueError, match='with --method gnebp'):
        method_tracker('nebp', scenario, checkpoint=checkpoint)
    # the correction trained in a window: its own key, and no hybrid BP
    # over it (that runs over one step)
    window = tmp_path / 'w.pt'
    save_checkpoint(window, FixedLagGaussianNEBP(lag=3, hidden_dim=4))
    tracker, key = method_tracker('gnebp', scenario, checkpoint=window)
    assert key == 'gnebp-lag3' and isinstance(tracker, FixedLagGaussianNEBP)
    with pytest.raises(ValueError, match='inside a window of 3'):
        method_tracker('hybrid', scenario, checkpoint=window)


def test_cli_evaluates_a_shipped_gaussian_nebp_by_name(tmp_path, capsys):
    assert main(['evaluate', '--method', 'gnebp', '--checkpoint', 'paper',
                 '--scenario', 'paper_train', '--realizations', '1',
                 '--root', str(tmp_path / 'data'), '--out',
                 str(tmp_path / 'out'), '--quiet']) == 0
    written = json.loads((tmp_path / 'out' / 'metrics.json').read_text())
    assert written['gnebp']['hidden_dim'] == 32
    assert main(['evaluate', '--method', 'gnebp', '--checkpoint',
                 str(tmp_path / 'absent.pt'), '--scenario', 'paper_train',
                 '--realizations', '1', '--root', str(tmp_path / 'data'),
                 '--out', str(tmp_path / 'out'), '--quiet']) == 2
    err = capsys.readouterr().err
    assert err.startswith('error: ') and err.count('\n') == 1
    assert 'absent.pt' in err


def test_a_run_without_inputs_has_its_own_entry():
    from tg_nebp.datasets import Scenario
    robots = Scenario.load('robots_test')
    tracker, key = method_tracker('gbp', robots, no_control=True)
    assert key == 'gbp-no-control' and tracker.use_control is False
    assert method_tracker('gbp', robots)[1] == 'gbp'


def test_a_checkpoint_on_data_of_other_models_is_refused_or_said(
        scenario, tmp_path):
    # the shipped correction of the paper's network: robots are another
    # kind of data (refused, naming both); NLOS ranges are the same kind
    # under another likelihood (tracked with the checkpoint's, said)
    with pytest.raises(ValueError, match=r"checkpoint 'paper' was trained "
                       r"for constant-velocity-drag motion and the link "
                       r"features \['range'\], but the data of scenario "
                       r"'mrclam-6' are unicycle-odometry with \['range', "
                       r"'bearing'\]"):
        method_tracker('gnebp', load_scenario('mrclam-6'),
                       checkpoint='paper')
    nlos = Scenario.load('paper_test_nlos')
    with pytest.warns(UserWarning, match=r"checkpoint 'paper' tracks with "
                      r"the models it was trained with .*GaussianRange.*, "
                      r"not those of scenario 'paper_test_nlos' "
                      r"\(.*NLOSRange"):
        tracker, _ = method_tracker('gnebp', nlos, checkpoint='paper')
    assert tracker.measurement.name == 'gaussian'
    particle = tmp_path / 'p.pt'
    save_checkpoint(particle, NEBP(num_particles=8))
    with pytest.raises(ValueError, match=r"the data of scenario 'mrclam-6'"):
        method_tracker('nebp', load_scenario('mrclam-6'),
                       checkpoint=particle)


def test_method_tracker_builds_the_smoothers(scenario):
    from tg_nebp.filters import CentralizedSmoother, FixedLagGaussianBP
    gbp, key = method_tracker('gbp', scenario, lag=4)
    assert isinstance(gbp, FixedLagGaussianBP) and key == 'gbp-lag4'
    assert gbp.lag == 4 and gbp.inflation == 1.5  # recommended otherwise
    iekf, key = method_tracker('iekf', scenario, lag=3)
    assert isinstance(iekf, CentralizedSmoother) and key == 'iekf-lag3'
    full, key = method_tracker('iekf', scenario, lag='all')
    assert full.lag is None and key == 'iekf-smoother'
    bound, key = method_tracker('pcrb', scenario, lag=5)
    assert bound.lag == 5 and key == 'pcrb-lag5'
    assert method_tracker('pcrb', scenario, lag='all')[1] == 'pcrb-smoother'
    with pytest.raises(ValueError, match="'lag' 'all' .* is for method "
                       "iekf or pcrb"):
        method_tracker('gbp', scenario, lag='all')
    with pytest.raises(ValueError, match="'lag' and 'marginal'"):
        method_tracker('iekf', scenario, lag=3, marginal=True)
    # a window reports its beliefs as they are; Gaussian BP and hybrid BP
    # inflate what they report as told
    with pytest.raises(ValueError, match="'report_inflation' .* and 'lag'"):
        method_tracker('gbp', scenario, lag=3, report_inflation=2.0)
    assert method_tracker('gbp', scenario, report_inflation=1.0)[
        0].report_inflation == 1.0
    assert method_tracker('hybrid', scenario, report_inflation=3.0)[
        0].gaussian.report_inflation == 3.0
    with pytest.raises(ValueError, match=r"'lag' \(--lag\) is for method "
                       r"gbp or hybrid or iekf or pcrb, not bp"):
        method_tracker('bp', scenario, lag=3)
    with pytest.raises(ValueError, match="'lag' must be positive"):
        method_tracker('gbp', scenario, lag=0)
    from tg_nebp.filters import IncrementalSmoother
    incremental, key = method_tracker('iekf', scenario, lag='all',
                                      incremental=True, iterations=3)
    assert isinstance(incremental, IncrementalSmoother)
    assert key == 'iekf-incremental' and incremental.num_iterations == 3
    for lag in (None, 4):
        with pytest.raises(ValueError, match="'incremental' is the smoother "
                           "of the whole sequence: give 'lag' 'all'"):
            method_tracker('iekf', scenario, lag=lag, incremental=True)
    with pytest.raises(ValueError, match=r"'incremental' \(--incremental\) "
                       r"is for method iekf, not gbp"):
        method_tracker('gbp', scenario, lag=3, incremental=True)


def test_cli_evaluates_the_incremental_smoother(tmp_path, capsys):
    # two entries: each step's newest states (the past relinearized) and
    # every step's smoothed estimate, which is closer to the truth
    out = tmp_path / 'out'
    assert main(['evaluate', '--scenario', 'paper_test', '--realizations',
                 '1', '--root', str(tmp_path / 'data'), '--out', str(out),
                 '--quiet', '--threads', '1', '--method', 'iekf', '--lag',
                 'all', '--incremental']) == 0
    printed = capsys.readouterr().out
    assert 'iekf-incremental: RMSE' in printed
    assert 'iekf-incremental-smoothed: RMSE' in printed
    metrics = json.loads((out / "metrics.json").read_text())
    filtered = metrics['iekf-incremental']
    smoothed = metrics['iekf-incremental-smoothed']
    assert filtered['incremental'] is True and smoothed['smoothed'] is True
    assert smoothed['rmse'] < filtered['rmse']


def test_cli_evaluates_a_smoother_filtered_and_smoothed(tmp_path, capsys):
    # two entries, each tracked on its own: the newest step of every
    # window, and every step's estimate as it leaves the window; the
    # smoothed one is closer to the truth
    from tg_nebp.datasets import CooperativeLocalizationDataset
    from tg_nebp.evaluation import summarize_result, track_dataset
    from tg_nebp.filters import FixedLagGaussianBP, Smoothed
    root, out = tmp_path / 'data', tmp_path / 'out'
    args = ['evaluate', '--scenario', 'paper_test', '--realizations', '1',
            '--root', str(root), '--out', str(out), '--quiet', '--threads',
            '1']
    assert main(args + ['--method', 'gbp', '--lag', '3']) == 0
    printed = capsys.readouterr().out
    assert 'gbp-lag3: RMSE' in printed and 'gbp-lag3-smoothed: RMSE' in \
        printed
    # the first realization's tracks, filtered and smoothed
    assert (out / 'tracks-gbp-lag3.png').stat().st_size > 0
    assert 'tracks, filtered and smoothed ->' in printed
    assert main(args + ['--method', 'pcrb', '--lag', '3']) == 0
    written = json.loads((out / 'metrics.json').read_text())
    assert written['gbp-lag3']['lag'] == 3
    assert written['gbp-lag3-smoothed']['smoothed'] is True
    assert written['gbp-lag3-smoothed']['rmse'] < written['gbp-lag3']['rmse']
    assert 'pcrb-lag3' in written
    scenario = Scenario.load('paper_test')
    dataset = CooperativeLocalizationDataset(str(root), scenario, 1)
    expected = summarize_result(track_dataset(Smoothed(
        FixedLagGaussianBP.recommended(
            lag=3, motion=scenario.motion_model,
            measurement=scenario.measurement_model)), dataset))
    assert written['gbp-lag3-smoothed']['rmse'] == expected['rmse']


def test_switches_checkpoints_and_records_are_checked_by_name(scenario):
    # 'no', 'false' or 0 switched an option on (anything not False did)
    for name in ('no_control', 'compile', 'incremental', 'marginal',
                 'adapt_noise'):
        for value in ('no', 'false', 0, None):
            with pytest.raises(TypeError, match=rf"'{name}' \(--"
                               rf"{name.replace('_', '-')}\) is a switch"):
                MethodOptions(**{name: value}).check('iekf')
    # a checkpoint that is not a path (a raw TypeError of pathlib)
    with pytest.raises(TypeError, match="'checkpoint' must be a path"):
        method_tracker('gnebp', scenario, checkpoint=5)
    # a record given as a plain mapping is one; anything else is named
    tracker, key = method_tracker('gbp', scenario,
                                  options=dict(iterations=3))
    assert tracker.num_iterations == 3 and key == 'gbp'
    with pytest.raises(ValueError, match=r"unknown method option\(s\) "
                       r"\['iteration'\]"):
        method_tracker('gbp', scenario, options=dict(iteration=3))
    with pytest.raises(TypeError, match="'options' must be a MethodOptions"):
        method_tracker('gbp', scenario, options=[('iterations', 3)])
