r"""Every user error of the :obj:`tg-nebp` command line exits with status 2
and prints one line, starting with :obj:`error:`, that names what is wrong:
no traceback, no usage block, and no work done first.

Each case runs :obj:`python -m tg_nebp` in its own folder. Importing torch
takes seconds per process, so the module's processes run together, once
(:func:`cli_runs`), and each case's test checks its own result. The
processes inherit the environment, :obj:`PYTHONPATH` included."""
import json
import os
import random
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path
from typing import Callable, Dict, List, NamedTuple, Optional, Tuple

import pytest
import torch

from tg_nebp import NEBP
from tg_nebp.datasets import MRCLAMScenario
from tg_nebp.experiments.compare import run_compare
from tg_nebp.io import read_json, write_json
from tg_nebp.training import save_checkpoint

from helpers import mixed_k_checkpoint, write_mrclam

# tiny runs: a case that is not caught early still ends in seconds
EVALUATE = ['evaluate', '--realizations', '1', '--particles', '8', '--quiet']
TRAIN = ['train', '--realizations', '1', '--val-realizations', '1',
         '--epochs', '1', '--batch-size', '1', '--particles', '8', '--quiet']
NEBP_EVALUATE = ['evaluate', '--method', 'nebp', '--realizations', '1',
                 '--quiet']
SECONDS_PER_RUN = 120  # a hang fails its case, not the whole module

# a case writes its files into its folder and returns the command line and
# the texts (file names, flags) that its error line must contain
Prepare = Callable[[Path], Tuple[List[str], List[str]]]


class CreatesFileWhenUnpickled:
    r"""A malicious checkpoint's payload: unpickling it runs
    :obj:`open(path, 'w')`, which creates :obj:`path`."""
    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, 'w'))


def out_is_file(command: List[str]) -> Prepare:
    def prepare(folder):
        (folder / 'taken.txt').write_text('')
        return command + ['--out', 'taken.txt'], ['taken.txt']

    return prepare


def out_is_unwritable(command: List[str]) -> Prepare:
    def prepare(folder):
        if os.geteuid() == 0:  # root writes into read-only folders
            (folder / 'plain.txt').write_text('')
            out = 'plain.txt/sub'
        else:
            (folder / 'locked').mkdir(mode=0o500)
            out = 'locked/sub'
        return command + ['--out', out], [out]

    return prepare


def root_is_file(folder):
    (folder / 'taken.txt').write_text('')
    return EVALUATE + ['--root', 'taken.txt'], ['taken.txt']


def paper_test_fields() -> dict:
    scenarios = resources.files('tg_nebp.datasets') / 'scenarios'
    return json.loads((scenarios / 'paper_test.json').read_text())


def scenario_file(edit: Callable[[dict], None],
                  expected: Optional[str] = None) -> Prepare:
    r"""A copy of :obj:`paper_test` changed by :obj:`edit`; the error line
    names :obj:`expected`, by default the file."""
    def prepare(folder):
        fields = paper_test_fields()
        edit(fields)
        (folder / 'bad.json').write_text(json.dumps(fields))
        return (EVALUATE + ['--scenario', 'bad.json'],
                [expected or 'bad.json'])

    return prepare


def scenario_missing(folder):
    return EVALUATE + ['--scenario', 'missing.json'], ['missing.json']


def scenario_malformed(folder):
    (folder / 'bad.json').write_text('{"name": ')
    return EVALUATE + ['--scenario', 'bad.json'], ['bad.json']


def checkpoint_malicious(folder):
    torch.save(CreatesFileWhenUnpickled(folder / 'marker'),
               folder / 'evil.pt')
    return NEBP_EVALUATE + ['--checkpoint', 'evil.pt'], ['evil.pt']


def checkpoint_missing(folder):
    return NEBP_EVALUATE + ['--checkpoint', 'absent.pt'], ['absent.pt']


def checkpoint_random_bytes(folder):
    (folder / 'noise.pt').write_bytes(random.Random(0).randbytes(4096))
    return NEBP_EVALUATE + ['--checkpoint', 'noise.pt'], ['noise.pt']


def checkpoint_other_k(folder):
    save_checkpoint(folder / 'k8.pt', NEBP(num_particles=8))
    return (NEBP_EVALUATE + ['--checkpoint', 'k8.pt', '--particles', '16'],
            ['k8.pt'])


def checkpoint_weights_of_other_k(folder):
    mixed_k_checkpoint(folder / 'mixed.pt')
    return NEBP_EVALUATE + ['--checkpoint', 'mixed.pt'], ['mixed.pt']


COMPARE = ['compare', '--realizations', '1', '--quiet']


def compare_scenarios_of_one_name(folder):
    for name, agents in (('a.json', 10), ('b.json', 12)):
        fields = dict(paper_test_fields(), name='same', num_agents=agents)
        (folder / name).write_text(json.dumps(fields))
    return (COMPARE + ['--methods', 'pcrb', '--scenario', 'a.json',
                       'b.json'], ["'a.json'", "'b.json'", "'same'"])


def compare_checkpoint_not_selected(folder):
    save_checkpoint(folder / 'k8.pt', NEBP(num_particles=8))
    return (COMPARE + ['--methods', 'pcrb', '--checkpoint', 'k8.pt'],
            ['k8.pt', "'methods'"])


def compare_zero_floor(folder):
    # a finished comparison whose bound has a zero floor
    fields = dict(paper_test_fields(), name='small', num_agents=4,
                  num_steps=2)
    (folder / 'small.json').write_text(json.dumps(fields))
    argv = COMPARE + ['--methods', 'pcrb', '--scenario', 'small.json',
                      '--root', 'data', '--out', 'out']
    run_compare(root=str(folder / 'data'), scenarios=[folder / 'small.json'],
                realizations=1, out=folder / 'out', methods=['pcrb'],
                log=lambda line: None)
    content = read_json(folder / 'out' / 'compare.json')
    content['results']['small']['pcrb']['spread']['realizations'][0][2] = 0
    write_json(folder / 'out' / 'compare.json', content)
    return argv, ['compare.json', "['pcrb']", 'remove the file']


def mrclam_window_too_long(folder):
    # a 28-s sequence under the 600-s test protocol
    write_mrclam(folder / 'MRCLAM_Dataset9')
    return (['evaluate', '--method', 'iekf', '--quiet', '--scenario',
             'mrclam-9', '--root', '.'], ["'mrclam-9'", '600 s'])


def mrclam_compare_uneven(folder):
    # windows of 4 s every 4 s, and one window: tables of unequal length
    write_mrclam(folder / 'MRCLAM_Dataset9')
    MRCLAMScenario.load('mrclam-9').replace(
        name='strided', duration=4.0, stride=4.0).save(folder / 's.json')
    return (['compare', '--quiet', '--methods', 'pcrb', '--root', '.',
             '--scenario', 's.json', 'mrclam-9-first-half'],
            ['strided', 'mrclam-9-first-half', '--realizations'])


def fit_output_is_folder(folder):
    write_mrclam(folder / 'MRCLAM_Dataset9')
    (folder / 'taken').mkdir()
    return (['fit', '--sequence', '9', '--root', '.', '--output', 'taken'],
            ["'taken'", 'folder'])


def argv_only(argv: List[str], expected: List[str]) -> Prepare:
    return lambda folder: (argv, expected)


def delete(key: str) -> Callable[[dict], None]:
    return lambda fields: fields.pop(key)


def assign(key: str, value) -> Callable[[dict], None]:
    return lambda fields: fields.__setitem__(key, value)


def track_terabytes(folder: Path):
    # a live tracker sizes its particles as nodes join: an allocation that
    # fails is one error line naming --particles, not the allocator's
    # traceback
    line = dict(time=1.0, join=[
        dict(id=0, anchor=[0.0, 0.0]),
        dict(id=1, mean=[5.0, 5.0, 0.0, 0.0],
             cov=[[4.0, 0, 0, 0], [0, 4.0, 0, 0], [0, 0, 0.01, 0],
                  [0, 0, 0, 0.01]])],
                links=[[0, 1, 7.1]])
    (folder / 'm.jsonl').write_text(json.dumps(line) + '\n')
    return (['track', '--method', 'hybrid', '--particles', str(10**12),
             '--input', 'm.jsonl', '--output', 'e.jsonl'],
            ['out of memory', '--particles'])


CASES: Dict[str, Prepare] = {
    'evaluate-out-is-file': out_is_file(EVALUATE),
    'train-out-is-file': out_is_file(TRAIN),
    'evaluate-out-unwritable': out_is_unwritable(EVALUATE),
    'train-out-unwritable': out_is_unwritable(TRAIN),
    'evaluate-root-is-file': root_is_file,
    'scenario-missing': scenario_missing,
    'scenario-without-num_agents': scenario_file(delete('num_agents')),
    'scenario-fractional-num_agents': scenario_file(assign('num_agents', 2.5)),
    'scenario-scalar-prior_var': scenario_file(assign('prior_var', 10.0)),
    'scenario-malformed-json': scenario_malformed,
    # '..' as a processed-file name would escape the dataset folder
    'scenario-name-dotdot': scenario_file(assign('name', '..'), "'name'"),
    'mrclam-window-too-long': mrclam_window_too_long,
    'mrclam-unknown-option': argv_only(
        ['evaluate', '--scenario', 'mrclam-6-fast'], ["'fast'"]),
    'mrclam-compare-uneven': mrclam_compare_uneven,
    'fit-output-is-folder': fit_output_is_folder,
    'checkpoint-malicious-pickle': checkpoint_malicious,
    'checkpoint-missing': checkpoint_missing,
    'checkpoint-random-bytes': checkpoint_random_bytes,
    'checkpoint-other-K': checkpoint_other_k,
    'checkpoint-weights-of-other-K': checkpoint_weights_of_other_k,
    'particles-zero': argv_only(['evaluate', '--particles', '0'],
                                ['--particles']),
    'unknown-flag': argv_only(['evaluate', '--bogus-flag'], ['--bogus-flag']),
    'device-tpu': argv_only(['evaluate', '--device', 'tpu'], ['--device']),
    'no-subcommand': argv_only([], []),
    'bench-agents-zero': argv_only(['bench', '--agents', '0'], ['--agents']),
    'bp-iterations-receiver': argv_only(
        ['evaluate', '--iterations', '2'], ['--iterations 2',
                                            '--ends both']),
    'pcrb-with-particles': argv_only(
        ['evaluate', '--method', 'pcrb', '--particles', '8'],
        ['--particles', 'pcrb']),
    'iekf-with-inflation': argv_only(
        ['evaluate', '--method', 'iekf', '--inflation', '2'],
        ['--inflation', 'gbp']),
    'gbp-inflation-below-one': argv_only(
        ['evaluate', '--method', 'gbp', '--inflation', '0.5'],
        ['--inflation']),
    'compare-missing-checkpoint': argv_only(
        ['compare', '--checkpoint', 'absent.pt', '--realizations', '1',
         '--quiet'], ['absent.pt']),
    # before: one scenario's rows under the other's fingerprint; nothing
    # run, then an error of the figure; an ignored checkpoint; a
    # ZeroDivisionError in the table
    'compare-scenarios-of-one-name': compare_scenarios_of_one_name,
    'compare-methods-typo': argv_only(COMPARE + ['--methods', 'pcrbb'],
                                      ["'pcrbb'", 'pcrb, iekf']),
    'compare-nebp-without-checkpoint': argv_only(
        COMPARE + ['--methods', 'nebp'], ["'nebp'", '--checkpoint']),
    'compare-checkpoint-not-selected': compare_checkpoint_not_selected,
    'compare-zero-floor': compare_zero_floor,
    # options that a method does not take, ignored before
    'compare-compile': argv_only(COMPARE + ['--methods', 'pcrb',
                                            '--compile'], ['--compile']),
    'iekf-with-resampler': argv_only(
        ['evaluate', '--method', 'iekf', '--resampler', 'systematic'],
        ['--resampler', 'iekf']),
    'nebp-with-resampler': argv_only(
        NEBP_EVALUATE + ['--checkpoint', 'absent.pt', '--resampler',
                         'systematic'], ['--resampler', 'nebp']),
    'iekf-with-compile': argv_only(
        ['evaluate', '--method', 'iekf', '--compile'], ['--compile', 'iekf']),
    'device-cuda-99': argv_only(EVALUATE + ['--device', 'cuda:99'],
                                ['--device', 'cuda:99']),
    # parameters accepted before that broke the numbers later, blaming
    # something else
    'regularize-huge': argv_only(['evaluate', '--regularize', '1e30'],
                                 ['--regularize']),
    'lr-inf': argv_only(TRAIN + ['--lr', 'inf'], ['--lr']),
    'lr-huge': argv_only(TRAIN + ['--lr', '1e6'], ['--lr']),
    'scenario-student-t-nu-tiny': scenario_file(assign('measurement', dict(
        name='student-t', params=dict(sigma=1.0, nu=0.05))), "'nu'"),
    'scenario-student-t-nu-huge': scenario_file(assign('measurement', dict(
        name='student-t', params=dict(sigma=1.0, nu=1e300))), "'nu'"),
    'scenario-nlos-bias-tiny': scenario_file(assign('measurement', dict(
        name='nlos', params=dict(sigma=1.0, bias_mean=1e-9))), "'bias_mean'"),
    # networks and particle counts that need terabytes: refused up front
    'scenario-terabytes': scenario_file(assign('num_agents', 10**9),
                                        "'num_agents'"),
    'particles-terabytes': argv_only(EVALUATE + ['--particles', str(10**9)],
                                     ["'particles'"]),
    'track-particles-terabytes': track_terabytes,
}


class Run(NamedTuple):
    folder: Path
    expected: List[str]
    returncode: Optional[int]  # None: still running after SECONDS_PER_RUN
    stdout: str
    stderr: str


def run_cli(argv: List[str],
            folder: Path) -> Tuple[Optional[int], str, str]:
    try:
        done = subprocess.run([sys.executable, '-m', 'tg_nebp', *argv],
                              cwd=folder, capture_output=True,
                              timeout=SECONDS_PER_RUN)
        returncode, stdout, stderr = done.returncode, done.stdout, done.stderr
    except subprocess.TimeoutExpired as e:
        returncode, stdout, stderr = None, e.stdout, e.stderr
    return (returncode, (stdout or b'').decode(errors='replace'),
            (stderr or b'').decode(errors='replace'))


@pytest.fixture(scope='module')
def cli_runs(tmp_path_factory) -> Dict[str, Run]:
    r"""Every case's process, run concurrently once for the module."""
    prepared = {}
    for name, prepare in CASES.items():
        folder = tmp_path_factory.mktemp(name)
        prepared[name] = (folder, *prepare(folder))
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
        futures = {
            name: pool.submit(run_cli, argv, folder)
            for name, (folder, argv, _) in prepared.items()
        }
        return {
            name: Run(prepared[name][0], prepared[name][2],
                      *futures[name].result())
            for name in CASES
        }


@pytest.mark.parametrize('case', list(CASES))
def test_user_error_is_one_line(cli_runs, case):
    r"""Status 2 and exactly one line, :obj:`error: ...`, naming the file or
    flag at fault; no traceback, no colour codes, and never the advice to
    load a checkpoint with :obj:`weights_only=False`."""
    run = cli_runs[case]
    report = (f'status {run.returncode}\nstdout:\n{run.stdout}\n'
              f'stderr:\n{run.stderr}')
    assert run.returncode == 2, report
    assert 'Traceback' not in run.stdout + run.stderr, report
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, report
    line = lines[0]
    assert line.startswith('error:'), report
    assert '\x1b' not in line, report
    assert 'weights_only=False' not in line, report
    for text in run.expected:
        assert text in line, report


def test_malicious_checkpoint_runs_no_code(cli_runs):
    r"""The payload that :obj:`checkpoint-malicious-pickle` refuses would
    have created its marker file."""
    assert not (cli_runs['checkpoint-malicious-pickle'].folder /
                'marker').exists()


def test_malicious_checkpoint_payload_works(tmp_path):
    r"""The payload is live: unpickled without :obj:`weights_only`, it
    creates the marker, so its absence above means no code ran."""
    torch.save(CreatesFileWhenUnpickled(tmp_path / 'marker'),
               tmp_path / 'evil.pt')
    torch.load(tmp_path / 'evil.pt', weights_only=False).close()
    assert (tmp_path / 'marker').exists()
