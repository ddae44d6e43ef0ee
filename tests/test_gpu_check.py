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
        "error: unknown option '--fast' (use --dry-run, --out DIR)"]


@pytest.mark.skipif(torch.cuda.is_available(), reason='a CUDA device here')
def test_without_cuda_it_stops_before_any_work(tmp_path):
    assert shutil.which('python3') is not None
    done = run('--out', str(tmp_path / 'check'))
    assert done.returncode == 2
    assert done.stderr.splitlines() == [
        'error: no CUDA device here (use --dry-run on a CPU)']
    assert not (tmp_path / 'check' / 'summary.json').exists()
