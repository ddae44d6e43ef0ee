r"""Every notebook in examples/ runs top to bottom without an error and is
stored without outputs (so that git stays small)."""
from pathlib import Path

import nbclient
import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = sorted((ROOT / 'examples').glob('*.ipynb'))

pytestmark = pytest.mark.notebooks


def test_examples_exist():
    assert NOTEBOOKS, f'no notebooks found in {ROOT / "examples"}'


@pytest.mark.parametrize('path', NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == 'code':
            assert cell.outputs == [], f'{path.name}: cell {i} has stored outputs'
            assert cell.execution_count is None, \
                f'{path.name}: cell {i} has an execution count'


@pytest.mark.parametrize('path', NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path, monkeypatch):
    # the kernel inherits it: on a busy 2-core machine spin-waiting OpenMP
    # threads made NEBP training ~30x slower than one thread
    monkeypatch.setenv('OMP_NUM_THREADS', '1')
    nb = nbformat.read(path, as_version=4)
    # the kernel's working directory is the repository root, so that relative
    # paths such as 'datasets' resolve as in the README
    client = nbclient.NotebookClient(
        nb, timeout=900, kernel_name='python3',
        resources={'metadata': {'path': str(ROOT)}})
    client.execute()  # raises CellExecutionError on the first failing cell
