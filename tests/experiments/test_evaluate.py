r"""Tests of :mod:`tg_nebp.experiments.evaluate`: the tracker each method's
options build, and one evaluation written as the command line writes it."""
import json

import pytest

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.cli import main
from tg_nebp.datasets import Scenario
from tg_nebp.experiments.evaluate import (METHODS, evaluate_scenario,
                                          method_tracker)
from tg_nebp.filters import CentralizedIEKF, GaussianBP, ParticleBP
from tg_nebp.models import StudentTRange


@pytest.fixture(scope='module')
def scenario():
    return Scenario.load('paper_test')


def test_method_tracker_builds_each_method(scenario):
    made = {m: method_tracker(m, scenario) for m in METHODS if m != 'nebp'}
    assert isinstance(made['bp'][0], ParticleBP)
    assert made['bp'][0].num_particles == 1000 and made['bp'][1] == 'bp'
    assert isinstance(made['gbp'][0], GaussianBP)
    assert made['gbp'][0].settings() == GaussianBP.recommended().settings()
    assert isinstance(made['iekf'][0], CentralizedIEKF)
    assert isinstance(made['pcrb'][0], PosteriorCRB)
    tracker, key = method_tracker('iekf', scenario, marginal=True,
                                  measurement='student-t')
    assert key == 'iekf-marginal'
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
    with pytest.raises(ValueError, match="one of bp, nebp"):
        method_tracker('ukf', scenario)


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
