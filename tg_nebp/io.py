r"""File writing shared by the CLI: every file is written to a temporary
name in the same folder and renamed, so a killed run never leaves a
half-written result."""
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Union

__all__ = ['atomic_write', 'write_json', 'write_text', 'read_json']


def atomic_write(path: Union[str, Path], write: Callable[[str], None]):
    r"""Calls :obj:`write(tmp_path)` and renames the result to :obj:`path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f'.{path.name}.',
                               suffix='.partial')
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 is for the temp
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_json(path: Union[str, Path], obj: Any):
    r"""Writes :obj:`obj` as indented JSON, atomically."""
    write_text(path, json.dumps(obj, indent=2, sort_keys=True) + '\n')


def write_text(path: Union[str, Path], text: str):
    r"""Writes :obj:`text`, atomically."""
    def write(tmp):
        with open(tmp, 'w') as f:
            f.write(text)

    atomic_write(path, write)


def read_json(path: Union[str, Path]) -> Any:
    r"""Reads a JSON file; a file that is not valid JSON gets a clear
    error."""
    try:
        with open(path) as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise ValueError(f"'{path}' is not a valid JSON file: {e}") from e
