r"""What a Gaussian NEBP correction learned: the distribution of its message
weights on LOS and NLOS links (the generated data's true NLOS flag, which
the tracker never reads), and its inflations against the agents'
consistency (the mean squared normalized residual of their links), on test
realizations of a scenario.

    python benchmarks/gnebp_learned.py --checkpoint nlos \
        --scenario paper_test_nlos --realizations 4
"""
import argparse
import json
import math

import torch


def quantiles(values: torch.Tensor) -> dict:
    if values.numel() == 0:
        return {}
    q = torch.quantile(values.double(), torch.tensor(
        [0.1, 0.25, 0.5, 0.75, 0.9], dtype=torch.float64))
    return dict(count=values.numel(), mean=round(float(values.mean()), 3),
                **{f'q{int(100 * p)}': round(float(v), 3)
                   for p, v in zip((0.1, 0.25, 0.5, 0.75, 0.9), q)})


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--checkpoint', required=True,
                        help='a path or a shipped name')
    parser.add_argument('--scenario', default='paper_test_nlos')
    parser.add_argument('--realizations', type=int, default=4)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--root', default='datasets')
    args = parser.parse_args()

    from tg_nebp.datasets import load_datasets
    from tg_nebp.training import gaussian_nebp_from_checkpoint
    from tg_nebp.utils import link_factors

    tracker = gaussian_nebp_from_checkpoint(args.checkpoint).eval()
    conv = tracker.conv
    dataset, = load_datasets(args.root, (args.scenario, args.realizations,
                                         args.seed))
    flagged = 'nlos' in dataset.scenario.measurement_model.generated_features
    weights = {'los': [], 'nlos': []}
    inflations, consistencies = [], []
    current = {}

    def on_linearize(belief, edge_index, edge_attr, factors,
                     generator=None):
        # whether every message edge's factor is NLOS (a pair is NLOS in
        # both directions)
        graph = link_factors(edge_index, current['anchor'], conv.ends)
        nlos = torch.zeros(graph.ends.size(0), dtype=torch.bool)
        if flagged:
            nlos.index_put_((graph.factor, ), edge_attr[:, 1] > 0.5,
                            accumulate=True)
        current['message_nlos'] = nlos[graph.link]
        return original_linearize(belief, edge_index, edge_attr, factors,
                                  generator)

    def on_weights(edge):
        weight = original_weights(edge)
        flat, nlos = weight.view(-1), current['message_nlos']
        weights['nlos'].append(flat[nlos].detach())
        weights['los'].append(flat[~nlos].detach())
        return weight

    def on_inflation(cov, memory, anchor):
        kappa = original_inflation(cov, memory, anchor)
        agents = ~anchor
        inflations.append(kappa[agents].detach())
        consistencies.append(memory[agents, -1].detach())
        return kappa

    original_linearize, original_inflation = (conv.bp.linearize,
                                              conv.inflation)
    original_weights = conv.message_weights
    conv.bp.linearize, conv.inflation = on_linearize, on_inflation
    conv.message_weights = on_weights
    with torch.no_grad():
        for data in dataset:
            current['anchor'] = data.anchor
            for _ in tracker.steps(data):
                pass
    kappa = torch.cat(inflations)
    history = torch.cat(consistencies)
    bins = [0, 0.5, 1, 2, 4, 8, math.inf]
    by_consistency = []
    for a, b in zip(bins[:-1], bins[1:]):
        inside = (history >= a) & (history < b)
        by_consistency.append(dict(consistency=f'[{a}, {b})',
                                   **quantiles(kappa[inside])))
    print(json.dumps(dict(
        checkpoint=str(args.checkpoint), scenario=args.scenario,
        realizations=args.realizations, seed=args.seed,
        weight_los=quantiles(torch.cat(weights['los'])),
        weight_nlos=quantiles(torch.cat(weights['nlos'])) if flagged
        else None,
        inflation=quantiles(kappa),
        inflation_by_consistency_history=by_consistency), indent=1))


if __name__ == '__main__':
    main()
