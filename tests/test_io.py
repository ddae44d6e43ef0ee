r"""Tests of :mod:`tg_nebp.io`: atomic writes, the removal of the
temporaries that killed runs leave, writable-folder checks and one-line
error messages."""
import math
import os
import subprocess
import sys

import pytest

from tg_nebp import io


def touch(path, age_seconds=0.0):
    path.write_text('partial')
    if age_seconds:
        stamp = path.stat().st_mtime - age_seconds
        os.utime(path, (stamp, stamp))
    return path


def dead_pid():
    r"""The pid of a process that has ended (and been reaped)."""
    child = subprocess.Popen([sys.executable, '-c', 'pass'])
    child.wait()
    return child.pid


def test_killed_writes_are_removed_live_ones_kept(tmp_path):
    host = io._host()
    dead = touch(tmp_path / f'.~{dead_pid()}@{host}~metrics.json.x1.partial')
    live = touch(tmp_path / f'.~{os.getpid()}@{host}~metrics.json.x2.partial')
    remote = touch(tmp_path / f'.~{dead_pid()}@elsewhere~a.json.x3.partial')
    old_unnamed = touch(tmp_path / '.nebp.pt.abc123.partial', 2 * 86400)
    new_unnamed = touch(tmp_path / '.nebp.pt.def456.partial')
    foreign = touch(tmp_path / 'notes.partial', 2 * 86400)  # not ours
    io.write_json(tmp_path / 'metrics.json', {'a': 1})
    left = set(os.listdir(tmp_path))
    assert dead.name not in left and old_unnamed.name not in left
    # another process's write may be under way: never touched
    assert {live.name, remote.name, new_unnamed.name, foreign.name,
            'metrics.json'} == left


def test_atomic_write_names_its_temporary_after_its_process(tmp_path):
    seen = []

    def write(tmp):
        seen.append(os.path.basename(tmp))
        with open(tmp, 'w') as f:
            f.write('x')

    io.atomic_write(tmp_path / 'out.txt', write)
    assert io._TEMPORARY.match(seen[0])['pid'] == str(os.getpid())
    assert os.listdir(tmp_path) == ['out.txt']


def test_failed_write_leaves_no_temporary(tmp_path):
    def failing(tmp):
        raise OSError('disk full')

    with pytest.raises(OSError, match='disk full'):
        io.atomic_write(tmp_path / 'out.txt', failing)
    assert os.listdir(tmp_path) == []


def test_check_writable_folder(tmp_path):
    assert io.check_writable_folder(tmp_path / 'a' / 'b', '--out').is_dir()
    a_file = tmp_path / 'file'
    a_file.write_text('x')
    with pytest.raises(ValueError, match=r"--out '.*file' is a file"):
        io.check_writable_folder(a_file, '--out')
    with pytest.raises(ValueError, match=r"--out '.*file/sub' is not a "
                       r"writable folder"):
        io.check_writable_folder(a_file / 'sub', '--out')


def test_read_json_names_the_file(tmp_path):
    bad = tmp_path / 'bad.json'
    bad.write_text('{"name": ')
    with pytest.raises(ValueError, match=r"'.*bad.json' is not a valid JSON"):
        io.read_json(bad)
    with pytest.raises(ValueError, match=r"cannot read '.*missing.json'"):
        io.read_json(tmp_path / 'missing.json')


def test_messages_on_one_line_without_colour_codes():
    error = RuntimeError('Weights only load failed. \x1b[1mdo this\x1b[0m\n'
                         '\tsecond line\n')
    assert io.one_line(error) == ('Weights only load failed. do this second '
                                  'line')
    assert io.first_line(error) == 'Weights only load failed. do this'


def test_read_resumable_checks_every_entry_against_the_schema(tmp_path):
    from tg_nebp.io import NUMBER, Number, read_resumable, write_json
    path, settings = tmp_path / 'r.json', dict(seed=0)
    probability = Number(0.0, 1.0)
    schema = dict(method=str, rmse=NUMBER, accept={'0.95': probability},
                  per=[[probability, Number(0.0, positive=True)]] * 2)
    row = dict(method='m', rmse=1.0, accept={'0.95': 0.9},
               per=[[0.5, 1.0], [0.0, 2]])
    good = dict(settings=settings, results={'s': {'a': row}})
    write_json(path, good)
    assert read_resumable(path, settings, 'results', schema=schema,
                          depth=2) == good
    entry = r"'results'\['s'\]\['a'\]"
    for damaged, message in [
            ([row], r"'results'\['s'\] is not an object"),
            (dict(row, rmse=None), entry + r"\['rmse'\] is not of the "
             r"expected"),
            (dict(row, accept={}), entry + r"\['accept'\] has no field "
             r"'0.95'"),
            (dict(row, rmse=True), entry + r"\['rmse'\] is not of the "
             r"expected"),
            # values, not only types: ranges, finite, lists of one length
            (dict(row, accept={'0.95': 1.5}), entry + r"\['accept'\]"
             r"\['0.95'\] is 1.5, not a finite number in \[0, 1\]"),
            (dict(row, accept={'0.95': math.nan}), entry + r"\['accept'\]"
             r"\['0.95'\] is nan, not a finite"),
            (dict(row, accept={'0.95': True}), entry + r"\['accept'\]"
             r"\['0.95'\] is True, not a finite"),
            (dict(row, per=[[0.5, 0.0], [0.0, 2]]), entry + r"\['per'\]"
             r"\[0\]\[1\] is 0.0, not a finite number > 0"),
            (dict(row, per=[[0.5, math.inf], [0.0, 2]]), entry +
             r"\['per'\]\[0\]\[1\] is inf, not a finite number > 0"),
            (dict(row, per=[]), entry + r"\['per'\] is a list of length "
             r"0, not 2"),
            (dict(row, per=[[0.5], [0.0, 2]]), entry + r"\['per'\]\[0\] "
             r"is a list of length 1, not 2"),
            (dict(row, per='x'), entry + r"\['per'\] is not a list")]:
        write_json(path, dict(good, results={'s': damaged if isinstance(
            damaged, list) else {'a': damaged}}))
        with pytest.raises(ValueError, match=r"r\.json' is damaged: " +
                           message + r".*remove the file"):
            read_resumable(path, settings, 'results', schema=schema,
                           depth=2)
    assert NUMBER == (int, float)


def test_read_resumable_with_a_schema_per_entry_name(tmp_path):
    from tg_nebp.io import Number, read_resumable, write_json
    path, settings = tmp_path / 'r.json', dict(seed=0)

    def schema(name):  # the entry 'floor' divides: positive
        return dict(rmse=Number(0.0, positive=name == 'floor'))

    good = dict(settings=settings, points={'floor': {'rmse': 1.0},
                                           'other': {'rmse': 0.0}})
    write_json(path, good)
    assert read_resumable(path, settings, 'points', schema=schema) == good
    write_json(path, dict(good, points={'floor': {'rmse': 0.0}}))
    with pytest.raises(ValueError, match=r"'points'\['floor'\]\['rmse'\] "
                       r"is 0.0, not a finite number > 0"):
        read_resumable(path, settings, 'points', schema=schema)


def test_write_json_keeps_the_order_without_sort_keys(tmp_path):
    rows = {'pcrb': 1, 'iekf': {'z': 1, 'a': 2}, 'bp': 3}
    io.write_json(tmp_path / 'kept.json', rows, sort_keys=False)
    io.write_json(tmp_path / 'sorted.json', rows)
    kept = io.read_json(tmp_path / 'kept.json')
    assert list(kept) == ['pcrb', 'iekf', 'bp']
    assert list(kept['iekf']) == ['z', 'a']
    assert list(io.read_json(tmp_path / 'sorted.json')) == ['bp', 'iekf',
                                                            'pcrb']
