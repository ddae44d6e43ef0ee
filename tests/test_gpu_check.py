r"""benchmarks/gpu_check.sh: it parses, refuses an unknown option in one
line, and refuses to run for real where there is no CUDA device. Its
--dry-run (about 3 minutes here) runs every step on the CPU; it is run by
hand, not in CI."""
import shutil
import subprocess
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parent.parent / 'benchmarks' / 'gpu_check.sh'


def run(*args, **kw):
    return subprocess.run(['bash', str(SCRIPT), *args], capture_output=True,
                          text=True, timeout=120, **kw)


def test_script_parses():
    assert subprocess.run(['bash', '-n', str(SCRIPT)]).returncode == 0


def test_unknown_option_is_one_error_line(tmp_path):
    done = run('--fast', '--out', str(tmp_path))
    assert done.returncode == 2
    assert done.stderr.splitlines() == [
        "error: unknown option '--fast' (use --dry-run, --out DIR, --help)"]


@pytest.mark.parametrize('args,message', [
    (('--out', ), '--out needs a folder (--out DIR)'),
    (('--out', ''), '--out needs a folder (--out DIR)'),
    (('--out', '--dry-run'), '--out needs a folder (--out DIR)'),
    (('--out', '{file}'), "--out '{file}' is a file, not a folder"),
    (('--out', '{file}/sub'), "--out '{file}/sub' cannot be created"),
])
def test_a_bad_out_is_one_error_line_before_any_work(tmp_path, args,
                                                     message):
    file = tmp_path / 'a_file'
    file.write_text('keep')
    done = run(*(a.format(file=file) for a in args), cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.splitlines() == ['error: ' +
                                        message.format(file=file)]
    assert done.stdout == ''
    assert file.read_text() == 'keep'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['a_file']


def test_help_prints_the_usage():
    done = run('--help')
    assert done.returncode == 0 and done.stderr == ''
    assert done.stdout.startswith('usage: bash benchmarks/gpu_check.sh '
                                  '[--out DIR] [--dry-run] [--help]')
    assert '--dry-run' in done.stdout and '--out DIR' in done.stdout


@pytest.mark.skipif(torch.cuda.is_available(), reason='a CUDA device here')
def test_without_cuda_it_stops_before_any_work(tmp_path):
    assert shutil.which('python3') is not None
    done = run('--out', str(tmp_path / 'check'))
    assert done.returncode == 2
    assert done.stderr.splitlines() == [
        'error: no CUDA device here (use --dry-run on a CPU)']
    assert not (tmp_path / 'check' / 'summary.json').exists()
