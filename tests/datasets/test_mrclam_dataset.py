r"""The MRCLAM sequences as scenarios and datasets, on a small sequence
written here in the dataset's format (and sequence 6 where ../shared has
it): names and their options, scenario files, windows and halves, the
zip, the folder and the download, and the models shipped for every
``mrclam-N`` name against a fit of sequence 6."""
import json
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from tg_nebp.datasets import (MRCLAM, MRCLAMScenario, fitted_scenario,
                              load_datasets, load_scenario, read_mrclam)
from tg_nebp.datasets.mrclam import long_run_factor
from tg_nebp.datasets.scenario import Scenario

from helpers import write_mrclam

SEQUENCE_6 = (Path(__file__).resolve().parents[2].parent / 'shared' / 'data'
              / 'mrclam' / 'MRCLAM_Dataset6.zip')


@pytest.fixture
def root(tmp_path):
    # sequence 9 of the written format, extracted
    write_mrclam(tmp_path / 'MRCLAM_Dataset9')
    return tmp_path


def test_names_and_their_options():
    full = load_scenario('mrclam-6')
    assert isinstance(full, MRCLAMScenario)
    assert (full.sequence, full.features, full.odometry, full.links,
            full.part, full.duration, full.dt) == (
                6, ('range', 'bearing'), True, 'all', 'all', 600.0, 0.5)
    assert full.measurement_model.name == 'student-t-range-bearing'
    blind = load_scenario('mrclam-7-range-no-odometry')
    assert (blind.name, blind.sequence, blind.features, blind.odometry) == (
        'mrclam-7-range-no-odometry', 7, ('range', ), False)
    # the range part of the same fitted likelihood
    assert blind.measurement_model.name == 'student-t'
    assert blind.measurement_model.sigma == full.measurement_model.sigma
    assert blind.motion == full.motion
    half = load_scenario('mrclam-6-landmarks-second-half')
    assert (half.links, half.part, half.duration) == ('landmarks',
                                                     'second-half', None)
    assert load_scenario('paper_test') == Scenario.load('paper_test')
    with pytest.raises(ValueError, match=r"scenario 'mrclam-6-fast': "
                       r"unknown option 'fast'"):
        load_scenario('mrclam-6-fast')
    with pytest.raises(ValueError, match=r"unknown scenario 'mrclam-0'"):
        load_scenario('mrclam-0')
    # options that set the same field contradict each other: the last
    # would win silently
    for name, first, last, field in (
            ('mrclam-6-landmarks-robots', 'landmarks', 'robots', 'links'),
            ('mrclam-6-first-half-range-second-half', 'first-half',
             'second-half', 'part')):
        with pytest.raises(ValueError, match=(
                f"scenario '{name}': the options '{first}' and '{last}' "
                f"contradict each other \\(both set '{field}'\\)")):
            load_scenario(name)
    with pytest.raises(ValueError, match="gives the option 'range' twice"):
        load_scenario('mrclam-6-range-range')


def test_scenario_file_round_trip_and_bad_fields(tmp_path):
    scenario = load_scenario('mrclam-6-range').replace(
        name='mine', duration=60.0, stride=30.0, part='first-half')
    path = tmp_path / 'mine.json'
    scenario.save(path)
    again = load_scenario(str(path))
    assert again == scenario
    assert again.fingerprint() == scenario.fingerprint()
    fields = json.loads(path.read_text())
    for key, value, message in (
            ('sequence', 10, r"'sequence' must be one of 1 to 9"),
            ('part', 'middle', r"'part' must be one of"),
            ('stride', -1.0, r"'stride' must be a positive number"),
            ('features', ['range', 'bearing'],
             r"'measurement' \(student-t\) reads the link features "
             r"\['range'\], but 'features' is \['range', 'bearing'\]"),
            ('speed', 1.0, r"unknown fields \['speed'\]")):
        path.write_text(json.dumps({**fields, key: value}))
        with pytest.raises(ValueError, match=rf"scenario '{path}'.*"
                           + message):
            load_scenario(str(path))


def test_windows_halves_and_counts(root):
    base = MRCLAMScenario.load('mrclam-9').replace(duration=10.0)
    one = MRCLAM(str(root), base)
    sequence = read_mrclam(root / 'MRCLAM_Dataset9')
    begin, end = sequence.start(), sequence.end()
    assert (begin, end) == pytest.approx((1001.0, 1028.98))
    assert len(one) == 1 and int(one[0].num_steps) == 20
    # the prior at the start, the truth at the step times after it
    assert float(one[0].prior_mean[0, 0]) == pytest.approx(0.1, abs=1e-5)
    windows = MRCLAM(str(root), base.replace(stride=4.0))
    # starts 0, 4, 8, 12, 16 s in: the last ends at 26 s of 27.98
    assert len(windows) == 5
    for k in range(5):
        x0 = float(windows[k].prior_mean[0, 0])
        assert x0 == pytest.approx(0.1 * (1.0 + 4 * k), abs=1e-5)
    assert len(MRCLAM(str(root), base.replace(stride=4.0), 2)) == 2
    with pytest.raises(ValueError, match=r"has 5 windows in sequence 9, "
                       r"not 6"):
        MRCLAM(str(root), base.replace(stride=4.0), 6)
    second = MRCLAM(str(root), 'mrclam-9-second-half')
    # the whole second half, in whole steps: 13.99 s -> 27 steps
    assert second.scenario.duration == 13.5
    assert int(second[0].num_steps) == 27
    x0 = float(second[0].prior_mean[0, 0])
    assert x0 == pytest.approx(0.1 * (1.0 + 0.5 * (end - begin)), abs=1e-4)
    with pytest.raises(ValueError, match=r"a window of 600 s from 0 s into "
                       r"the all part does not fit in sequence 9's 28.0 s"):
        MRCLAM(str(root), 'mrclam-9')
    # the range-only option keeps one feature, no odometry none
    ranges = MRCLAM(str(root), MRCLAMScenario.load(
        'mrclam-9-range-no-odometry').replace(duration=10.0))
    assert ranges[0].edge_attr.size(1) == 1
    assert getattr(ranges[0], 'control', None) is None
    assert one.counts[0]['unknown_barcodes'] == 1


def test_zip_folder_and_download(root, tmp_path, monkeypatch):
    scenario = MRCLAMScenario.load('mrclam-9').replace(duration=10.0)
    from_folder = MRCLAM(str(root), scenario)[0]
    zipped = tmp_path / 'zipped'
    zipped.mkdir()
    with zipfile.ZipFile(zipped / 'MRCLAM_Dataset9.zip', 'w') as archive:
        for path in (root / 'MRCLAM_Dataset9').iterdir():
            archive.write(path, f'MRCLAM_Dataset9/{path.name}')
    from_zip = MRCLAM(str(zipped), scenario)[0]
    torch.testing.assert_close(from_zip.edge_attr, from_folder.edge_attr,
                               rtol=0, atol=0)
    # absent: the official zip is downloaded into root, then read
    fetched = []

    def download_url(url, folder, log=True):
        fetched.append(url)
        target = Path(folder) / url.rsplit('/', 1)[1]
        target.write_bytes((zipped / 'MRCLAM_Dataset9.zip').read_bytes())
        return str(target)

    import torch_geometric.data
    monkeypatch.setattr(torch_geometric.data, 'download_url', download_url)
    empty = tmp_path / 'empty'
    got = MRCLAM(str(empty), scenario, log=False)[0]
    assert fetched == ['http://asrl.utias.utoronto.ca/datasets/mrclam/'
                       'MRCLAM_Dataset9.zip']
    torch.testing.assert_close(got.edge_attr, from_folder.edge_attr,
                               rtol=0, atol=0)

    def offline(url, folder, log=True):
        raise OSError('no network')

    monkeypatch.setattr(torch_geometric.data, 'download_url', offline)
    with pytest.raises(ValueError, match=r"MRCLAM sequence 9 is not in "
                       r"'.*nowhere' \(neither MRCLAM_Dataset9.zip nor "
                       r"MRCLAM_Dataset9/\) and could not be downloaded"):
        MRCLAM(str(tmp_path / 'nowhere'), scenario)
    # the failed download leaves none of the folders it made
    with pytest.raises(ValueError, match="could not be downloaded"):
        MRCLAM(str(tmp_path / 'new' / 'deeper'), scenario)
    assert not (tmp_path / 'new').exists()
    assert not (tmp_path / 'nowhere').exists()


def test_load_datasets_reads_a_sequence(root):
    scenario = MRCLAMScenario.load('mrclam-9').replace(duration=10.0,
                                                      stride=5.0)
    every, two = load_datasets(str(root), (scenario, None, 0),
                               (scenario, 2, 0))
    assert isinstance(every, MRCLAM) and (len(every), len(two)) == (4, 2)


def test_long_run_factor_of_an_autoregression():
    # an AR(1) series of correlation rho: the variance of the mean of H
    # steps is (1 + 2 sum_k (1 - k/H) rho^k) / H times one step's
    rho, horizon = 0.8, 10
    generator = np.random.default_rng(3)
    series = np.zeros((40, 3000))
    series[:, 0] = generator.standard_normal(40)
    for k in range(1, series.shape[1]):
        series[:, k] = rho * series[:, k - 1] + math.sqrt(
            1 - rho**2) * generator.standard_normal(40)
    series[:, ::7] = np.nan  # gaps, as a link seen now and then
    expected = 1 + 2 * sum((1 - k / horizon) * rho**k
                           for k in range(1, horizon))
    assert long_run_factor(series, horizon) == pytest.approx(expected,
                                                             rel=0.03)
    assert long_run_factor(series, 1) == 1.0
    white = generator.standard_normal((40, 3000))
    assert long_run_factor(white, horizon) == pytest.approx(1.0, abs=0.05)


@pytest.mark.skipif(not SEQUENCE_6.exists(),
                    reason=f'sequence 6 is not at {SEQUENCE_6}')
def test_shipped_models_are_the_fit_of_sequence_6():
    fitted, report = fitted_scenario(SEQUENCE_6, 6)
    shipped = load_scenario('mrclam-6')
    assert fitted.motion == shipped.motion
    assert fitted.measurement == shipped.measurement
    assert report['horizon'] == 40
    dataset = MRCLAM(str(SEQUENCE_6.parent), shipped)
    assert len(dataset) == 1 and int(dataset[0].num_steps) == 1200
