r"""File writing shared by the library: every file is written to a
temporary name in the same folder and renamed, so a killed run never leaves
a half-written result; the temporaries that killed runs leave behind are
removed at the next write to their folder."""
import json
import math
import os
import pickle
import re
import socket
import tempfile
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Union

import torch

__all__ = ['atomic_write', 'write_json', 'write_text', 'read_json',
           'read_tensors',
           'read_resumable', 'NUMBER', 'Number', 'claim_folder',
           'remove_stale_temporaries', 'check_writable_folder', 'one_line',
           'first_line']

_ANSI_ESCAPE = re.compile(r'\x1b\[[0-9;]*[A-Za-z]')

# '.~<pid>@<host>~<name>.<random>.partial': the writer is known, so only
# the temporaries of processes that no longer run are removed
_TEMPORARY = re.compile(r'\.~(?P<pid>\d+)@(?P<host>[^~/]+)~.*\.partial\Z')
# the unnamed temporaries of earlier tg_nebp versions: no live write lasts
# this long (seconds)
_UNNAMED_STALE_AFTER = 24 * 3600


def atomic_write(path: Union[str, Path], write: Callable[[str], None]):
    r"""Calls :obj:`write(tmp_path)` and renames the result to :obj:`path`;
    first removes the stale temporaries of killed writes in that folder
    (:func:`remove_stale_temporaries`)."""
    path = Path(path)
    if path.is_dir():  # else the rename's error names the temporary
        raise IsADirectoryError(f"'{path}' is a folder, not a file")
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path.parent)
    fd, tmp = tempfile.mkstemp(
        dir=path.parent, prefix=f'.~{os.getpid()}@{_host()}~{path.name}.',
        suffix='.partial')
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 is for the temp
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def remove_stale_temporaries(folder: Union[str, Path]) -> None:
    r"""Removes this library's temporary files in :obj:`folder` that no
    live write owns: those written on this host by a process that has
    ended, and unnamed ones (earlier versions) unmodified for a day. Another
    process's live temporary is never touched."""
    host = _host()
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for entry in entries:
        if not (entry.name.startswith('.') and entry.name.endswith('.partial')
                and entry.is_file(follow_symlinks=False)):
            continue
        match = _TEMPORARY.match(entry.name)
        if match is not None:
            stale = (match['host'] == host
                     and not _process_alive(int(match['pid'])))
        else:
            try:
                age = time.time() - entry.stat(follow_symlinks=False).st_mtime
            except OSError:
                continue
            stale = age > _UNNAMED_STALE_AFTER
        if stale:
            try:
                os.unlink(entry.path)
            except OSError:  # removed by another cleaner meanwhile
                pass


def _host() -> str:
    return socket.gethostname().replace('~', '-').replace('/', '-') or 'host'


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by another user
        return True
    return True


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_json(path: Union[str, Path], obj: Any, sort_keys: bool = True):
    r"""Writes :obj:`obj` as indented JSON, atomically, with the keys of
    every object sorted, or in their order in :obj:`obj` (an order that
    means something, such as a table's rows) without :obj:`sort_keys`."""
    write_text(path, json.dumps(obj, indent=2, sort_keys=sort_keys) + '\n')


def _verify_archive(path: Union[str, Path]) -> None:
    # the CRC-32 of every member of the zip archive that torch.save writes
    # (a file that is no zip archive is left to torch.load, which refuses
    # it): zipfile reads each member and compares
    if not zipfile.is_zipfile(path):
        return
    with zipfile.ZipFile(path) as archive:
        bad = archive.testzip()
    if bad is not None:
        raise zipfile.BadZipFile(f"the checksum of {bad!r} does not match: "
                                 f"the file was changed after it was "
                                 f"written")


def read_tensors(path: Union[str, Path], what: str) -> Any:
    r"""The object that :func:`torch.save` wrote to :obj:`path`, read with
    :obj:`weights_only=True`: tensors and plain values only, so no code
    from the file runs. A missing, foreign or unsafe file is a
    :class:`ValueError` that calls it :obj:`what` (a checkpoint, a saved
    session), and so is a damaged one: every member's checksum in the
    archive is verified first (:func:`torch.load` does not), so a flipped
    bit is refused whole, never loaded as a changed value."""
    try:
        _verify_archive(path)
        return torch.load(path, map_location='cpu', weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"{what} '{path}' does not exist") from None
    except pickle.UnpicklingError as e:
        # never pass on torch's advice to retry with weights_only=False
        # (torch names the refused class or function: 'Unsupported global';
        # random bytes fail on an opcode instead)
        reason = ('it holds objects other than tensors and primitives: '
                  'refused' if 'global' in str(e).lower() else
                  'corrupt or foreign')
        raise ValueError(f"'{path}' is not a readable {what}: {reason}"
                         ) from None
    except Exception as e:  # the unpickler raises many kinds on bad input
        raise ValueError(f"'{path}' is not a readable {what} (corrupt or "
                         f"foreign): {first_line(e)}") from None


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
        # past a byte-order mark, which common editors write
        with open(path, encoding='utf-8-sig') as f:
            return json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"'{path}' is not a valid JSON file: {e}") from None
    except OSError as e:
        raise ValueError(f"cannot read '{path}': "
                         f"{e.strerror or e}") from None


#: A JSON number in an entry's schema (:func:`read_resumable`).
NUMBER = (int, float)


@dataclass(frozen=True)
class Number:
    r"""In an entry's schema (:func:`read_resumable`): a finite JSON number
    from :obj:`minimum` to :obj:`maximum`, above :obj:`minimum` only if
    :obj:`positive` (a divisor)."""
    minimum: float = -math.inf
    maximum: float = math.inf
    positive: bool = False


def _schema_error(value, schema, where: str) -> Optional[str]:
    # where 'value' departs from 'schema': a type (or tuple of types), a
    # Number, a list of schemas (a list of as many items, of these schemas
    # in order) or a dict of required fields and their schemas; None where
    # it does not
    if isinstance(schema, dict):
        if not isinstance(value, dict):
            return f'{where} is not an object'
        for field, inner in schema.items():
            if field not in value:
                return f"{where} has no field '{field}'"
            error = _schema_error(value[field], inner, f"{where}['{field}']")
            if error:
                return error
        return None
    if isinstance(schema, list):
        if not isinstance(value, list):
            return f'{where} is not a list ({value!r})'
        if len(value) != len(schema):
            return (f'{where} is a list of length {len(value)}, not '
                    f'{len(schema)}')
        for i, (item, inner) in enumerate(zip(value, schema)):
            error = _schema_error(item, inner, f'{where}[{i}]')
            if error:
                return error
        return None
    if isinstance(schema, Number):
        low, high = schema.minimum, schema.maximum
        if (isinstance(value, bool) or not isinstance(value, NUMBER)
                or not (math.isfinite(value) and value <= high and (
                    value > low if schema.positive else value >= low))):
            within = (f"in {'(' if schema.positive else '['}{low:g}, "
                      f"{high:g}]" if high < math.inf else
                      f"{'>' if schema.positive else '>='} {low:g}")
            return f'{where} is {value!r}, not a finite number {within}'
        return None
    if isinstance(value, bool) or not isinstance(value, schema):
        return f'{where} is not of the expected type ({value!r})'
    return None


def read_resumable(path: Union[str, Path], settings: dict, section: str,
                   what: str = 'a result',
                   schema: Union[dict, Callable[[str], dict], None] = None,
                   depth: int = 1) -> dict:
    r"""The content of a resumable result file (:obj:`frontier.json`,
    :obj:`compare.json`): :obj:`{"settings": settings, section: {}}` if
    :obj:`path` does not exist, else the file, which must be a JSON object
    with exactly these :obj:`settings` and a :obj:`section` that maps
    names to entries (through :obj:`depth` levels of objects), each with
    the fields of :obj:`schema`: a dict of fields and their types, value
    ranges (:class:`Number`), lists of schemas (a list of as many items)
    or sub-schemas, or a function from an entry's name to its dict, where
    entries differ. Anything else is a :class:`ValueError` naming the file
    and the entry, rather than results of other settings mixed in or a
    traceback later."""
    path = Path(path)
    if not path.exists():
        return {'settings': settings, section: {}}
    content = read_json(path)
    found = content.get('settings') if isinstance(content, dict) else None
    if found != settings:
        raise ValueError(f"'{path}' holds {what} made with {found}, not "
                         f"{settings}: use another --out folder")
    # the section's levels of objects, then every entry against the schema
    entries = [(f"'{section}'", None, content.get(section))]
    for _ in range(depth):
        error = next((f'{where} is not an object'
                      for where, _, value in entries
                      if not isinstance(value, dict)), None)
        if error is not None:
            break
        entries = [(f'{where}[{name!r}]', name, entry)
                   for where, _, value in entries
                   for name, entry in value.items()]
    else:
        schema_of = schema if callable(schema) else lambda _: schema or {}
        error = next(filter(None, (_schema_error(value, schema_of(name),
                                                 where)
                                   for where, name, value in entries)), None)
    if error is not None:
        raise ValueError(f"'{path}' is damaged: {error}; remove the file to "
                         f"start again")
    return content


def claim_folder(out: Union[str, Path], settings: dict) -> None:
    r"""Marks the folder :obj:`out` as holding the results of a run with
    these :obj:`settings` (:obj:`out/settings.json`); a folder that holds a
    run with other settings is a :class:`ValueError`, not results of two
    runs mixed in one folder."""
    path = Path(out) / 'settings.json'
    if path.exists():
        found = read_json(path)
        if found != settings:
            raise ValueError(f"'{out}' holds a run with other settings "
                             f"({found}, not {settings}); use another "
                             f"--out")
    write_json(path, settings)


def check_writable_folder(path: Union[str, Path], name: str) -> Path:
    r"""Creates the folder :obj:`path` if needed and checks that files can
    be written in it, before any work that would write there starts; a
    :class:`ValueError` names the argument :obj:`name` otherwise."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{name} '{path}' is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as e:
        raise ValueError(f"{name} '{path}' is not a writable folder: "
                         f"{e.strerror or e}") from None
    return path


def one_line(error: Union[BaseException, str]) -> str:
    r"""An error message on one line, without terminal colour codes."""
    text = _ANSI_ESCAPE.sub('', str(error))
    return ' '.join(text.split()) or type(error).__name__


def first_line(error: BaseException) -> str:
    r"""The first line of an error message, without colour codes (the rest
    of a library's message is often advice that does not apply)."""
    lines = _ANSI_ESCAPE.sub('', str(error)).strip().splitlines()
    return lines[0].strip() if lines else type(error).__name__
