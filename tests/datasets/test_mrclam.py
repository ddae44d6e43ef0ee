r"""The MRCLAM reader on a small sequence written here in the dataset's
format (and on sequence 6 where ../shared has it): barcodes, repeated
measurements, unknown barcodes, the ground truth's interpolation across
the heading's cut, odometry against the closed form of constant
velocities, the step boundaries, the zip and the folder alike."""
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from tg_nebp.data import check_realization
from tg_nebp.datasets.mrclam import (integrate_odometry, interpolate_pose,
                                     mrclam_realization, read_mrclam)

from helpers import (MRCLAM_HEADER, MRCLAM_HEADING, MRCLAM_MEASUREMENTS,
                     MRCLAM_SPEED, MRCLAM_T0, MRCLAM_TURN, write_mrclam)

T0, SPEED, TURN, HEADING = (MRCLAM_T0, MRCLAM_SPEED, MRCLAM_TURN,
                            MRCLAM_HEADING)
HEADER, MEASUREMENTS = MRCLAM_HEADER, MRCLAM_MEASUREMENTS
_write = write_mrclam


@pytest.fixture
def folder(tmp_path):
    path = tmp_path / 'MRCLAM_Dataset9'
    _write(path, MEASUREMENTS)
    return path


def test_protocol_steps_links_and_counts(folder):
    sequence = read_mrclam(folder)
    assert sequence.start() == pytest.approx(T0 + 1.0)
    data, counts = mrclam_realization(sequence, dt=0.5, duration=10.0)
    check_realization(data, ('range', 'bearing'))
    assert data.num_nodes == 7 and int(data.num_steps) == 20
    assert data.anchor.tolist() == [False] * 5 + [True] * 2
    assert counts == dict(unknown_barcodes=1, repeated=2, outside=1)
    links = sorted(zip(data.edge_time.tolist(),
                       data.edge_index.t().tolist(),
                       data.edge_attr.tolist()))
    # (t0, t0 + 0.5]: the latest of robot 1's three sightings of landmark
    # 6 (node 5), the one at exactly t0 + 0.5 included; then robot 2
    # (node 1) in step 1, landmark 7 (node 6) by robot 3 in step 2
    assert links == [(0, [5, 0], pytest.approx([1.7, 0.3])),
                     (1, [1, 0], pytest.approx([2.0, -0.1])),
                     (2, [6, 2], pytest.approx([4.1, -0.3]))]
    assert data.prior_mean[5].tolist() == [1.0, 2.0, 0.0]
    only_landmarks, _ = mrclam_realization(sequence, dt=0.5,
                                             duration=10.0,
                                             links='landmarks',
                                             features=('range', ))
    assert only_landmarks.edge_index[0].tolist() == [5, 6]
    assert only_landmarks.edge_attr.shape == (2, 1)
    assert getattr(mrclam_realization(sequence, dt=0.5, duration=10.0,
                                        odometry=False)[0], 'control',
                   None) is None


def test_ground_truth_interpolated_across_the_cut(folder):
    sequence = read_mrclam(folder)
    data, _ = mrclam_realization(sequence, dt=0.5, duration=20.0)
    times = sequence.start() + 0.5 * torch.arange(1, 41).double()
    for r in range(5):
        heading = HEADING[r] + TURN[r] * (times - T0)
        expected = torch.stack([r + SPEED[r] * (times - T0),
                                torch.full_like(times, 0.5 * r),
                                math.pi - torch.remainder(
                                    math.pi - heading, 2 * math.pi)], -1)
        difference = data.states[r].double() - expected
        difference[:, 2] = torch.remainder(difference[:, 2] + math.pi,
                                           2 * math.pi) - math.pi
        assert float(difference.abs().max()) < 1e-4
    # robot 2 turns from 3 rad through pi: the cut is crossed
    assert bool((data.states[1, :, 2] < 0).any())


def test_odometry_against_constant_velocities(folder):
    sequence = read_mrclam(folder)
    data, _ = mrclam_realization(sequence, dt=0.5, duration=20.0)
    for r in range(5):
        expected = torch.tensor([SPEED[r] * 0.5, TURN[r] * 0.5])
        assert torch.allclose(data.control[r], expected.expand(40, 2),
                              atol=1e-6)
    assert bool(torch.isnan(data.control[5:]).all())
    # outside the odometry's span: no input
    odometry = np.array([[0.0, 1.0, 0.5], [1.0, 2.0, 0.5], [2.0, 2.0, 0.5]])
    inputs = integrate_odometry(odometry, np.array([-0.5, 0.5, 1.5, 2.5]))
    assert np.isnan(inputs[0]).all() and np.isnan(inputs[2]).all()
    assert inputs[1].tolist() == pytest.approx([0.5 * 1.0 + 0.5 * 2.0,
                                                0.5])


def test_zip_and_folder_read_alike(folder, tmp_path):
    archive = tmp_path / 'MRCLAM_Dataset9.zip'
    with zipfile.ZipFile(archive, 'w') as z:
        for path in folder.iterdir():
            z.write(path, f'MRCLAM_Dataset9/{path.name}')
    a, _ = mrclam_realization(read_mrclam(folder), duration=10.0)
    b, _ = mrclam_realization(read_mrclam(archive), duration=10.0)
    for key in ('states', 'edge_index', 'edge_attr', 'control'):
        torch.testing.assert_close(getattr(a, key), getattr(b, key),
                                   rtol=0, atol=0, equal_nan=True)


def test_bad_files_are_named(folder):
    (folder / 'Robot3_Odometry.dat').write_text(HEADER + '1.0 2.0\n')
    with pytest.raises(ValueError, match=r"'Robot3_Odometry.dat': data row "
                       r"1 has 2 columns, expected 3"):
        read_mrclam(folder)
    (folder / 'Robot3_Odometry.dat').unlink()
    with pytest.raises(ValueError, match="has no 'Robot3_Odometry.dat'"):
        read_mrclam(folder)
    _write(folder, MEASUREMENTS)
    with pytest.raises(ValueError, match='leave the span'):
        mrclam_realization(read_mrclam(folder), duration=100.0)


def _zipped(folder, archive, edit=None):
    # the folder's files as a zip (members 'MRCLAM_Dataset9/NAME'), each
    # member's bytes through 'edit' (name, bytes) -> bytes
    with zipfile.ZipFile(archive, 'w', zipfile.ZIP_DEFLATED) as z:
        for path in sorted(folder.iterdir()):
            data = path.read_bytes()
            z.writestr(f'MRCLAM_Dataset9/{path.name}',
                       data if edit is None else edit(path.name, data))
    return archive


def test_resource_forks_and_other_encodings_are_read(folder, tmp_path):
    # what macOS's archiver adds (resource forks of every file) and a
    # Latin-1 header comment: read as the plain sequence
    plain, _ = mrclam_realization(read_mrclam(folder), duration=10.0)
    archive = _zipped(folder, tmp_path / 'MRCLAM_Dataset9.zip', lambda name,
                      data: b'# \xe9t\xe9 ' + data if name == 'Barcodes.dat'
                      else data)
    with zipfile.ZipFile(archive, 'a') as z:
        for path in folder.iterdir():
            z.writestr(f'__MACOSX/MRCLAM_Dataset9/._{path.name}',
                       b'\x00\x05\x16\x07\xff\xfe binary')
    read, _ = mrclam_realization(read_mrclam(archive), duration=10.0)
    assert torch.equal(read.edge_attr, plain.edge_attr)
    (folder / '._Barcodes.dat').write_bytes(b'\x00\x05\x16\x07\xff')
    read, _ = mrclam_realization(read_mrclam(folder), duration=10.0)
    assert torch.equal(read.edge_attr, plain.edge_attr)


def test_a_damaged_member_is_named(folder, tmp_path):
    # a deflate stream cut short: the archive and the member named
    archive = _zipped(folder, tmp_path / 'MRCLAM_Dataset9.zip')
    raw = bytearray(archive.read_bytes())
    with zipfile.ZipFile(archive) as z:
        info = z.getinfo('MRCLAM_Dataset9/Robot2_Groundtruth.dat')
    start = info.header_offset + 30 + len(info.filename.encode())
    raw[start + 10:start + 60] = bytes(50)  # inside its compressed data
    archive.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"its member "
                       r"'MRCLAM_Dataset9/Robot2_Groundtruth.dat' is damaged"):
        read_mrclam(archive)


@pytest.mark.parametrize('name,row,match', [
    # a barcode given to a second subject (the last row won)
    ('Barcodes.dat', '8 16', r"'Barcodes.dat': data row 8 gives barcode 16 "
     r"to subject 8; it is subject 6's"),
    # a landmark under a robot's subject (it replaced the robot)
    ('Landmark_Groundtruth.dat', '3 5.0 5.0 0.0 0.0', r"data row 3 lists "
     r"subject 3, a robot's \(1 to 5\)"),
    # a second log appended: its time starts again (it was sorted in)
    ('Robot4_Groundtruth.dat', f'{T0} 3.0 1.5 0.0',
     r"'Robot4_Groundtruth.dat': data row 3001 goes back in time"),
    # a bearing of 100 rad was wrapped to -0.531 rad and used
    ('Robot1_Measurement.dat', f'{T0 + 2.0} 16 1.0 100.0',
     r"'Robot1_Measurement.dat': data row 6 gives a bearing of 100.0 rad, "
     r"outside \[-pi, pi\]"),
])
def test_clashing_ids_and_time_going_back_are_refused_by_row(folder, name,
                                                             row, match):
    path = folder / name
    path.write_text(path.read_text() + row + '\n')
    with pytest.raises(ValueError, match=match):
        read_mrclam(folder)


def test_a_negative_range_is_the_likelihoods_to_take(folder):
    # read as it is; kept where the likelihood takes negative ranges (every
    # model of the library does), refused by file and row where not
    path = folder / 'Robot3_Measurement.dat'
    path.write_text(path.read_text() + f'{T0 + 2.45} 17 -0.2 0.1\n')
    sequence = read_mrclam(folder)
    data, _ = mrclam_realization(sequence, duration=10.0)
    assert float(data.edge_attr[:, 0].min()) == pytest.approx(-0.2)
    with pytest.raises(ValueError, match=(
            r"'Robot3_Measurement.dat': data row 3 gives a negative range "
            r"\(-0.2 m\), which the likelihood does not take")):
        mrclam_realization(sequence, duration=10.0, negative_ranges=False)


def test_interpolate_pose_turns_the_short_way():
    truth = np.array([[0.0, 0.0, 0.0, 3.1], [1.0, 1.0, 0.0, -3.1]])
    pose = interpolate_pose(truth, np.array([0.5]))
    assert abs(abs(pose[0, 2]) - math.pi) < 1e-9


SEQUENCE_6 = Path(__file__).resolve().parents[3] / 'shared' / 'data' / \
    'mrclam' / 'MRCLAM_Dataset6.zip'


@pytest.mark.skipif(not SEQUENCE_6.is_file(),
                    reason=f'sequence 6 is not at {SEQUENCE_6}')
def test_sequence_6_under_the_test_protocol():
    data, counts = mrclam_realization(read_mrclam(SEQUENCE_6))
    check_realization(data, ('range', 'bearing'))
    assert int(data.num_steps) == 1200 and data.num_nodes == 20
    assert int((~data.anchor).sum()) == 5
    assert data.edge_index.size(1) == 8164
    assert counts == dict(unknown_barcodes=6, repeated=3813, outside=7394)
    assert not bool(torch.isnan(data.control[:5]).any())


def test_fitted_noise_recovers_a_simulation():
    # simulated robots of known noise, read as a sequence would be: the
    # fitted scales, tails and odometry variances are the simulation's
    from tg_nebp.datasets import Scenario, fit_models
    scenario = Scenario.load('robots_test')
    data = scenario.generate(torch.Generator().manual_seed(5))
    motion, measurement, report = fit_models(data)
    truth = scenario.measurement_model
    assert measurement.sigma == pytest.approx(truth.sigma, rel=0.1)
    assert measurement.sigma_bearing == pytest.approx(truth.sigma_bearing,
                                                      rel=0.1)
    assert measurement.nu >= 16  # Gaussian residuals: light tails
    assert report['range_beyond_3_sigma'] < 0.01
    assert abs(report['range_bias_slope']) < 0.02
    typical = data.control[:scenario.num_agents].reshape(-1, 2).median(0)
    fitted = motion.input_variances(typical.values.double().view(1, 2))
    true = scenario.motion_model.input_variances(
        typical.values.double().view(1, 2))
    assert torch.allclose(fitted.sqrt(), true.sqrt(), rtol=0.15)


def test_a_sequence_that_cannot_be_fitted_says_what_it_lacks():
    # each lack named as it is (not a NaN model parameter or a raw
    # numpy error)
    from tg_nebp.datasets import Scenario, fit_models
    scenario = Scenario.load('robots_test').replace(num_steps=30)
    data = scenario.generate(torch.Generator().manual_seed(5))
    with pytest.raises(ValueError, match=r"has 30 steps, fewer moves \(29\) "
                       r"than the horizon of 40 steps.*at most 29"):
        fit_models(data, horizon=40)
    few = data.clone()
    few.edge_index, few.edge_attr = data.edge_index[:, :2], data.edge_attr[:2]
    few.edge_time = data.edge_time[:2]
    with pytest.raises(ValueError, match="has 2 usable links.*at least 3"):
        fit_models(few, horizon=5)
    still = data.clone()
    still.states = data.states[:, :1].expand_as(data.states).clone()
    with pytest.raises(ValueError, match="no robot moves"):
        fit_models(still, horizon=5)
    blind = data.clone()
    blind.control = torch.full_like(data.control, float('nan'))
    with pytest.raises(ValueError, match="has no odometry"):
        fit_models(blind, horizon=5)
    fit_models(data, horizon=5)  # the sequence itself fits
