r"""Seconds and peak memory of generating a realization of the paper's test
network grown to many agents (Scenario.grown, the same density), and of
its link search alone (RangeModel.connect, a cell list), each measurement
in a fresh process.

    python benchmarks/scenario_generation_scaling.py --agents 10000 100000 \
        1000000 --steps 2
"""
import argparse
import json
import multiprocessing
import resource
import time


def measure(agents: int, steps: int, queue) -> None:
    import torch

    from tg_nebp.datasets import Scenario

    torch.set_num_threads(1)
    scenario = Scenario.load('paper_test').grown(agents).replace(
        num_steps=steps)
    start = time.perf_counter()
    data = scenario.generate(torch.Generator().manual_seed(0))
    generation = time.perf_counter() - start
    positions = data.states[:, 0, :scenario.position_dim]
    start = time.perf_counter()
    edges = scenario.measurement_model.connect(positions, ~data.anchor)
    search = time.perf_counter() - start
    queue.put(dict(agents=agents, nodes=data.num_nodes, steps=steps,
                   links_per_step=edges.size(1),
                   generation_s=round(generation, 2),
                   link_search_s=round(search, 2),
                   peak_gib=round(resource.getrusage(
                       resource.RUSAGE_SELF).ru_maxrss / 2**20, 2)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--agents', type=int, nargs='+',
                        default=[10_000, 100_000])
    parser.add_argument('--steps', type=int, default=2)
    args = parser.parse_args()
    context = multiprocessing.get_context('spawn')
    for agents in args.agents:
        queue = context.Queue()
        child = context.Process(target=measure,
                                args=(agents, args.steps, queue))
        child.start()
        child.join()
        if child.exitcode != 0:
            print(json.dumps(dict(agents=agents, failed=child.exitcode)))
            continue
        print(json.dumps(queue.get()), flush=True)


if __name__ == '__main__':
    main()
