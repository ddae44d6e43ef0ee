r"""Seconds per time step and peak memory of Gaussian BP, fixed-lag Gaussian
BP (gbp-lagL: the recommended window of L steps, e.g. gbp-lag5;
gbp-lag5-residual: with residual scheduling), its learned correction,
Gaussian BP with the relocation of lost agents (gbp-relocation), hybrid BP
(hybrid, hybrid-lag3) and particle BP on the paper's test network grown to
many agents
(Scenario.grown, the same density), each measurement in a fresh process:
the figures of the docs' pages on Gaussian BP and Gaussian NEBP.

    python benchmarks/gbp_scaling.py --agents 10000 --methods gbp bp
    python benchmarks/gbp_scaling.py --agents 100 10000 --methods gbp \
        gbp-lag5 --steps 8      # a full window from the fifth step on
    python benchmarks/gbp_scaling.py --agents 10000 --methods gbp-lag20 \
        --steps 24              # 5 steps iterated, 15 settled
    python benchmarks/gbp_scaling.py --agents 100 10000 --methods gbp \
        gnebp:paper     # a Gaussian NEBP checkpoint: a path or shipped name
    python benchmarks/gbp_scaling.py --agents 100 1000 10000 --methods gbp \
        gbp-relocation hybrid --steps 6
"""
import argparse
import json
import multiprocessing
import resource
import time


def measure(method: str, agents: int, steps: int, queue) -> None:
    import torch

    from tg_nebp.datasets import Scenario
    from tg_nebp.filters import (FixedLagGaussianBP, GaussianBP, HybridBP,
                                 LinkSearch, ParticleBP)
    from tg_nebp.training import gaussian_nebp_from_checkpoint

    scenario = Scenario.load('paper_test').grown(agents).replace(
        num_steps=steps)
    start = time.perf_counter()
    data = scenario.generate(torch.Generator().manual_seed(0))
    generation = time.perf_counter() - start
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    # gbp-lagL: fixed-lag Gaussian BP's recommended window of L steps
    # (settled steps beyond 5), gbp-lagL-residual with residual scheduling
    window, _, residual = (method[len('gbp-lag'):].partition('-') if
                           method.startswith('gbp-lag') else ('', '', ''))
    tracker = {
        'gbp': lambda: GaussianBP.recommended(**models),
        'gbp-plain': lambda: GaussianBP.recommended(inflation=1.0,
                                                    **models),
        'gbp-lag': lambda: FixedLagGaussianBP.recommended(
            lag=int(window), **(dict(schedule='residual') if residual
                                else {}), **models),
        'gbp-relocation': lambda: GaussianBP.recommended(
            relocation=LinkSearch(), **models),
        'hybrid': lambda: HybridBP.recommended(**models),
        'hybrid-lag3': lambda: HybridBP.recommended(lag=3, **models),
        'bp': lambda: ParticleBP(1000, **models),
        'bp-recommended': lambda: ParticleBP.recommended(**models),
        'gnebp': lambda: gaussian_nebp_from_checkpoint(
            method.partition(':')[2]),
    }['gbp-lag' if window else method.partition(':')[0]]()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    times, start = [], time.perf_counter()
    with torch.no_grad():
        for _ in tracker.steps(data, torch.Generator().manual_seed(1)):
            now = time.perf_counter()
            times.append(now - start)
            start = now
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # the steps after the first (and, for a smoother, with a full window)
    later = sorted(times[max(1, getattr(tracker, 'lag', 1)):]) or times
    queue.put(dict(method=method, agents=agents, nodes=data.num_nodes,
                   edges_per_step=data.edge_index.size(1) // steps,
                   first_step_s=round(times[0], 3),
                   step_s=round(later[len(later) // 2], 3),
                   generation_s=round(generation, 1),
                   peak_gib=round(peak / 2**20, 2),
                   tracker_gib=round((peak - before) / 2**20, 2)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--agents', type=int, nargs='+', default=[10_000])
    parser.add_argument('--methods', nargs='+', default=['gbp', 'bp'])
    parser.add_argument('--steps', type=int, default=3,
                        help='time steps; the median of those after the '
                        'first is reported')
    args = parser.parse_args()
    context = multiprocessing.get_context('spawn')
    for agents in args.agents:
        for method in args.methods:
            queue = context.Queue()
            child = context.Process(target=measure, args=(
                method, agents, args.steps, queue))
            child.start()
            child.join()
            if child.exitcode != 0:
                print(json.dumps(dict(method=method, agents=agents,
                                      failed=child.exitcode)))
                continue
            print(json.dumps(queue.get()), flush=True)


if __name__ == '__main__':
    main()
