"""Figures for reports: every number the toolkit computes, also as a picture.

Each function returns a `matplotlib.figure.Figure` (built without pyplot, so importing this
module leaves the caller's backend alone, e.g. a notebook's inline one), so tests can count its
lines and bars and the report can save it. Conventions:

- Euler angles appear only here, as intrinsic ZYX (yaw about z, then pitch about the new y,
  then roll about the newest x) of `R_world_body`; the sequence is in the axis labels. A
  jump of more than 180 deg between neighbouring samples (a wrap at +-180) breaks the line
  instead of drawing a vertical stroke across the plot.
- Time axes are seconds since the recording's first IMU sample, shared by every panel.
- Shaded: spans without the truth (tracking gaps, before and after its span) in grey, and spans
  where `imu.gyr_valid` is False in red.
- An estimator keeps one colour in every figure of a report (its position in the run).
- The filter-consistency figures draw long recordings from per-bin statistics (about one bin
  per pixel: `decimate_minmax`, `decimate_max`): a BROAD trial has 50,000 samples.
"""
from __future__ import annotations

import math
import re

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from scipy.spatial.transform import Rotation

from fusion.checks import runs
from fusion.estimators.params import parse_specs

from ..run.series import RecordingSeries
from ..scoring.metrics import KINDS, MIN_COVERAGE

EULER_SEQ = "ZYX"
EULER_NAMES = ("roll", "pitch", "yaw")
TRUTH_COLOR = "black"
GAP_COLOR, GAP_ALPHA = "0.6", 0.3
BAD_GYRO_COLOR, BAD_GYRO_ALPHA = "tab:red", 0.2
DPI = 100


TRUTH = "truth"  # a recording's truth system, when the caller does not name it (VICON, BROAD's ...)


def color(index: int):
    """The colour of the estimator at `index` in the run's estimator list: tab10 for the
    first ten, then Dark2 (drawn dashed, see `linestyle`), so thirteen estimators stay apart."""
    if index < 10:
        return f"C{index}"
    return matplotlib.colormaps["Dark2"].colors[(index - 10) % 8]


def linestyle(index: int) -> str:
    return "-" if index < 10 else "--"


def euler_deg(quat_wxyz: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw in deg (intrinsic ZYX) of (N, 4) quat_wxyz; NaN rows stay NaN."""
    quat = np.asarray(quat_wxyz, dtype=float)
    out = np.full((len(quat), 3), np.nan)
    good = np.all(np.isfinite(quat), axis=1)
    if good.any():
        ypr = Rotation.from_quat(quat[good], scalar_first=True).as_euler(EULER_SEQ, degrees=True)
        out[good] = ypr[:, ::-1]
    return out


def break_wraps(x: np.ndarray, y: np.ndarray, jump_deg: float = 180.0) -> tuple[np.ndarray, np.ndarray]:
    """Insert a NaN point between neighbours whose angle differs by more than `jump_deg`,
    so that a wrap from +180 to -180 leaves a break instead of a vertical line."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    cut = np.flatnonzero(np.abs(np.diff(y)) > jump_deg) + 1
    if len(cut) == 0:
        return x, y
    return np.insert(x, cut, np.nan), np.insert(y, cut, np.nan)


def _time_spans(t: np.ndarray, mask: np.ndarray) -> list[tuple[float, float]]:
    """Time spans of the runs of True in `mask` over samples `t`, each widened to the
    neighbouring samples (a single bad sample still gets a visible span)."""
    out = []
    for a, stop in runs(mask):
        out.append((float(t[max(a - 1, 0)]), float(t[min(stop, len(t) - 1)])))
    return out


def truth_gaps(s: RecordingSeries) -> list[tuple[float, float]]:
    """Spans (s, absolute) inside the IMU's time span with no usable truth orientation:
    before its first and after its last valid sample, NaN rows, and time-stamp gaps longer
    than five median steps."""
    t0, t1 = float(s.imu_t[0]), float(s.imu_t[-1])
    if not s.has_truth:
        return [(t0, t1)]
    valid = np.all(np.isfinite(s.truth_quat), axis=1)
    if not valid.any():
        return [(t0, t1)]
    tv = s.truth_t[valid]
    spans = []
    if tv[0] > t0:
        spans.append((t0, float(tv[0])))
    if tv[-1] < t1:
        spans.append((float(tv[-1]), t1))
    spans += _time_spans(s.truth_t, ~valid)
    if len(tv) > 2:
        step = np.diff(tv)
        for k in np.flatnonzero(step > 5 * np.median(step)):
            spans.append((float(tv[k]), float(tv[k + 1])))
    return merge_spans(spans)


def merge_spans(spans: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Sorted spans with overlapping or touching ones merged (each gap shaded once)."""
    out: list[tuple[float, float]] = []
    for a, b in sorted(x for x in spans if x[1] > x[0]):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def bad_gyro_spans(s: RecordingSeries) -> list[tuple[float, float]]:
    """Spans (s, absolute) where `gyr_valid` is False."""
    return _time_spans(s.imu_t, ~s.gyr_valid)


def _shade(ax, s: RecordingSeries, t0: float) -> None:
    for a, b in truth_gaps(s):
        ax.axvspan(a - t0, b - t0, color=GAP_COLOR, alpha=GAP_ALPHA, lw=0, zorder=0)
    for a, b in bad_gyro_spans(s):
        ax.axvspan(a - t0, b - t0, color=BAD_GYRO_COLOR, alpha=BAD_GYRO_ALPHA, lw=0, zorder=0)


def _shade_handles(s: RecordingSeries, truth: str = TRUTH) -> list:
    handles = []
    if truth_gaps(s):
        handles.append(Patch(color=GAP_COLOR, alpha=GAP_ALPHA + 0.2, label=f"no {truth}"))
    if bad_gyro_spans(s):
        handles.append(Patch(color=BAD_GYRO_COLOR, alpha=BAD_GYRO_ALPHA + 0.2, label="gyro invalid"))
    return handles


def _display_label(label: str, causal: bool) -> str:
    return label if causal else f"{label} (smoother)"


def _new_figure(width: float, height: float) -> Figure:
    return Figure(figsize=(width, height), dpi=DPI, layout="constrained")


def euler_figure(s: RecordingSeries, truth: str = TRUTH) -> Figure:
    """Roll, pitch and yaw of the truth (named `truth`: VICON, BROAD's optical motion capture, ...)
    and of every estimator, on one shared time axis."""
    fig = _new_figure(11, 7.5)
    axes = fig.subplots(3, 1, sharex=True)
    t0 = float(s.imu_t[0])
    curves = []
    if s.has_truth:
        curves.append((truth, s.truth_t - t0, euler_deg(s.truth_quat), None, 2.2))
    for e, label in enumerate(s.labels):
        curves.append((_display_label(label, s.causal[e]), s.imu_t - t0, euler_deg(s.quat[e]), e, 1.0))
    limits = {"roll": 180, "pitch": 90, "yaw": 180}
    for k, (ax, name) in enumerate(zip(axes, EULER_NAMES)):
        _shade(ax, s, t0)
        for label, x, angles, e, width in curves:
            style = dict(color=TRUTH_COLOR, ls="-") if e is None else dict(color=color(e), ls=linestyle(e))
            ax.plot(*break_wraps(x, angles[:, k]), lw=width, label=label, **style)
        lim = limits[name]
        ax.set_ylim(-lim * 1.05, lim * 1.05)
        ax.set_yticks(np.arange(-lim, lim + 1, 90 if lim == 180 else 45))
        ax.set_ylabel(f"{name} [deg]\n(Euler {EULER_SEQ} intrinsic)")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time since first IMU sample [s]")
    axes[-1].set_xlim(0, float(s.imu_t[-1] - t0))
    handles, labels = axes[0].get_legend_handles_labels()
    handles += _shade_handles(s, truth)
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 6), fontsize=9)
    fig.suptitle(f"{s.id}: orientation R_world_body as Euler angles (yaw-pitch-roll, {EULER_SEQ})", fontsize=11)
    return fig


def error_figure(s: RecordingSeries, truth: str = TRUTH) -> Figure | None:
    """Total, inclination and heading error of every estimator over time (None without truth)."""
    if not s.has_truth or not np.isfinite(s.err_deg).any():
        return None
    fig = _new_figure(11, 7.5)
    axes = fig.subplots(3, 1, sharex=True)
    t0 = float(s.imu_t[0])
    x = s.imu_t - t0
    for k, (ax, kind) in enumerate(zip(axes, KINDS)):
        _shade(ax, s, t0)
        for e, label in enumerate(s.labels):
            ax.plot(x, s.err_deg[e, k], color=color(e), ls=linestyle(e), lw=1.0,
                    label=_display_label(label, s.causal[e]))
        ax.set_ylabel(f"{kind} error [deg]")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time since first IMU sample [s]")
    axes[-1].set_xlim(0, float(x[-1]))
    handles, labels = axes[0].get_legend_handles_labels()
    handles += _shade_handles(s, truth)
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 6), fontsize=9)
    fig.suptitle(f"{s.id}: error against {truth} (total = geodesic angle, inclination = gravity direction, "
                 "heading = twist about world z)", fontsize=10)
    return fig


def loss_figure(s: RecordingSeries) -> Figure | None:
    """Cost per iteration of the estimators that report one (smoothers), one panel per
    estimator, each on its own y axis (settings of the cost, e.g. its weighting, change its
    scale by orders of magnitude); None if none reports a cost."""
    if not s.losses:
        return None
    items = sorted(s.losses.items())
    fig = _new_figure(8, 1.2 + 2.6 * len(items))
    axes = np.atleast_1d(fig.subplots(len(items), 1))
    for ax, (e, loss) in zip(axes, items):
        ax.plot(np.arange(len(loss)), loss, color=color(e), ls=linestyle(e), marker="." if len(loss) < 60 else None)
        finite = loss[np.isfinite(loss)]
        log = finite.size > 0 and np.all(finite > 0)
        if log:
            ax.set_yscale("log")
        ax.set_ylabel(f"cost J{' (log)' if log else ''}\n(own axis)")
        ax.grid(alpha=0.3, which="both")
        ax.set_title(_display_label(s.labels[e], s.causal[e]), fontsize=10, loc="left")
    axes[-1].set_xlabel("iteration")
    fig.suptitle(f"{s.id}: smoother cost per iteration (each estimator's own cost, own y axis)", fontsize=11)
    return fig


# --- summaries over a run (from the rows of results.json) ---

def rmse_matrix(rows: list[dict], kind: str) -> tuple[list[str], list[str], np.ndarray]:
    """(estimators, datasets, (E, D) RMSE in deg, NaN where missing) in the run's order."""
    labels = list(dict.fromkeys(r["estimator"] for r in rows))
    datasets = list(dict.fromkeys(r["dataset"] for r in rows))
    m = np.full((len(labels), len(datasets)), np.nan)
    for r in rows:
        if r["rmse_deg"]:
            m[labels.index(r["estimator"]), datasets.index(r["dataset"])] = r["rmse_deg"][kind]
    return labels, datasets, m


def _short(label: str, limit: int = 32) -> str:
    """A tick label that cannot squeeze the axes away: long ids (file paths) keep their end."""
    return label if len(label) <= limit else "..." + label[-(limit - 3):]


def _heatmap(ax, m: np.ndarray, rows: list[str], cols: list[str], title: str, cbar_label: str, fig: Figure) -> None:
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.85")
    finite = m[np.isfinite(m)]
    vmax = float(finite.max()) if finite.size else 1.0
    image = ax.imshow(np.ma.masked_invalid(m), cmap=cmap, vmin=0, vmax=vmax or 1.0, aspect="auto")
    ax.set_xticks(range(len(cols)), [_short(c) for c in cols],
                  rotation=45 if max(map(len, cols), default=0) > 4 else 0, ha="right", fontsize=8)
    ax.set_yticks(range(len(rows)), [_short(r) for r in rows], fontsize=8)
    if m.size <= 400:
        for (i, j), v in np.ndenumerate(m):
            text = "-" if not np.isfinite(v) else f"{v:.1f}"
            dark = np.isfinite(v) and v > 0.6 * vmax
            ax.text(j, i, text, ha="center", va="center", fontsize=7, color="black" if dark else "white"
                    if np.isfinite(v) else "black")
    ax.set_title(title, fontsize=10)
    fig.colorbar(image, ax=ax, label=cbar_label, shrink=0.9)


def summary_rmse_figure(rows: list[dict]) -> Figure:
    """Heat maps of the RMSE (total, inclination, heading) per estimator x recording."""
    labels, datasets, _ = rmse_matrix(rows, "total")
    width = min(6 + 0.55 * len(datasets), 14)
    height = 1.6 + 0.38 * len(labels)
    fig = _new_figure(width, 3 * height + 0.6)
    axes = fig.subplots(3, 1)
    for ax, kind in zip(axes, KINDS):
        _, _, m = rmse_matrix(rows, kind)
        _heatmap(ax, m, labels, datasets, f"{kind} RMSE [deg]", "deg", fig)
    fig.suptitle("RMSE per estimator and recording (grey: no ground truth)", fontsize=11)
    return fig


def speed_points(rows: list[dict]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(estimators, mean us/sample over the recordings it ran on, mean total RMSE deg over recordings
    with truth, across datasets as the table takes it: `mean_across_datasets`)."""
    labels = list(dict.fromkeys(r["estimator"] for r in rows))
    us, err = [], []
    for label in labels:
        mine = [r for r in rows if r["estimator"] == label]
        ran = [1e6 * r["seconds"] / r["samples"] for r in mine if r["samples"] and not r.get("error")]
        us.append(np.mean(ran) if ran else np.nan)
        err.append(_mean_rmse(rows, label, "total"))
    return labels, np.array(us), np.array(err)


def speed_figure(rows: list[dict], causal: dict[str, bool]) -> Figure:
    """Accuracy against speed: mean total RMSE against microseconds per sample."""
    labels, us, err = speed_points(rows)
    fig = _new_figure(7.5, 5)
    ax = fig.subplots()
    for e, label in enumerate(labels):
        smoother = not causal.get(label, True)
        ax.scatter([us[e]], [err[e]], s=60, color=color(e), marker="s" if smoother else "o", zorder=3,
                   label=_display_label(label, not smoother))
    positive = us[np.isfinite(us) & (us > 0)]
    if positive.size and positive.max() / positive.min() > 20:
        ax.set_xscale("log")
    else:
        ax.set_xlim(left=0, right=1.15 * float(np.nanmax(us)) if np.isfinite(us).any() else None)
    ax.set_xlabel("time per IMU sample [us] (mean over recordings; wall time, noisy)")
    ax.set_ylabel("total RMSE [deg] (mean over recordings with truth)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3, which="both")
    ax.set_title("accuracy vs speed (lower left is better; squares: smoothers)", fontsize=10)
    place_labels(ax, us, err, labels, fontsize=8)
    return fig


# Where a point's label may go, tried in this order: (dx, dy) in points from the point, and
# the text's horizontal and vertical alignment.
_LABEL_SLOTS = [(6, 4, "left", "bottom"), (6, -4, "left", "top"), (-6, 4, "right", "bottom"),
                (-6, -4, "right", "top"), (0, 8, "center", "bottom"), (0, -8, "center", "top"),
                (8, 0, "left", "center"), (-8, 0, "right", "center"), (10, 14, "left", "bottom"),
                (10, -14, "left", "top"), (-10, 14, "right", "bottom"), (-10, -14, "right", "top"),
                (0, 20, "center", "bottom"), (0, -20, "center", "top")]


def place_labels(ax, xs: np.ndarray, ys: np.ndarray, labels: list[str], fontsize: float = 8,
                 marker_radius_pt: float = 5.0) -> list:
    """Label each point (xs[i], ys[i]) with labels[i] next to it, avoiding the other labels,
    the markers and the axes' edges: each label takes the first of a few slots around its point
    (`_LABEL_SLOTS`) whose text box overlaps nothing placed so far, else the least overlapping
    one. Call after the axes' scales and limits are set (the layout is fixed here). Returns the
    annotations."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.transforms import Bbox

    fig = ax.figure
    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    fig.draw_without_rendering()  # runs the layout, so display coordinates are final
    fig.set_layout_engine("none")
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    r = marker_radius_pt * fig.dpi / 72
    points = [ax.transData.transform((x, y)) for x, y in zip(xs, ys)]
    taken = [Bbox.from_extents(px - r, py - r, px + r, py + r) for px, py in points if np.all(np.isfinite((px, py)))]

    def overlap(box: Bbox) -> float:
        area = sum(max(0.0, min(box.x1, b.x1) - max(box.x0, b.x0)) * max(0.0, min(box.y1, b.y1) - max(box.y0, b.y0))
                   for b in taken)
        outside = box.width * box.height - max(0.0, min(box.x1, frame.x1) - max(box.x0, frame.x0)) * \
            max(0.0, min(box.y1, frame.y1) - max(box.y0, frame.y0))
        return area + 10 * outside

    out = []
    for (x, y), label in zip(zip(xs, ys), labels):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        best = None
        for dx, dy, ha, va in _LABEL_SLOTS:
            text = ax.annotate(label, (x, y), textcoords="offset points", xytext=(dx, dy), ha=ha, va=va,
                               fontsize=fontsize, zorder=4)
            box = text.get_window_extent(renderer).expanded(1.05, 1.1)
            cost = overlap(box)
            if best is None or cost < best[0]:
                if best is not None:
                    best[1].remove()
                best = (cost, text, box)
            else:
                text.remove()
            if cost == 0:
                break
        taken.append(best[2])
        out.append(best[1])
    return out


# --- ablations (parameters read back from the estimator labels) ---

def label_params(labels: list[str]) -> tuple[str | None, dict[str, list[str]]]:
    """If every label names the same estimator: (name, {parameter: value per label}) for the
    parameters whose value differs between labels ("default" where a label omits it)."""
    specs = [parse_specs(label)[0] for label in labels]
    names = {s.name for s in specs}
    if len(names) != 1:
        return None, {}
    keys = list(dict.fromkeys(k for s in specs for k, _ in s.overrides))
    table = {k: [dict(s.overrides).get(k, "default") for s in specs] for k in keys}
    return names.pop(), {k: v for k, v in table.items() if len(set(v)) > 1}


def _as_numbers(values: list[str]) -> np.ndarray | None:
    try:
        return np.array([float(v) for v in values])
    except ValueError:
        return None


def _mean_rmse(rows: list[dict], label: str, kind: str) -> float:
    """An estimator's mean `kind` RMSE as the table takes it: over the recordings it was scored on
    (below `MIN_COVERAGE` left out), across datasets the mean of per-dataset means."""
    from ..scoring.stats import mean_across_datasets

    return mean_across_datasets({r["dataset"]: r["rmse_deg"][kind] for r in rows if r["estimator"] == label
                                 and r["rmse_deg"] and (r.get("coverage") is None or r["coverage"] >= MIN_COVERAGE)})


def param_figure(rows: list[dict], kind: str = "total") -> Figure | None:
    """Mean RMSE against each varied parameter: one panel per parameter, one line per
    combination of the other parameters. None when the labels vary no parameter."""
    labels = list(dict.fromkeys(r["estimator"] for r in rows))
    name, table = label_params(labels)
    if not table:
        return None
    keys = list(table)
    fig = _new_figure(max(6.5, 5.2 * len(keys)), 4.6)
    axes = np.atleast_1d(fig.subplots(1, len(keys)))
    means = np.array([_mean_rmse(rows, label, kind) for label in labels])
    for ax, key in zip(axes, keys):
        values = table[key]
        order = list(dict.fromkeys(values))
        numbers = _as_numbers(order)
        others = [tuple((k, table[k][i]) for k in keys if k != key) for i in range(len(labels))]
        groups = list(dict.fromkeys(others))
        for g, group in enumerate(groups):
            idx = [i for i in range(len(labels)) if others[i] == group]
            idx.sort(key=lambda i: order.index(values[i]))
            xs = [numbers[order.index(values[i])] if numbers is not None else order.index(values[i]) for i in idx]
            text = ", ".join(f"{k}={v}" for k, v in group) or name
            ax.plot(xs, means[idx], marker="o", color=color(g), label=text)
        if numbers is not None:
            if np.all(numbers > 0) and numbers.max() / numbers.min() >= 10:
                ax.set_xscale("log")
            ax.set_xticks(numbers, order)
        else:
            ax.set_xticks(range(len(order)), order)
        ax.set_xlabel(f"{name} {key}")
        ax.set_ylabel(f"mean {kind} RMSE [deg]")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        if len(groups) > 1:
            ax.legend(fontsize=8)
    # two short lines: one panel is narrower than the one-line title
    fig.suptitle(f"{name}: mean {kind} RMSE against each parameter\n(over the recordings with truth)", fontsize=11)
    return fig


def sweep_figure(rows: list[dict], kind: str = "total") -> Figure | None:
    """A sweep at a glance: mean RMSE against each varied parameter, one panel per parameter,
    each point the minimum over the other parameters' values (BROAD's figures); the best common
    setting is marked. None unless at least two parameters vary (one is `param_figure`)."""
    labels = list(dict.fromkeys(r["estimator"] for r in rows))
    name, table = label_params(labels)
    if len(table) < 2:
        return None
    means = np.array([_mean_rmse(rows, label, kind) for label in labels])
    if not np.any(np.isfinite(means)):
        return None
    best = int(np.nanargmin(means))
    keys = list(table)
    fig = _new_figure(max(6.5, 4.2 * len(keys)), 4.2)
    axes = np.atleast_1d(fig.subplots(1, len(keys), sharey=True))
    for ax, key in zip(axes, keys):
        values = table[key]
        order = list(dict.fromkeys(values))
        numbers = _as_numbers(order)
        xs = numbers if numbers is not None else np.arange(len(order))
        ys = [np.nanmin(np.where([v == value for v in values], means, np.nan)) for value in order]
        ax.plot(xs, ys, marker="o", color=color(0), label="minimum over the others")
        ax.plot(xs[order.index(values[best])], means[best], marker="*", markersize=14, color=color(1),
                linestyle="none", label="best common setting")
        if numbers is not None and np.all(numbers > 0) and numbers.max() / numbers.min() >= 10:
            ax.set_xscale("log")
        ax.set_xticks(xs, order)
        ax.set_xlabel(f"{name} {key}")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"mean {kind} RMSE [deg]")
    axes[0].set_ylim(bottom=0)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{name}: mean {kind} RMSE against each parameter (minimum over the others)\n"
                 f"best common setting: {labels[best]}, {means[best]:.2f} deg", fontsize=10)
    return fig


def grid_figure(rows: list[dict], kind: str = "total") -> Figure | None:
    """Heat map of the mean RMSE over a two-parameter grid; None unless exactly two vary."""
    labels = list(dict.fromkeys(r["estimator"] for r in rows))
    name, table = label_params(labels)
    if len(table) != 2:
        return None
    (k1, v1), (k2, v2) = table.items()
    a, b = list(dict.fromkeys(v1)), list(dict.fromkeys(v2))
    m = np.full((len(a), len(b)), np.nan)
    for i, label in enumerate(labels):
        m[a.index(v1[i]), b.index(v2[i])] = _mean_rmse(rows, label, kind)
    fig = _new_figure(2.5 + 1.1 * len(b), 1.8 + 0.6 * len(a))
    ax = fig.subplots()
    _heatmap(ax, m, a, b, f"{name}: mean {kind} RMSE [deg]", "deg", fig)
    ax.set_ylabel(k1)
    ax.set_xlabel(k2)
    return fig


def bars_figure(rows: list[dict]) -> Figure:
    """Grouped bars: mean RMSE (total, inclination, heading) per estimator setting."""
    labels = list(dict.fromkeys(r["estimator"] for r in rows))
    fig = _new_figure(max(6, 1.2 + 0.9 * len(labels)), 4.8)
    ax = fig.subplots()
    width = 0.8 / len(KINDS)
    x = np.arange(len(labels))
    for k, kind in enumerate(KINDS):
        values = [_mean_rmse(rows, label, kind) for label in labels]
        ax.bar(x + (k - 1) * width, np.nan_to_num(values), width, label=kind, color=f"C{k}")
    ax.set_xticks(x, labels, rotation=30 if len(labels) > 3 else 0, ha="right" if len(labels) > 3 else "center",
                  fontsize=8)
    ax.set_ylabel("mean RMSE [deg] over recordings with truth")
    ax.grid(alpha=0.3, axis="y")
    fig.legend(fontsize=9, loc="outside right upper")  # beside the axes: never over a bar
    ax.set_title("mean RMSE per setting", fontsize=10)
    return fig


def slug(text: str) -> str:
    """A file-name-safe form of a dataset id or label."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "x"


# --- filter consistency (what a filter believes, `fusion.evaluation.scoring.consistency`) ---

MAX_BINS = 800  # a curve longer than this is drawn from per-bin statistics (about one bin per pixel)
ERR_COLOR, SIGMA_COLOR, NIS_COLOR, BAND_COLOR = "tab:red", "tab:blue", "tab:purple", "tab:green"
EVENT_COLORS = {"skipped": "tab:red", "guarded": "tab:orange", "rest": "tab:green"}


def _bins(n: int, max_bins: int) -> tuple[np.ndarray, int]:
    """Start indices of equal bins of k samples covering n samples (k = 1 when n <= max_bins)."""
    k = max(1, math.ceil(n / max_bins))
    return np.arange(0, n, k), k


def _centres(x: np.ndarray, starts: np.ndarray, k: int) -> np.ndarray:
    return x[np.minimum(starts + k // 2, len(x) - 1)]


def decimate_minmax(x: np.ndarray, y: np.ndarray, max_bins: int = MAX_BINS) -> tuple[np.ndarray, np.ndarray]:
    """A long curve as the minimum and maximum of each of at most `max_bins` bins, drawn as a
    vertical stroke per bin, so that no spike is lost; bins with only NaN stay NaN (a break).
    Short curves (at most 2 `max_bins` samples) are returned as they are."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(y) <= 2 * max_bins:
        return x, y
    starts, k = _bins(len(y), max_bins)
    lo, hi = np.fmin.reduceat(y, starts), np.fmax.reduceat(y, starts)
    xc = _centres(x, starts, k)
    return np.repeat(xc, 2), np.column_stack([lo, hi]).ravel()


def decimate_max(x: np.ndarray, y: np.ndarray, max_bins: int = MAX_BINS) -> tuple[np.ndarray, np.ndarray]:
    """A long curve as the maximum of each of at most `max_bins` bins (an envelope drawn no
    narrower than it is), at the bins' centres; NaN-only bins stay NaN."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(y) <= max_bins:
        return x, y
    starts, k = _bins(len(y), max_bins)
    return _centres(x, starts, k), np.fmax.reduceat(y, starts)


def decimate_stride(x: np.ndarray, y: np.ndarray, max_bins: int = MAX_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Every k-th sample of a smooth curve (at most `max_bins` points); y may be (N,) or (N, m)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    _, k = _bins(len(x), max_bins)
    return x[::k], y[::k]


def _bin_quantiles(y: np.ndarray, max_bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """(starts, min, median, max) of the finite values of each bin, and k."""
    import warnings

    starts, k = _bins(len(y), max_bins)
    padded = np.full(len(starts) * k, np.nan)
    padded[:len(y)] = y
    table = padded.reshape(len(starts), k)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN bins (no update) give NaN
        return starts, np.nanmin(table, axis=1), np.nanmedian(table, axis=1), np.nanmax(table, axis=1), k


def event_spans(t: np.ndarray, mask: np.ndarray, min_width: float) -> list[tuple[float, float]]:
    """(start, width) of the runs of True in `mask` over samples `t`, each at least `min_width`
    wide (one sample of a 50,000-sample recording would be a fraction of a pixel) and merged
    where they then overlap, for `broken_barh`."""
    ends = [(float(t[a]), max(float(t[min(stop, len(t) - 1)]), float(t[a]) + min_width)) for a, stop in runs(mask)]
    return [(a, b - a) for a, b in merge_spans(ends)]


def _pct(value: float) -> str:
    return "-" if not np.isfinite(value) else f"{100 * value:.1f} %"


def _error_limit(err: np.ndarray, env: np.ndarray) -> float:
    """Half-range (deg) of an error panel: set by the error, not by the envelope, so that an
    error of 2 deg stays readable beside a heading envelope of 40 deg: 1.3 times the larger of the
    largest error and the envelope's 10th percentile (where the filter is most confident), at most
    180 deg. Where the envelope is wider, its band runs off the panel (the title says so)."""
    peak = float(np.nanmax(np.abs(err))) if np.isfinite(err).any() else 0.0
    tight = float(np.nanpercentile(env, 10)) if np.isfinite(env).any() else 1.0
    return min(180.0, 1.3 * max(peak, tight, 1e-3))


def consistency_figure(s: RecordingSeries, e: int, max_bins: int = MAX_BINS, summary=None,
                       truth: str = TRUTH) -> Figure | None:
    """What filter `e` believed on this recording (None if it reports no covariance):

    (a) the attitude error against the truth about each body axis with the filter's own
        +-3 sqrt(P_ii) envelope, deg, and the fraction of samples inside it;
    (b) the NIS of its accelerometer updates on a log axis with the chi-square(3) two-sided
        95 % band, the fraction inside it and the mean with its own band;
    (c) the samples without an accelerometer update (skipped or gated), the rest bias updates
        and the chi-square guard, as marks on the time axis;
    (d) the gyro-bias estimate, deg/s, where the filter estimates one.

    Recordings longer than `max_bins` samples are drawn from per-bin statistics: the error as
    per-bin minimum and maximum, the envelope as per-bin maximum, the NIS as per-bin median
    with its minimum-maximum range. The error panels' range follows the error
    (`_error_limit`). See `fusion.evaluation.scoring.consistency` for the tests and what they cannot
    separate (heading is unobservable; the truth's own error enters the error). The layout is
    fixed (no layout engine): a report draws one of these per filter and recording, and the
    constrained layout would double its cost. `summary`: the belief's `consistency.summarize`,
    if the caller has it already.
    """
    from matplotlib.ticker import LogLocator, NullLocator

    from ..scoring import consistency as cons

    belief = s.beliefs.get(e)
    if belief is None:
        return None
    summary = cons.summarize(belief) if summary is None else summary
    t0 = float(s.imu_t[0])
    x = s.imu_t - t0
    span = float(x[-1]) if len(x) > 1 and x[-1] > 0 else 1.0
    has_bias = belief.bias_rad_s is not None
    ratios = [1.0, 1.0, 1.0, 1.3, 0.55] + ([0.9] if has_bias else [])
    panel_in, gap_in, top_in, bottom_in = 1.45, 0.3, 0.65, 0.55
    height = top_in + bottom_in + panel_in * sum(ratios) + gap_in * (len(ratios) - 1)
    fig = Figure(figsize=(11, height), dpi=DPI)
    with matplotlib.rc_context({"axes.grid": True, "grid.alpha": 0.3}):  # grids made with the ticks, not redone
        axes = fig.subplots(len(ratios), 1, sharex=True, gridspec_kw={
            "height_ratios": ratios, "left": 0.11, "right": 0.985, "top": 1 - top_in / height,
            "bottom": bottom_in / height, "hspace": gap_in / (panel_in * sum(ratios) / len(ratios))})
    # Text is most of the drawing time of a figure like this one (a report draws one per filter and
    # recording): the numbers go into few, short titles; the report's section explains them.
    err_deg = np.degrees(belief.err_rad)
    env_deg = cons.N_SIGMA * np.degrees(belief.sigma_rad)
    has_truth = summary.samples_with_truth > 0
    clipped = []
    for i, (ax, name) in enumerate(zip(axes[:3], "xyz")):
        _shade(ax, s, t0)
        xe, env = decimate_max(x, env_deg[:, i], max_bins)
        ax.fill_between(xe, -env, env, color=SIGMA_COLOR, alpha=0.18, lw=0, label="filter's ±3σ")
        if has_truth:
            ax.plot(*decimate_minmax(x, err_deg[:, i], max_bins), color=ERR_COLOR, lw=0.7, label=f"error vs {truth}")
        lim = _error_limit(err_deg[:, i] if has_truth else np.array([np.nan]), env_deg[:, i])
        ax.set_ylim(-lim, lim)
        ax.set_ylabel(f"about body {name}\n[deg]")
        widest = float(np.nanmax(env_deg[:, i])) if np.isfinite(env_deg[:, i]).any() else 0.0
        if widest > lim:
            clipped.append(f"{name} ±{widest:.0f}")
    if has_truth:
        x_in, y_in, z_in = (_pct(v) for v in summary.inside_3sigma)
        text = (f"inside ±3σ (99.7 % if consistent): x {x_in}, y {y_in}, z {z_in} of {summary.samples_with_truth} "
                "samples")
    else:
        text = f"no {truth}: the error is unknown, the filter's envelope only"
    if clipped:
        text += f"; envelope beyond the panel up to {', '.join(clipped)} deg"
    axes[0].set_title(text, fontsize=9, loc="left", y=1.0)
    handles, _ = axes[0].get_legend_handles_labels()
    axes[0].legend(handles=handles + _shade_handles(s, truth), loc="upper right", fontsize=8, ncol=4, framealpha=0.9)

    ax = axes[3]
    lo, hi = cons.chi2_band(cons.NIS_DOF)
    ax.axhspan(lo, hi, color=BAND_COLOR, alpha=0.15, lw=0, label="χ²(3) 95 % band")
    ax.axhline(cons.NIS_DOF, color=BAND_COLOR, lw=1.0, ls=":", label="mean if consistent")
    nis = np.where(belief.nis > 0, belief.nis, np.nan)  # log axis: a zero NIS is drawn as no point
    if summary.updates and len(nis) > max_bins:
        starts, nmin, nmed, nmax, k = _bin_quantiles(nis, max_bins)
        xc = _centres(x, starts, k)
        ax.fill_between(xc, nmin, nmax, color=NIS_COLOR, alpha=0.25, lw=0, label=f"min-max per {k} samples")
        ax.plot(xc, nmed, color=NIS_COLOR, lw=0.8, label="median")
    elif summary.updates:
        ax.plot(x, nis, ".", color=NIS_COLOR, ms=2, label="NIS per update")
    ax.set_yscale("log")
    finite = nis[np.isfinite(nis)]
    if finite.size:
        ax.set_ylim(max(min(float(finite.min()), lo) / 2, 1e-6), max(float(finite.max()), hi) * 2)
    else:
        ax.set_ylim(1e-2, 1e2)
        ax.text(0.5, 0.5, "no accelerometer update: no NIS", transform=ax.transAxes, ha="center", va="center")
    ax.yaxis.set_major_locator(LogLocator(numticks=6))
    ax.yaxis.set_minor_locator(NullLocator())
    ax.yaxis.set_major_formatter(lambda v, _: f"{v:g}")  # plain numbers, no mathtext: cheaper and as clear
    ax.set_ylabel("NIS (log)")
    mlo, mhi = summary.nis_mean_band
    ax.set_title(f"NIS: {_pct(summary.nis_inside)} of {summary.updates} updates in [{lo:.2f}, {hi:.2f}] (95 % if "
                 f"consistent); mean {summary.nis_mean:.3g} (if consistent {mlo:.2f}-{mhi:.2f})", fontsize=9,
                 loc="left", y=1.0)
    ax.legend(loc="upper right", fontsize=8, ncol=4, framealpha=0.9)

    ax = axes[4]
    rows = [("skipped", belief.skipped, "no acc update", summary.skipped)]
    if belief.guarded is not None:
        rows.append(("guarded", belief.guarded, "bias guarded", summary.guarded))
    if belief.rest is not None:
        rows.append(("rest", belief.rest, "rest update", summary.rest))
    for r, (key, mask, _, _) in enumerate(rows):
        ax.broken_barh(event_spans(x, mask, span / 800), (r - 0.35, 0.7), color=EVENT_COLORS[key])
    ax.set_yticks(range(len(rows)), [label for _, _, label, _ in rows], fontsize=8)
    ax.set_ylim(-0.6, len(rows) - 0.4)
    ax.yaxis.grid(False)
    counts = ", ".join(f"{label} {count}" for _, _, label, count in rows)
    ax.set_title(f"samples: {counts}", fontsize=9, loc="left", y=1.0)

    if has_bias:
        ax = axes[5]
        xb, bias = decimate_stride(x, np.degrees(belief.bias_rad_s), max_bins)
        for i, name in enumerate("xyz"):
            ax.plot(xb, bias[:, i], color=f"C{i}", lw=1.0, label=name)
        ax.set_ylabel("gyro bias\n[deg/s]")
        ax.legend(loc="upper right", fontsize=8, ncol=3, framealpha=0.9)
    axes[-1].set_xlabel("time since first IMU sample [s]")
    axes[-1].set_xlim(0, span)
    label = _display_label(s.labels[e], s.causal[e])
    fig.suptitle(f"{s.id}, {label}: attitude error against the filter's ±3σ, NIS, events"
                 + (", gyro bias" if has_bias else ""), fontsize=10, y=1 - 0.15 / height, va="top")
    return fig


# --- the error around a recording's events ---

# a filter's flags (`fusion.evaluation.scoring.consistency.Belief`), marked where they switch on; any other
# per-sample flag of an estimator (`RecordingSeries.flags`) gets one of OTHER_FLAG_MARKERS, in order
FLAG_MARKS = {"rest": ("v", "rest update on"), "guarded": ("x", "bias guard on"),
              "skipped": ("|", "accelerometer update skipped")}
OTHER_FLAG_MARKERS = ("^", "s", "D", "o", "P", "*", "<", ">", "d", "h")
# the recording's events (`RecordingSeries.events`) other than those the series shows itself (no
# truth, gyro invalid: `_shade`): colour and alpha of their shading
EVENT_STYLES = {"rest": ("tab:green", 0.15), "gyro freeze": ("tab:purple", 0.25),
                "gyro beyond range": ("tab:orange", 0.25), "time-stamp gap": ("tab:brown", 0.25),
                "magnetic disturbance": ("tab:cyan", 0.2), "movement": ("tab:blue", 0.06)}
# states rather than incidents: shaded, never zoomed on
NOT_ZOOMED = ("rest", "movement")


def recording_events(s: RecordingSeries) -> list[tuple[float, float, str]]:
    """The events inside the recording the series knows (s, absolute): spans where the gyro was
    marked invalid (`gyr_valid`: detected freezes, saturation) and gaps in the truth, leaving out
    the spans before its first and after its last sample; and, where the series kept them
    (`RecordingSeries.events`), the recording's rests, gyro freezes, samples beyond the gyro's
    range, time-stamp gaps, magnetic disturbances and movement phases; sorted by start."""
    t0, t1 = float(s.imu_t[0]), float(s.imu_t[-1])
    inside = [(a, b, "no truth") for a, b in truth_gaps(s) if a > t0 and b < t1] if s.has_truth else []
    kept = [(t0 + a, t0 + b, name) for name, spans in (s.events or {}).items() if name in EVENT_STYLES
            for a, b in spans]
    return sorted(inside + [(a, b, "gyro invalid") for a, b in bad_gyro_spans(s)] + kept)


def flag_switches(s: RecordingSeries, e: int) -> dict[str, np.ndarray]:
    """Times (s, absolute) where estimator `e`'s flags switched on, by flag: its belief's rest
    update, bias guard and skipped accelerometer updates (`FLAG_MARKS`), and its other per-sample
    flags (`RecordingSeries.flags`: VQF's rest and magnetic-disturbance detection, Fusion's
    rejections, our filters' magnetometer use and scale test, ...); {} without any. A flag already
    on at the first sample counts as switched on there."""
    belief = s.beliefs.get(e)
    flags = {"rest": belief.rest, "guarded": belief.guarded, "skipped": belief.skipped} if belief is not None else {}
    flags.update(s.flags.get(e, {}))
    return {key: np.asarray(s.imu_t, float)[[a for a, _ in runs(mask)]]
            for key, mask in flags.items() if mask is not None and np.any(mask)}


def _flag_marks(keys) -> dict[str, tuple[str, str]]:
    """(marker, legend label) of each flag name: `FLAG_MARKS`, then `OTHER_FLAG_MARKERS` in order."""
    others = sorted(k for k in set(keys) if k not in FLAG_MARKS)
    marks = {k: FLAG_MARKS[k] for k in FLAG_MARKS if k in keys}
    marks.update({k: (OTHER_FLAG_MARKERS[i % len(OTHER_FLAG_MARKERS)], k.replace("_", " ") + " on")
                  for i, k in enumerate(others)})
    return marks


def _shade_events(ax, s: RecordingSeries, t0: float) -> None:
    """Shade the recording's kept events (`EVENT_STYLES`) besides what `_shade` shows."""
    for name, spans in (s.events or {}).items():
        if name in EVENT_STYLES:
            rgb, alpha = EVENT_STYLES[name]
            for a, b in spans:
                ax.axvspan(a, max(b, a + 1e-3), color=rgb, alpha=alpha, lw=0, zorder=0)


def _event_handles(s: RecordingSeries) -> list:
    return [Patch(color=EVENT_STYLES[name][0], alpha=EVENT_STYLES[name][1] + 0.2, label=name)
            for name in EVENT_STYLES if (s.events or {}).get(name)]


def event_error_figure(s: RecordingSeries, truth: str = TRUTH, window_s: float = 3.0,
                       max_windows: int = 3) -> Figure | None:
    """The total error of every estimator against time, with the recording's events shaded
    (`recording_events`: no truth in grey, gyro invalid in red, the others in `EVENT_STYLES`'
    colours) and each estimator's flag switches marked (`flag_switches`): over the whole recording,
    then zoomed to `window_s` either side of its `max_windows` longest events (rests and movement
    phases are shaded, not zoomed on; events closer than two windows share one). None without
    truth, or with neither events nor flags."""
    if not s.has_truth or not np.isfinite(s.err_deg).any():
        return None
    events = recording_events(s)
    switches = {e: flag_switches(s, e) for e in range(len(s.labels))}
    flagged = [e for e, marks in switches.items() if marks]
    if not events and not flagged:
        return None
    marks = _flag_marks({key for e in flagged for key in switches[e]})
    near: list[tuple[float, float, str]] = []  # events whose zoomed windows would overlap share one
    for a, b, kind in (ev for ev in events if ev[2] not in NOT_ZOOMED):
        if near and a - window_s <= near[-1][1] + window_s:
            kinds = list(dict.fromkeys(near[-1][2].split(" + ") + [kind]))
            near[-1] = (near[-1][0], max(near[-1][1], b), " + ".join(kinds))
        else:
            near.append((a, b, kind))
    windows = sorted(sorted(near, key=lambda ev: ev[0] - ev[1])[:max_windows])
    t0 = float(s.imu_t[0])
    x = s.imu_t - t0
    ncols = max(len(windows), 1)
    layout = [["all"] * ncols] + ([["flags"] * ncols] if flagged else []) + ([[f"w{i}" for i in range(ncols)]]
                                                                              if windows else [])
    heights = [3.0] + ([0.5 + 0.35 * len(flagged)] if flagged else []) + ([2.6] if windows else [])
    fig = _new_figure(11, 1.2 + sum(heights))
    axes = fig.subplot_mosaic(layout, height_ratios=heights)

    def draw_errors(ax, lo: float, hi: float, decimate: bool) -> None:
        _shade(ax, s, t0)
        _shade_events(ax, s, t0)
        top = 0.0
        for e, label in enumerate(s.labels):
            err = s.err_deg[e, 0]
            inside = (x >= lo) & (x <= hi)
            xs, ys = decimate_minmax(x[inside], err[inside]) if decimate else (x[inside], err[inside])
            ax.plot(xs, ys, color=color(e), ls=linestyle(e), lw=1.0, label=_display_label(label, s.causal[e]))
            if np.isfinite(err[inside]).any():
                top = max(top, float(np.nanmax(err[inside])))
        for r, e in enumerate(flagged):  # flag switches as ticks along the bottom, one row per filter
            for key, times in switches[e].items():
                shown = times[(times - t0 >= lo) & (times - t0 <= hi)] - t0
                ax.plot(shown, np.full(len(shown), 0.04 + 0.07 * r), marks[key][0], color=color(e), ms=5,
                        transform=ax.get_xaxis_transform(), clip_on=True)
        ax.set_xlim(lo, hi)
        ax.set_ylim(0, 1.1 * top if top > 0 else 1.0)
        ax.grid(alpha=0.3)

    span = float(x[-1])
    draw_errors(axes["all"], 0.0, span, decimate=True)
    axes["all"].set_ylabel("total error [deg]")
    axes["all"].set_xlabel("time since first IMU sample [s]")
    for a, b, _ in windows:
        axes["all"].axvspan(a - t0 - window_s, b - t0 + window_s, fill=False, ec="0.3", lw=0.8, ls="--", zorder=3)
    if flagged:
        ax = axes["flags"]
        for r, e in enumerate(flagged):
            for key, times in switches[e].items():
                ax.plot(times - t0, np.full(len(times), r), marks[key][0], color=color(e), ms=6)
        ax.set_yticks(range(len(flagged)), [_display_label(s.labels[e], s.causal[e]) for e in flagged], fontsize=8)
        ax.set_ylim(-0.6, len(flagged) - 0.4)
        ax.set_xlim(0, span)
        ax.set_title("where each filter's flags switched on", fontsize=9, loc="left")
        ax.grid(alpha=0.3, axis="x")
    for i, (a, b, kind) in enumerate(windows):
        ax = axes[f"w{i}"]
        draw_errors(ax, max(a - t0 - window_s, 0.0), min(b - t0 + window_s, span), decimate=False)
        ax.set_title(f"{kind}: {a - t0:.2f}-{b - t0:.2f} s", fontsize=9, loc="left")
        ax.set_xlabel("time [s]")
        if i == 0:
            ax.set_ylabel("total error [deg]")
    handles, _ = axes["all"].get_legend_handles_labels()
    handles += _shade_handles(s, truth) + _event_handles(s)
    handles += [Line2D([], [], ls="none", marker=marker, color="0.2", label=label) for marker, label in marks.values()]
    longest = max(len(h.get_label()) for h in handles)  # columns that fit the figure's width (11 in at 9 pt)
    fig.legend(handles=handles, loc="outside lower center", ncol=max(1, min(len(handles), 4, 110 // (longest + 8))),
               fontsize=9)
    fig.suptitle(f"{s.id}: total error against {truth} around the events"
                 + (f" (dashed: the {len(windows)} longest, zoomed below)" if windows else ""), fontsize=10)
    return fig
