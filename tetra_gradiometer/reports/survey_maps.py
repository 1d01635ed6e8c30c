"""The survey report's maps as PNG bytes (matplotlib's object API, imported inside).

Both maps are drawn in the grids' projected CRS at true scale (equal axes), the axes in
metres of that CRS with every digit (``686,850``), targets as magenta discs with their
3-sigma ellipses and their ``targets.csv`` id:

- :func:`overview_png`: the whole track (the straight legs black, the rest grey, lost and
  refused spans coloured, health alarms as crosses), the gridded area outlined;
- :func:`quantities_png`: one panel per gridded quantity (six components, the invariants
  I1, I2 and the normalized source strength) over the gridded area, the track and the
  targets on each, each with its colour bar in the report's units (nT/m, nT²/m², nT³/m³).
"""

from __future__ import annotations

import io
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from ..io import survey_files as files
from ..pipelines.survey import SurveyResult

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ['MAP_QUANTITIES', 'TARGET_COLOUR', 'overview_png', 'quantities_png']

#: The targets' colour (no colour map of the panels contains it).
TARGET_COLOUR = '#ff00ff'
SPAN_COLOURS = {'lost': '#ff8c00', 'refused': '#d62728'}
#: Panel title and colour-bar unit per quantity drawn, in the order drawn.
MAP_QUANTITIES = {
    'gxx': ('Gxx = dBE/dE', 'nT/m'),
    'gxy': ('Gxy = dBE/dN', 'nT/m'),
    'gxz': ('Gxz = dBE/dU', 'nT/m'),
    'gyy': ('Gyy = dBN/dN', 'nT/m'),
    'gyz': ('Gyz = dBN/dU', 'nT/m'),
    'gzz': ('Gzz = dBU/dU', 'nT/m'),
    'i1': ('invariant I1', 'nT²/m²'),
    'i2': ('invariant I2', 'nT³/m³'),
    'nss': ('normalized source strength', 'nT/m'),
}
#: A map's shorter side is at least this fraction of its longer one (a single line's
#: gridded strip is shown in a band around it, not as a hairline).
MIN_ASPECT = 1 / 8
#: The same for the overview (room for its legend).
OVERVIEW_MIN_ASPECT = 1 / 3
DPI = 130


def _figure(width_in: float, height_in: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), layout='constrained')


def _png(fig: Figure) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format='png', dpi=DPI)
    return buffer.getvalue()


def _gridded_box(result: SurveyResult) -> tuple[slice, slice]:
    """Rows and columns of the grid that hold gridded cells."""
    rows = np.flatnonzero(result.grids.mask.any(axis=1))
    columns = np.flatnonzero(result.grids.mask.any(axis=0))
    if not len(rows):
        return slice(None), slice(None)
    return slice(rows[0], rows[-1] + 1), slice(columns[0], columns[-1] + 1)


def _limits(
    x: np.ndarray, y: np.ndarray, margin_m: float, min_aspect: float = MIN_ASPECT
) -> tuple[list[float], list[float]]:
    """x and y limits (m) around the points, padded by ``margin_m`` and widened so that
    neither side is shorter than ``min_aspect`` of the other."""
    xs = [float(np.nanmin(x)) - margin_m, float(np.nanmax(x)) + margin_m]
    ys = [float(np.nanmin(y)) - margin_m, float(np.nanmax(y)) + margin_m]
    width, height = xs[1] - xs[0], ys[1] - ys[0]
    if height < min_aspect * width:
        grow = (min_aspect * width - height) / 2
        ys = [ys[0] - grow, ys[1] + grow]
    elif width < min_aspect * height:
        grow = (min_aspect * height - width) / 2
        xs = [xs[0] - grow, xs[1] + grow]
    return xs, ys


def _style_axes(ax: Axes, limits: tuple[list[float], list[float]], nbins: tuple[int, int]) -> None:
    """True scale, the limits, at most ``nbins`` (x, y) ticks with every digit of the CRS's
    metres."""
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    ax.set_aspect('equal', adjustable='box')
    for axis, n in zip((ax.xaxis, ax.yaxis), nbins, strict=True):
        axis.set_major_locator(MaxNLocator(nbins=n, steps=[1, 2, 2.5, 5, 10]))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f'{v:,.0f}'))
    ax.tick_params(labelsize=7)


def _targets_xy(result: SurveyResult, records: list[dict[str, Any]]) -> np.ndarray:
    """The targets (T, 2) in the CRS, m."""
    if not records:
        return np.zeros((0, 2))
    positions = np.array([r['position_m'] for r in records])
    return result.georeference.to_crs(positions, result.crs)


def _draw_targets(ax: Axes, result: SurveyResult, xy: np.ndarray, labels: bool) -> None:
    """The targets' discs, 3-sigma ellipses and (``labels``) ids."""
    angles = np.linspace(0, 2 * np.pi, 49)
    circle = np.column_stack([np.cos(angles), np.sin(angles)])
    for i, target in enumerate(result.targets):
        values, vectors = np.linalg.eigh(target.fit.covariance[:2, :2])
        ring = files.ELLIPSE_SIGMAS * (circle * np.sqrt(np.maximum(values, 0))) @ vectors.T
        points = np.column_stack([target.fit.position[:2] + ring, np.zeros(len(ring))])
        outline = result.georeference.to_crs(points, result.crs)
        ax.plot(outline[:, 0], outline[:, 1], color=TARGET_COLOUR, lw=1)
        if labels:
            ax.annotate(
                str(i),
                xy[i],
                xytext=(6, 6),
                textcoords='offset points',
                fontsize=9,
                color='black',
                fontweight='bold',
            )
    ax.plot(
        xy[:, 0],
        xy[:, 1],
        'o',
        color=TARGET_COLOUR,
        ms=7,
        mec='black',
        mew=0.8,
        label='target (3σ ellipse)',
        zorder=5,
    )


def _draw_track(ax: Axes, result: SurveyResult, width: float) -> None:
    """The track: the straight legs (gridded) black, the rest (turns, transits) grey."""
    x, y = result.track.xy_m[:, 0], result.track.xy_m[:, 1]
    ax.plot(x, y, color='0.6', lw=width, ls='--', label='track between legs')
    for n, (a, b) in enumerate(result.track.legs):
        ax.plot(x[a:b], y[a:b], color='black', lw=width, label='straight leg' if n == 0 else None)


def _draw_events(ax: Axes, result: SurveyResult) -> None:
    """Lost and refused spans along the track, and the health alarms."""
    track = result.track
    x, y = track.xy_m[:, 0], track.xy_m[:, 1]
    shown: set[str] = set()
    for span in result.spans:
        inside = (track.t_s >= span.start_s) & (track.t_s <= span.stop_s)
        xs = np.interp([span.start_s, span.stop_s], track.t_s, x)
        ys = np.interp([span.start_s, span.stop_s], track.t_s, y)
        if inside.sum() > 2:
            xs, ys = x[inside], y[inside]
        label = None if span.kind in shown else f'{span.kind} span'
        shown.add(span.kind)
        ax.plot(xs, ys, color=SPAN_COLOURS[span.kind], lw=4, alpha=0.8, label=label)
    times = [a['t_s'] for a in result.health['alarms']]
    if times:
        ax.plot(
            np.interp(times, track.t_s, x),
            np.interp(times, track.t_s, y),
            'x',
            color='#d62728',
            ms=10,
            mew=2,
            label='health alarm',
        )


def overview_png(result: SurveyResult, records: list[dict[str, Any]]) -> bytes:
    """The whole track with the gridded area outlined (module docstring)."""
    from matplotlib.patches import Rectangle

    grids, xy = result.grids, _targets_xy(result, records)
    rows, columns = _gridded_box(result)
    half = grids.cell_m / 2
    x0, x1 = grids.x[columns][0] - half, grids.x[columns][-1] + half
    y0, y1 = grids.y[rows][0] - half, grids.y[rows][-1] + half
    track = result.track.xy_m
    every_x = np.concatenate([track[:, 0], [x0, x1], xy[:, 0]])
    every_y = np.concatenate([track[:, 1], [y0, y1], xy[:, 1]])
    span = max(np.ptp(every_x), np.ptp(every_y), 1.0)
    limits = _limits(every_x, every_y, 0.05 * span, min_aspect=OVERVIEW_MIN_ASPECT)
    aspect = (limits[1][1] - limits[1][0]) / (limits[0][1] - limits[0][0])
    fig = _figure(8.0, min(6.0 * aspect, 9.0) + 0.7)
    ax = fig.subplots()
    ax.add_patch(
        Rectangle(
            (min(x0, x1), min(y0, y1)),
            abs(x1 - x0),
            abs(y1 - y0),
            fill=True,
            fc='#e8f0ff',
            ec='#1f77b4',
            lw=1.2,
            label='gridded area',
        )
    )
    _draw_track(ax, result, 1.0)
    _draw_events(ax, result)
    start = track[0]
    ax.plot(*start, '^', color='#2ca02c', ms=8, mec='black', mew=0.6, label='start')
    _draw_targets(ax, result, xy, labels=True)
    _style_axes(ax, limits, nbins=(6, 6))
    ax.set_xlabel(f'easting, m ({result.crs})', fontsize=8)
    ax.set_ylabel(f'northing, m ({result.crs})', fontsize=8)
    ax.grid(color='0.9', lw=0.5)
    fig.legend(*ax.get_legend_handles_labels(), loc='outside right upper', fontsize=7)
    return _png(fig)


def _columns(aspect: float) -> int:
    """Panels per row for maps of ``aspect`` (width / height): the figure closest to square."""
    n = len(MAP_QUANTITIES)
    return min((1, 2, 3), key=lambda c: abs(math.log(c * aspect / math.ceil(n / c))))


def _colour(values: np.ndarray, name: str) -> dict[str, Any]:
    """Colour map and limits: diverging about 0 for a signed quantity, else sequential with
    the largest magnitude brightest (I1 is never positive for a field in free space)."""
    finite = values[np.isfinite(values)]
    if not len(finite) or finite.min() >= 0 or name == 'nss':
        return {'cmap': 'viridis'}
    if finite.max() <= 0:
        return {'cmap': 'viridis_r'}
    limit = float(np.abs(finite).max())
    return {'cmap': 'RdBu_r', 'vmin': -limit, 'vmax': limit}


def quantities_png(result: SurveyResult, records: list[dict[str, Any]]) -> bytes:
    """One panel per quantity of :data:`MAP_QUANTITIES` (module docstring)."""
    grids, xy = result.grids, _targets_xy(result, records)
    rows, columns = _gridded_box(result)
    x, y = grids.x[columns], grids.y[rows]
    limits = _limits(x, y, grids.cell_m)
    aspect = (limits[0][1] - limits[0][0]) / (limits[1][1] - limits[1][0])
    ncols = _columns(aspect)
    nrows = math.ceil(len(MAP_QUANTITIES) / ncols)
    width = 10.0
    panel_height = (width / ncols - 0.9) / aspect + 0.45
    fig = _figure(width, nrows * panel_height + 0.6)
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=True, sharey=True)
    for ax, (name, (title, unit)) in zip(axes.flat, MAP_QUANTITIES.items(), strict=False):
        _, factor = files.UNITS[name]
        values = grids.values[name][rows, columns] * factor
        mesh = ax.pcolormesh(x, y, values, shading='nearest', **_colour(values, name))
        bar = fig.colorbar(mesh, ax=ax, pad=0.01, fraction=0.05)
        bar.set_label(unit, fontsize=7)
        bar.ax.tick_params(labelsize=6)
        bar.ax.ticklabel_format(axis='y', style='sci', scilimits=(-3, 4))
        bar.ax.yaxis.get_offset_text().set_fontsize(6)
        _draw_track(ax, result, 0.6)
        _draw_targets(ax, result, xy, labels=False)
        _style_axes(ax, limits, nbins=(4 if ncols > 1 else 8, 3))
        ax.set_title(title, fontsize=8)
    for ax in axes.flat[len(MAP_QUANTITIES) :]:
        ax.set_visible(False)
    for ax in axes.flat:
        ax.label_outer()
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc='outside upper center', ncols=len(labels), fontsize=7)
    fig.supxlabel(f'easting, m ({result.crs})', fontsize=8)
    fig.supylabel(f'northing, m ({result.crs})', fontsize=8)
    return _png(fig)
