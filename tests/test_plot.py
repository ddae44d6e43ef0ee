r"""The figures of :mod:`tg_nebp.plot` that carry more than pixels: the
tracks figure keeps one colour per method."""
import torch

from tg_nebp import plot


def test_every_track_of_a_method_has_its_colour(tmp_path, monkeypatch):
    # a method without a colour of its own (a smoother's two rows) got the
    # next colour of matplotlib's cycle for each agent's line, so the
    # legend named colours that no track had
    drawn = {}
    monkeypatch.setattr(plot, '_save', lambda fig, path: drawn.update(
        fig=fig))
    states = torch.rand(4, 5, 4)
    anchor = torch.tensor([False, False, False, True])
    means = {'gbp-lag5': states + 0.1, 'gbp-lag5-smoothed': states - 0.1,
             'bp': states}
    plot.plot_tracks(states, means, anchor, tmp_path / 'tracks.png')
    ax, = drawn['fig'].axes
    # three agents, each with the three methods' lines in the same order
    lines = [line for line in ax.get_lines()
             if line.get_linestyle() == '--' and len(line.get_xdata())]
    colours = [line.get_color() for line in lines]
    assert colours == colours[:3] * 3
    assert len(set(colours)) == 3 and colours[2] == plot.COLORS['bp']
    legend = {text.get_text(): handle.get_color() for text, handle in zip(
        ax.get_legend().get_texts(), ax.get_legend().legend_handles)
        if text.get_text() in ('GBP-LAG5', 'GBP-LAG5-SMOOTHED')}
    assert legend == {'GBP-LAG5': colours[0], 'GBP-LAG5-SMOOTHED': colours[1]}
