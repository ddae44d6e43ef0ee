r"""Tests of :mod:`tg_nebp.io`: atomic writes, the removal of the
temporaries that killed runs leave, writable-folder checks and one-line
error messages."""
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
    from tg_nebp.experiments.compare import ROW_SCHEMA
    from tg_nebp.io import NUMBER, read_resumable, write_json
    path, settings = tmp_path / 'r.json', dict(seed=0)
    summary = dict(mean=0.1, std=0.0)
    row = dict(method='m', rmse=1.0, seconds_per_realization=2,
               outage={'0.5': 0.5, '1.0': 0.1, '2.0': 0.0},
               accept={'0.95': 0.9},
               spread={'realizations': [], 'outage_1m': summary,
                       'rmse': summary, 'accept_0.95': summary})
    good = dict(settings=settings, results={'s': {'a': row}})
    write_json(path, good)
    assert read_resumable(path, settings, 'results', schema=ROW_SCHEMA,
                          depth=2) == good
    for damaged, message in [
            (dict(good, results={'s': [row]}), r"'results'\['s'\] is not "
             r"an object"),
            (dict(good, results={'s': {'a': dict(row, rmse=None)}}),
             r"'results'\['s'\]\['a'\]\['rmse'\] is not of the expected"),
            (dict(good, results={'s': {'a': dict(row, accept={})}}),
             r".*\['accept'\] has no field '0.95'"),
            (dict(good, results={'s': {'a': dict(row, rmse=True)}}),
             r".*\['rmse'\] is not of the expected")]:
        write_json(path, damaged)
        with pytest.raises(ValueError, match=r"r\.json' is damaged: " +
                           message):
            read_resumable(path, settings, 'results', schema=ROW_SCHEMA,
                           depth=2)
    assert NUMBER == (int, float)
