r"""Tests of :mod:`tg_nebp.experiments.bench`: the figures describe the
graph that was measured, measurements that would not fit are skipped (not
killed), and the command line prints one JSON object per measurement."""
import json
import queue as queue_module

import pytest

from tg_nebp.experiments import bench
from tg_nebp.cli import main


def test_network_grows_the_test_network():
    small = bench.network(100, 2, 2, 0)
    assert small.num_graphs == 2 and int(small.num_nodes) == 2 * 113
    grown = bench.network(400, 1, 2, 0)
    assert int((~grown.anchor).sum()) == 400
    # same density: about four times the edges of one test network
    edges = [d.edges_by_step()[0][0].size(1) for d in (grown, small[0])]
    assert 3.0 < edges[0] / edges[1] < 5.0


@pytest.mark.parametrize('operation', ['bp', 'naive', 'nebp'])
def test_measure_reports_the_measured_graph(operation):
    figures = bench.measure(operation, 100, 32, repeats=1, steps=1)
    edge_index, _ = bench.network(100, 1, 3, 0).edges_by_step()[0]
    assert figures['edges'] == edge_index.size(1)
    assert figures['edge_particles'] == 32 * edge_index.size(1)
    assert figures['forward_edge_particles_per_s'] == pytest.approx(
        figures['edge_particles'] / (figures['forward_ms'] / 1e3))
    assert ('forward_backward_ms' in figures) == (operation != 'naive')


def test_measure_skips_what_does_not_fit(monkeypatch):
    monkeypatch.setattr(bench, 'free_memory_bytes', lambda device: 2**20)
    figures = bench.measure('nebp', 100, 1000)
    assert 'needs about' in figures['skipped']
    assert 'forward_ms' not in figures


def test_cli_prints_one_json_object_per_measurement(capsys):
    assert main(['bench', '--agents', '100', '--particles', '16', '24',
                 '--ops', 'tracker', '--steps', '1', '--json']) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(r['particles'], r['operation']) for r in rows] == [
        (16, 'tracker'), (24, 'tracker')]
    assert all(r['s_per_step'] > 0 and r['edges'] > 0 for r in rows)


def test_cli_rejects_non_positive_sizes(capsys):
    assert main(['bench', '--agents', '0']) == 2
    assert "'--agents' must be positive" in capsys.readouterr().err


@pytest.mark.parametrize('argv, message', [
    (['--samples', '16', '--particles', '8', '100'], "'--samples' [16]"),
    (['--chunk-size', '0'], "'--chunk-size' must be positive"),
])
def test_options_are_checked_before_any_process(argv, message, capsys,
                                                monkeypatch):
    monkeypatch.setattr(bench.multiprocessing, 'get_context', None)
    assert main(['bench', *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


class InlineContext:
    r"""A multiprocessing context whose processes run their target at
    start, in this process (so that a patched :func:`bench.measure`
    holds)."""
    Queue = staticmethod(queue_module.Queue)

    class Process:
        def __init__(self, target, args):
            self.target, self.args, self.exitcode = target, args, 0

        def start(self):
            self.target(*self.args)

        def is_alive(self):
            return False

        def join(self):
            pass


def test_a_failed_measurement_is_a_row_and_fails_the_bench(capsys,
                                                           monkeypatch):
    def measure(operation, *args):
        if operation == 'naive':
            raise RuntimeError('out of luck\nsecond line')
        return dict(forward_ms=1.0)

    monkeypatch.setattr(bench, 'measure', measure)
    monkeypatch.setattr(bench.multiprocessing, 'get_context',
                        lambda method: InlineContext)
    assert main(['bench', '--ops', 'bp', 'naive', 'tracker', '--particles',
                 '8', '--threads', '1']) == 1
    captured = capsys.readouterr()
    rows = captured.out.strip().splitlines()[1:]
    assert len(rows) == 3
    assert rows[1].endswith('failed: RuntimeError: out of luck')
    assert captured.err.strip().splitlines() == [
        'error: 1 of 3 measurements failed (see the table)']
