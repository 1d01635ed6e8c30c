"""Every PNG the offline commands write is readable, measured on the figure as matplotlib
lays it out (its renderer's text extents, not the code's intent): no text (title, labels,
tick labels, legend) runs off the canvas, no two tick labels of an axis overlap, and a
figure with several labelled series in one axes has a legend. The commands run on the
shipped sample bags; the checks are shown to fail on figures built to break them."""
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.text import Text

from tetra_gradiometer.__main__ import main

REPO = Path(__file__).resolve().parents[2]
PARAMS = str(REPO / 'config' / 'tetra_gradiometer.yaml')


def _tick_labels(axis):
    """The tick labels an axis draws: those of its ticks inside the view, with text."""
    low, high = sorted(axis.get_view_interval())
    ticks = axis.get_major_ticks() + axis.get_minor_ticks()
    locations = list(axis.get_majorticklocs()) + list(axis.get_minorticklocs())
    return [tick.label1 for tick, at in zip(ticks, locations, strict=False)
            if low - 1e-9 * abs(high - low) <= at <= high + 1e-9 * abs(high - low)
            and tick.label1.get_visible() and tick.label1.get_text()]


def _off_canvas(fig, renderer):
    """Texts drawn beyond the figure's edges (tick labels of ticks outside the view are not
    drawn: left out)."""
    canvas = fig.bbox.padded(1.0)
    ticks = {id(t.label1) for ax in fig.axes for axis in (ax.xaxis, ax.yaxis)
             for t in axis.get_major_ticks() + axis.get_minor_ticks()}
    drawn = {id(label) for ax in fig.axes for axis in (ax.xaxis, ax.yaxis) for label in _tick_labels(axis)}
    texts = fig.findobj(lambda a: isinstance(a, Text) and a.get_visible() and a.get_text().strip())
    return [f'text off the canvas: {t.get_text()!r}' for t in texts
            if (id(t) not in ticks or id(t) in drawn) and not _inside(t.get_window_extent(renderer), canvas)]


def _inside(box, canvas):
    return box.x0 >= canvas.x0 and box.y0 >= canvas.y0 and box.x1 <= canvas.x1 and box.y1 <= canvas.y1


def _overlapping_ticks(fig, renderer):
    found = []
    for ax in fig.axes:
        for name, axis in (('x', ax.xaxis), ('y', ax.yaxis)):
            boxes = [(label.get_text(), label.get_window_extent(renderer)) for label in _tick_labels(axis)]
            found += [f'{name} tick labels overlap: {a!r} and {b!r}'
                      for i, (a, box_a) in enumerate(boxes) for b, box_b in boxes[i + 1:] if box_a.overlaps(box_b)]
    return found


def _legend_problems(fig, renderer):
    """A legend over a title, or several labelled series in an axes and no legend at all."""
    legends = fig.legends + [ax.get_legend() for ax in fig.axes if ax.get_legend()]
    titles = [t for t in (fig._suptitle, fig._supxlabel, fig._supylabel, *(ax.title for ax in fig.axes))
              if t is not None and t.get_visible() and t.get_text()]
    found = [f'a legend over the title {title.get_text()!r}' for legend in legends for title in titles
             if legend.get_window_extent(renderer).overlaps(title.get_window_extent(renderer))]
    for ax in fig.axes:
        labelled = [h for h in ax.get_lines() + ax.collections + ax.patches
                    if not str(h.get_label()).startswith('_')]
        if len(labelled) >= 2 and not legends:
            found.append(f'{len(labelled)} labelled series and no legend')
    return found


def problems(fig: Figure) -> list[str]:
    """What makes ``fig`` hard to read, as it would be saved (empty: nothing)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig).draw()
    renderer = fig.canvas.get_renderer()
    return _off_canvas(fig, renderer) + _overlapping_ticks(fig, renderer) + _legend_problems(fig, renderer)


def test_the_checks_find_a_clipped_title_overlapping_ticks_a_legend_over_a_title_and_none():
    fig = Figure(figsize=(2.5, 2))
    ax = fig.subplots()
    ax.set_title('a title far wider than a figure of two and a half inches')
    ax.plot([0, 1], [0, 1], label='one')
    ax.plot([0, 1], [1, 0], label='two')
    ax.set_xticks(np.linspace(0, 1, 12), [f'{v:,.0f}' for v in np.linspace(4_785_500, 4_786_600, 12)])
    fig.suptitle('the figure')
    fig.legend(loc='upper center')
    found = problems(fig)
    assert any('off the canvas' in p for p in found), found
    assert any('x tick labels overlap' in p for p in found), found
    assert any('a legend over the title' in p for p in found), found
    fig.legends.clear()
    assert any('no legend' in p for p in problems(fig))
    good = Figure(figsize=(5, 3), layout='constrained')
    ax = good.subplots()
    ax.set_title('a short title')
    ax.plot([0, 1], [0, 1], label='one')
    ax.plot([0, 1], [1, 0], label='two')
    ax.legend()
    assert problems(good) == []


@pytest.fixture
def checked_figures(monkeypatch):
    """Figure.savefig checks each figure it saves: file name -> its problems."""
    found: dict[str, list[str]] = {}
    save = Figure.savefig

    def checked(fig, target, *args, **kwargs):
        save(fig, target, *args, **kwargs)
        name = Path(target).name if isinstance(target, (str, Path)) else f'in-memory {len(found)}'
        found[name] = problems(fig)

    monkeypatch.setattr(Figure, 'savefig', checked)
    return found


#: Rounds of a search: the base model alone, and one that added, revised and removed units
#: on every sensor (tick labels of several lines, the longest the report makes).
SEARCHES = {
    'base only': [[]],
    'long': [[], *[[f'{family}@sensor_{s}' for family in ('eddy_current', 'time_skew', 'vehicle_current')
                    for s in range(2, 2 + n)] for n in (1, 2, 3)], ['time_skew@sensor_2']],
}


@pytest.mark.parametrize('search', sorted(SEARCHES))
def test_the_discrepancy_figures_are_readable_for_one_round_and_for_many(search, checked_figures, tmp_path):
    from test_discrepancy_report_robust import _report

    from tetra_gradiometer.reports.discrepancy import write_report

    write_report(_report(SEARCHES[search], []), tmp_path / 'out')
    assert {'gap.png', 'diagnostics.png'} <= set(checked_figures)
    unreadable = {name: found for name, found in checked_figures.items() if found}
    assert not unreadable, unreadable


@pytest.mark.slow
def test_every_figure_of_the_commands_is_readable(checked_figures, tmp_path):
    calibration = str(tmp_path / 'cal.yaml')
    survey = str(REPO / 'bags' / 'survey')
    commands = [
        ['calibrate', str(REPO / 'bags' / 'trim'), '--params', PARAMS, '--out', calibration,
         '--report', str(tmp_path / 'calibration')],
        ['compensate', survey, '--params', PARAMS, '--calibration', calibration, '--report', str(tmp_path / 'health')],
        ['discrepancy', str(REPO / 'bags' / 'trim'), '--params', PARAMS, '--out', str(tmp_path / 'discrepancy')],
        ['locate', survey, '--params', PARAMS, '--calibration', calibration, '--out', str(tmp_path / 'locate')],
        ['survey', survey, '--params', PARAMS, '--calibration', calibration, '--origin', '43.2,5.3',
         '--out', str(tmp_path / 'survey')],
    ]
    for command in commands:
        assert main(command) == 0, command
    expected = {'residual.png', 'parameters.png', 'coverage.png', 'survey.png', 'health.png', 'gap.png',
                'diagnostics.png', 'map.png'}
    assert expected <= set(checked_figures), sorted(checked_figures)
    assert sum(name.startswith('in-memory') for name in checked_figures) == 2  # the survey report's maps
    unreadable = {name: sorted(set(found)) for name, found in checked_figures.items() if found}
    assert not unreadable, unreadable
