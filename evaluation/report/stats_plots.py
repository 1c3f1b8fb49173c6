"""The critical-difference diagram of a comparison (Demsar 2006, "Statistical comparisons of
classifiers over multiple data sets", JMLR 7:1-30, sec. 3.2.2 and Fig. 1), drawn by
`scikit_posthocs.critical_difference_diagram` from a `fusion.evaluation.scoring.stats.Statistics`: the
rows on an axis at their average rank over the recordings (1: the lowest error), a bar joining the
rows that Nemenyi's test does not tell apart (p >= alpha), and the critical difference above the
axis. Built on a `matplotlib.figure.Figure` without pyplot, as `fusion.evaluation.report.plots` does.
"""
from __future__ import annotations

from typing import Any, Mapping

from matplotlib.figure import Figure

from ..scoring.stats import Statistics
from .plots import DPI, color


def cd_figure(statistics: Statistics, title: str = "", colors: Mapping[str, Any] | None = None) -> Figure | None:
    """The diagram, or None without Nemenyi's test (fewer than three rows).

    title: what is compared (e.g. "total RMSE"); the recordings and Friedman's p are added to it.
    colors: each row's colour (a report's: the estimator's in every figure); None: `plots.color`
        in the rows' order.
    """
    if statistics.nemenyi_p is None:
        return None
    import pandas as pd
    import scikit_posthocs

    labels = list(statistics.labels)
    ranks = pd.Series({r.label: r.rank for r in statistics.rows})
    p = pd.DataFrame(statistics.nemenyi_p, index=labels, columns=labels)
    width = max(len(label) for label in labels)
    fig = Figure(figsize=(7.5 + 0.12 * width, 1.6 + 0.3 * len(labels)), dpi=DPI, layout="constrained")
    ax = fig.subplots()
    scikit_posthocs.critical_difference_diagram(
        ranks, p, ax=ax, cd=statistics.critical_difference, alpha=statistics.alpha,
        color_palette={label: (colors or {}).get(label, color(i)) for i, label in enumerate(labels)},
        label_fmt_left="{label} ({rank:.2f})", label_fmt_right="({rank:.2f}) {label}",
        label_props={"fontsize": 8})
    # room for the labels left and right of the axis (the diagram writes them outside the ranks' span)
    ax.set_xlim(0.5, len(labels) + 0.5)
    friedman = "" if statistics.friedman_p is None else f", Friedman p = {statistics.friedman_p:.2g}"
    ax.set_title(f"{title + ': ' if title else ''}average rank over {len(statistics.recordings)} recordings "
                 f"(1 = lowest){friedman}; bars: Nemenyi p >= {statistics.alpha:g}", fontsize=9, pad=28)
    return fig
