r"""Figures of the paper's Fig. 2 (tracks, outage and consistency curves,
with the paper's digitized curves for comparison), of the accuracy-cost
frontier and of a training run's losses, with matplotlib (a dependency of
the default install)."""
import math
from pathlib import Path
from typing import Dict, Union

import torch

from tg_nebp import metrics
from tg_nebp.io import atomic_write
from tg_nebp.reference import paper_curves

__all__ = ['plot_tracks', 'plot_outage', 'plot_consistency',
           'plot_frontier', 'plot_outage_against_particles',
           'plot_training_history', 'plot_compare']

COLORS = {'bp': 'tab:blue', 'nebp': 'tab:red'}
PAPER_SERIES = {'bp': 'BP', 'nebp': 'NEBP'}


def _figure(figsize):
    # a bare Figure, not pyplot: leaves a notebook's backend untouched
    from matplotlib.figure import Figure
    fig = Figure(figsize=figsize)
    return fig, fig.subplots()


def _save(fig, path):
    atomic_write(path, lambda tmp: fig.savefig(tmp, format='png', dpi=130,
                                               bbox_inches='tight'))


def plot_tracks(states: torch.Tensor, means: Dict[str, torch.Tensor],
                anchor: torch.Tensor, path: Union[str, Path]):
    r"""True (black) and estimated agent tracks :math:`(N, T, \ge 2)` of one
    realization, dots at the final positions, anchors as triangles; 3-D
    tracks (states of 6 entries) projected on the horizontal plane (the
    title says so)."""
    fig, ax = _figure((6, 6))
    if states.size(-1) == 6:
        ax.set_title('projected on the horizontal plane (x, y)', fontsize=9)
    agents = (~anchor).nonzero().view(-1).tolist()
    # one colour per method, its own where it has one
    colors = {name: COLORS.get(name, f'C{k}') for k, name in enumerate(means)}
    for i in agents:
        ax.plot(states[i, :, 0], states[i, :, 1], color='black', lw=1)
        ax.plot(*states[i, -1, :2], 'o', color='black', ms=3)
        for name, mean in means.items():
            ax.plot(mean[i, :, 0], mean[i, :, 1], color=colors[name],
                    lw=0.8, ls='--')
            ax.plot(*mean[i, -1, :2], 'o', color=colors[name], ms=2)
    anchors = states[anchor, 0, :2]
    ax.plot(anchors[:, 0], anchors[:, 1], '^', color='tab:green', ms=8,
            label='anchors')
    ax.plot([], [], color='black', label='truth')
    for name in means:
        ax.plot([], [], color=colors[name], ls='--', label=name.upper())
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal')
    ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1), fontsize=8)
    _save(fig, path)


def _plot_with_paper(ax, figure, curves):
    # this run's curve of every method (x, y), then the paper's curves of
    # the methods it has ('bp', 'nebp'), dashed in the same colour
    reference = paper_curves()
    colors = {}
    for name, (x, y) in curves.items():
        line, = ax.plot(x, y, color=COLORS.get(name),
                        label=f'{name.upper()} (this run)')
        colors[name] = line.get_color()
    for name in PAPER_SERIES:
        if name in curves:
            ax.plot(*reference[(figure, PAPER_SERIES[name])],
                    color=colors[name], ls='--',
                    label=f'{name.upper()} (paper)')


def plot_outage(errors: Dict[str, torch.Tensor], path: Union[str, Path],
                max_threshold: float = 3.0):
    r"""Outage probability versus error threshold per method, with the
    paper's curves of BP and NEBP (methods :obj:`"bp"`, :obj:`"nebp"`)
    dashed."""
    thresholds = torch.linspace(0, max_threshold, 121)
    fig, ax = _figure((5, 4))
    _plot_with_paper(ax, 'outage', {
        name: (thresholds, metrics.outage_from_errors(err, thresholds))
        for name, err in errors.items()})
    ax.set_xlabel('error threshold $e_{th}$ [m]')
    ax.set_ylabel('outage probability')
    ax.set_xlim(0, max_threshold)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, path)


def plot_consistency(nees: Dict[str, torch.Tensor], path: Union[str, Path],
                     dof: int = 2):
    r"""P(accept H0) of the two-sided chi-square NEES test (:obj:`dof`
    degrees of freedom: the position dimension) versus confidence level
    per method, the ideal diagonal, and the paper's curves of BP and NEBP
    dashed."""
    levels = torch.linspace(0.01, 0.99, 99)
    fig, ax = _figure((5, 4))
    ax.plot([0, 1], [0, 1], color='black', lw=0.8, ls=':', label='ideal')
    _plot_with_paper(ax, 'consistency', {
        name: (levels, metrics.consistency_curve(values, levels, dof=dof))
        for name, values in nees.items()})
    ax.axvline(0.95, color='gray', ls=':', lw=0.8)
    ax.set_xlabel('confidence level $1 - \\alpha$')
    ax.set_ylabel('P(accept $H_0$)')
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, path)


def plot_frontier(frontier: dict, path: Union[str, Path]):
    r"""The accuracy-cost frontier of :obj:`frontier.json`
    (:func:`~tg_nebp.experiments.frontier.run_frontier`):
    :math:`P_\mathrm{out}` (1 m) and P(accept :math:`H_0`) at the 0.95
    level against seconds per realization (log scale), one colour per
    number of sender samples :math:`M`, one marker per resampling option,
    :math:`K` written at each point, the Pareto-optimal points joined, and
    the paper's BP and NEBP rows as horizontal lines."""
    from matplotlib.figure import Figure
    from tg_nebp.evaluation import CONFIDENCE_KEY, OUTAGE_KEY
    from tg_nebp.reference import PAPER_TABLE

    entries = list(frontier['points'].values())
    fig = Figure(figsize=(11, 4.5))
    panels = fig.subplots(1, 2)
    samples = sorted({str(e['samples']) for e in entries},
                     key=lambda m: (m == 'all', int(m) if m != 'all' else 0))
    colors = {m: f'C{i % 10}' for i, m in enumerate(samples)}
    options = sorted({_resampling_label(e) for e in entries})
    markers = {o: 'osD^v<>px*'[i % 10] for i, o in enumerate(options)}
    for ax, (panel, field, key) in zip(panels, (
            ('outage', 'outage', OUTAGE_KEY),
            ('accept', 'accept', CONFIDENCE_KEY))):
        for e in entries:
            x, y = e['seconds_per_realization'], e[field][key]
            ax.plot(x, y, markers[_resampling_label(e)],
                    color=colors[str(e['samples'])], ms=6,
                    mfc='none' if not e['pareto'][panel] else None)
            ax.annotate(str(e['particles']), (x, y), fontsize=6,
                        xytext=(3, 3), textcoords='offset points')
        front = sorted((e['seconds_per_realization'], e[field][key])
                       for e in entries if e['pareto'][panel])
        if front:
            ax.plot(*zip(*front), color='black', lw=0.8, zorder=0,
                    label='Pareto front')
        for method, style in (('bp', ':'), ('nebp', '--')):
            ax.axhline(PAPER_TABLE[method][field][key], color='gray',
                       ls=style, lw=1, label=f'paper {method.upper()}')
        ax.set_xscale('log')
        ax.set_xlabel('seconds per realization')
        ax.grid(alpha=0.3)
    panels[0].set_ylabel('$P_{out}$ (1 m)')
    panels[1].set_ylabel('P(accept $H_0$) at 0.95')
    panels[1].axhline(float(CONFIDENCE_KEY), color='black', ls=':', lw=0.6,
                      label='ideal')
    for m in samples:
        panels[1].plot([], [], 's', color=colors[m], label=f'M = {m}')
    for o in options:
        panels[1].plot([], [], markers[o], color='black', mfc='none',
                       label=o)
    panels[1].legend(loc='upper left', bbox_to_anchor=(1.01, 1), fontsize=7)
    fig.suptitle('filled: Pareto-optimal; numbers: K', fontsize=8)
    _save(fig, path)


def _resampling_label(entry: dict) -> str:
    parts = [entry['resampler']]
    if entry['regularize'] is not None:
        parts.append(f"regularized ({entry['regularize']})")
    if entry['ess_threshold'] is not None:
        parts.append(f"ESS < {entry['ess_threshold']} K")
    return ', '.join(parts)


def plot_outage_against_particles(entries: Dict[str, Dict[int, dict]],
                                  path: Union[str, Path],
                                  paper: Dict[str, dict] = None):
    r"""P_out (1 m) and P(accept :math:`H_0`) at the 0.95 level against the
    particle count :math:`K` (log scale), one line per method from
    :obj:`{method: {K: metrics.json entry}}`, and the :obj:`paper`'s rows
    (:obj:`{label: entry}`, at their :obj:`"particles"`) as stars."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(10, 4))
    axes = fig.subplots(1, 2)
    for ax, (key, level, label) in zip(axes, (
            ('outage', '1.0', '$P_\\mathrm{out}$ (1 m)'),
            ('accept', '0.95', 'P(accept $H_0$) at 0.95'))):
        for name, by_k in entries.items():
            ks = sorted(by_k)
            ax.plot(ks, [by_k[k][key][level] for k in ks], 'o-',
                    label=name)
        for name, entry in (paper or {}).items():
            ax.plot(entry['particles'], entry[key][level], '*', ms=12,
                    label=name)
        ax.set_xscale('log')
        ax.set_xlabel('particles $K$ per agent')
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7, loc='lower right')
    _save(fig, path)


def plot_training_history(log: Dict[str, list], steps_per_epoch: int,
                          path: Union[str, Path]):
    r"""The training loss of every optimizer step (thin) and of every epoch,
    and the validation loss of every epoch, against the epoch, from
    :func:`~tg_nebp.training_log.read_training_log`'s
    :obj:`{"steps": [...], "epochs": [...]}` (either may be empty: a run
    resumed from a checkpoint without a log has only its epochs)."""
    fig, ax = _figure((6, 4))
    steps, epochs = log['steps'], log['epochs']
    if steps:
        ax.plot([s['epoch'] + s['step'] / steps_per_epoch for s in steps],
                [s['loss'] for s in steps], color='tab:blue', lw=0.5,
                alpha=0.4, label='training, per step')
    done = [e['epoch'] + 1 for e in epochs]
    ax.plot(done, [e['train_loss'] for e in epochs], 'o-', color='tab:blue',
            label='training, per epoch')
    ax.plot(done, [e['val_loss'] for e in epochs], 's-', color='tab:red',
            label='validation')
    losses = [v for v in [s['loss'] for s in steps] + [
        v for e in epochs for v in (e['train_loss'], e['val_loss'])]
        if not math.isnan(v)]  # no validation set: NaN
    if losses and min(losses) > 0:
        from matplotlib.ticker import StrMethodFormatter
        ax.set_yscale('log')
        for axis in (ax.yaxis.set_major_formatter,
                     ax.yaxis.set_minor_formatter):
            axis(StrMethodFormatter('{x:g}'))
    ax.set_xlabel('epoch')
    ax.set_ylabel('loss per agent and step [m$^2$]')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, path)


# the families of the compare table's rows: colour and marker
_COMPARE_STYLES = (('iekf-marginal', 'tab:orange', 's'),
                   ('iekf', 'tab:green', 'D'), ('bp', 'tab:blue', 'o'),
                   ('nebp', 'tab:red', '^'), ('', 'tab:gray', 'v'))


def plot_compare(points: Dict[str, list], path: Union[str, Path],
                 bound: str = 'pcrb'):
    r"""The compare table as a figure
    (:func:`~tg_nebp.experiments.compare.compare_points`): one row of
    panels per scenario, :math:`P_\mathrm{out}` (1 m), P(accept
    :math:`H_0`) at 0.95 and RMSE as a multiple of the bound's floor
    against seconds per realization (log scale), every method a point with
    its spread over the realizations (one standard deviation), the bound's
    row (:obj:`bound`) a horizontal line: its efficient outage, the ideal
    0.95 and the floor itself."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter
    fig = Figure(figsize=(14, 4.2 * len(points)), layout='constrained')
    panels = fig.subplots(len(points), 3, squeeze=False)
    plain = FuncFormatter(lambda value, _: f'{value:g}')
    for row, (scenario, entries) in zip(panels, points.items()):
        limit = {e['key']: e for e in entries}.get(bound)
        for ax, (field, label) in zip(row, (
                ('outage', '$P_{out}$ (1 m)'),
                ('accept', 'P(accept $H_0$) at 0.95'),
                ('floor_ratio', 'RMSE / floor'))):
            for e in entries:
                if e['key'] == bound or e[field] is None:
                    continue
                color, marker = next((c, m) for prefix, c, m in
                                     _COMPARE_STYLES
                                     if e['key'].startswith(prefix))
                (y, err), x = e[field], e['seconds']
                ax.errorbar(x, y, yerr=err, fmt=marker, color=color, ms=5,
                            capsize=2, lw=0.8)
                ax.annotate(e['key'], (x, y), fontsize=6, xytext=(4, 2),
                            textcoords='offset points')
            level = {'outage': limit['outage'][0] if limit else None,
                     'accept': 0.95, 'floor_ratio': 1.0}[field]
            if level is not None:
                ax.axhline(level, color='black', ls='--', lw=0.8,
                           label='bound' if field != 'accept' else 'ideal')
                ax.legend(fontsize=7, loc='best')
            if field == 'outage':
                ax.set_yscale('log')
            ax.set_xscale('log')
            # plain numbers on the log axes, seconds' minor ticks too
            ax.xaxis.set_major_formatter(plain)
            ax.xaxis.set_minor_formatter(plain)
            ax.yaxis.set_major_formatter(plain)
            ax.tick_params(which='minor', labelsize=6)
            ax.set_xlabel('seconds per realization')
            ax.set_ylabel(label)
            ax.set_title(scenario, fontsize=9)
            ax.grid(alpha=0.3)
    _save(fig, path)
