"""How sure is a difference in the table: statistics over the recordings of a comparison.

Each row (an estimator, an ablation's setting, a tuning trial) has one score per recording, lower
is better (an RMSE in degrees here; any score will do). On the recordings where every row has a
finite score (complete cases; the others are dropped, and `Statistics.dropped` says which and for
want of which row's score), for each row:

- its mean over the recordings with a 95 % bootstrap confidence interval: the recordings are
  resampled with replacement, the same resamples for every row, and the interval is the
  bias-corrected and accelerated (BCa) percentile interval (Efron & Tibshirani 1993, An
  Introduction to the Bootstrap, ch. 14.3), computed by `scipy.stats.bootstrap` with a fixed
  seed, so the same scores always give the same interval;
- paired against the best row (the lowest mean): per recording a win, a tie or a loss (a tie:
  equal to within a relative tolerance `TIE_RTOL`), and the p-value of the two-sided Wilcoxon
  signed-rank test of the paired differences (Demsar 2006, sec. 3.1.3; differences within the tie
  tolerance count as zero and are dropped, Wilcoxon's own rule), Holm-corrected over the
  comparisons with the best (Holm 1979, "A simple sequentially rejective multiple test
  procedure", Scand. J. Statist. 6:65-70). A row whose corrected p is at least `ALPHA` is not
  significantly worse than the best (the best row itself counts as such);
- with three rows or more: the Friedman test over all rows and Nemenyi's post-hoc test on the
  average ranks (Demsar 2006, "Statistical comparisons of classifiers over multiple data sets",
  JMLR 7:1-30, sec. 3.2.2), with its critical difference: the data of a critical-difference
  diagram (`fusion.evaluation.report.stats_plots.cd_figure`).

With fewer than `MIN_RECORDINGS` complete recordings there are no statistics: `paired_statistics`
returns None and `no_statistics_reason` says why in one line. Few recordings limit what a test can
show: the smallest two-sided Wilcoxon p of n pairs is 2 / 2^n (a row worse on every recording:
0.0625 for 5, 0.031 for 6, 0.0039 for 9, 0.00012 for 14), and Holm multiplies the smallest p by
the number of rows compared with the best.

    from fusion.evaluation.scoring.stats import paired_statistics
    s = paired_statistics({"ekf": {"r1": 2.1, "r2": 1.7, ...}, "vqf": {"r1": 2.4, "r2": 1.9, ...}})
    s.row("vqf").p_holm, s.row("vqf").ci_low, s.friedman_p

`run_statistics(fusion.evaluation.compare.summary_groups(results))` does it for a run's rows
(`fusion.evaluation.run.job.Result`), per metric, over the groups the table's means are taken over.

SciPy's statistics, statsmodels and scikit-posthocs (with pandas) are imported when statistics
are computed, never with this module: they take a second or two to import.
"""
from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ..run.job import Result
from .metrics import KINDS

# Fewer complete recordings: no statistics. The two-sided Wilcoxon p of n pairs is at least 2 / 2^n (module
# docstring): no row is significantly worse than the best on five recordings, only a row worse on all six when it
# is the only one compared, ...; the intervals and ranks say what five can.
MIN_RECORDINGS = 5
CONFIDENCE_LEVEL = 0.95
N_RESAMPLES = 9999  # SciPy's default; between seeds a bound moves by a few percent of the interval's width
SEED = 20060101  # any fixed value: the same scores always give the same intervals
ALPHA = 0.05
TIE_RTOL = 1e-9  # |a - b| <= TIE_RTOL * max(|a|, |b|): a tie (RMSEs of 1-50 deg: within 1e-9-5e-8 deg)
CI_METHOD = "BCa"


@dataclass(frozen=True)
class RowStatistics:
    """One row against the others, over the complete recordings.

    mean: the mean score; ci_low, ci_high: its `CONFIDENCE_LEVEL` bootstrap interval (None when it
        cannot be computed).
    rank: the average rank over the recordings (1: the lowest score; ties share the mean rank).
    wins, ties, losses: recordings where the row scores lower than, the same as (within
        `TIE_RTOL`) or higher than the best row (the best row: all ties).
    p_value: two-sided Wilcoxon signed-rank p against the best row; p_holm: Holm-adjusted over
        the rows compared with the best; both None for the best row.
    not_worse: the best row, or p_holm >= alpha.
    """

    label: str
    mean: float
    ci_low: float | None
    ci_high: float | None
    rank: float
    wins: int
    ties: int
    losses: int
    p_value: float | None
    p_holm: float | None
    not_worse: bool

    def to_json(self) -> dict[str, Any]:
        return {"label": self.label, "mean": _num(self.mean), "ci_low": _num(self.ci_low),
                "ci_high": _num(self.ci_high), "rank": _num(self.rank), "wins": self.wins, "ties": self.ties,
                "losses": self.losses, "p_value": _num(self.p_value), "p_holm": _num(self.p_holm),
                "not_worse": self.not_worse}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "RowStatistics":
        return cls(d["label"], float(d["mean"]), _opt(d["ci_low"]), _opt(d["ci_high"]), float(d["rank"]),
                   int(d["wins"]), int(d["ties"]), int(d["losses"]), _opt(d["p_value"]), _opt(d["p_holm"]),
                   bool(d["not_worse"]))


@dataclass(frozen=True)
class Dropped:
    """A recording left out of the statistics, and the rows without a finite score on it."""

    recording: str
    without_score: tuple[str, ...]

    def to_json(self) -> dict[str, Any]:
        return {"recording": self.recording, "without_score": list(self.without_score)}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Dropped":
        return cls(d["recording"], tuple(d["without_score"]))


@dataclass(frozen=True)
class Statistics:
    """The statistics of one comparison (module docstring); `paired_statistics` builds it.

    metric: what the scores are (`total`, `inclination`, `heading`, or a caller's name).
    rows: one per row compared, in the order given.
    best: the label of the row with the lowest mean (ties: the first label in sorted order).
    recordings: the complete recordings, sorted: the order every computation uses.
    dropped: the recordings left out, sorted; left_out: rows with a finite score on at most half of the
        recordings, none included (left out before the complete cases are taken, else their failures
        would drop most recordings from every row's comparison).
    friedman_statistic, friedman_p: Friedman's chi-square and its p-value (Demsar 2006, sec. 3.2.2,
        the chi-square form); None with fewer than three rows or when every recording ties.
    nemenyi_p: (k, k) Nemenyi p-values between the rows, in `rows` order (None below three rows);
    critical_difference: Nemenyi's critical difference of average ranks at `alpha`,
        q_alpha sqrt(k (k + 1) / (6 N)) (Demsar 2006, sec. 3.2.2), None below three rows.
    confidence_level, n_resamples, seed, ci_method: the bootstrap's settings; alpha: the level of
        the tests; tie_rtol: the relative tolerance of a tie.
    """

    metric: str
    rows: tuple[RowStatistics, ...]
    best: str
    recordings: tuple[str, ...]
    dropped: tuple[Dropped, ...] = ()
    left_out: tuple[str, ...] = ()
    friedman_statistic: float | None = None
    friedman_p: float | None = None
    nemenyi_p: tuple[tuple[float, ...], ...] | None = None
    critical_difference: float | None = None
    confidence_level: float = CONFIDENCE_LEVEL
    n_resamples: int = N_RESAMPLES
    seed: int = SEED
    ci_method: str = CI_METHOD
    alpha: float = ALPHA
    tie_rtol: float = TIE_RTOL

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(r.label for r in self.rows)

    def row(self, label: str) -> RowStatistics:
        for r in self.rows:
            if r.label == label:
                return r
        raise KeyError(f"no row {label!r} in the statistics of {self.metric} (rows: {', '.join(self.labels)})")

    def to_json(self) -> dict[str, Any]:
        """Plain JSON types; a number that is not finite is written as null (docs/json-format.md)."""
        return {
            "metric": self.metric, "rows": [r.to_json() for r in self.rows], "best": self.best,
            "recordings": list(self.recordings), "dropped": [d.to_json() for d in self.dropped],
            "left_out": list(self.left_out), "friedman_statistic": _num(self.friedman_statistic),
            "friedman_p": _num(self.friedman_p),
            "nemenyi_p": None if self.nemenyi_p is None else [[_num(v) for v in row] for row in self.nemenyi_p],
            "critical_difference": _num(self.critical_difference), "confidence_level": self.confidence_level,
            "n_resamples": self.n_resamples, "seed": self.seed, "ci_method": self.ci_method, "alpha": self.alpha,
            "tie_rtol": self.tie_rtol,
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Statistics":
        nemenyi = d.get("nemenyi_p")
        return cls(
            d["metric"], tuple(RowStatistics.from_json(r) for r in d["rows"]), d["best"], tuple(d["recordings"]),
            tuple(Dropped.from_json(x) for x in d.get("dropped", ())), tuple(d.get("left_out", ())),
            _opt(d.get("friedman_statistic")), _opt(d.get("friedman_p")),
            None if nemenyi is None else tuple(tuple(math.nan if v is None else float(v) for v in row)
                                               for row in nemenyi),
            _opt(d.get("critical_difference")), float(d.get("confidence_level", CONFIDENCE_LEVEL)),
            int(d.get("n_resamples", N_RESAMPLES)), int(d.get("seed", SEED)), d.get("ci_method", CI_METHOD),
            float(d.get("alpha", ALPHA)), float(d.get("tie_rtol", TIE_RTOL)))


def _num(v: float | None) -> float | None:
    """A plain float for JSON, None for None, NaN or infinity."""
    return None if v is None or not math.isfinite(v) else float(v)


def _opt(v: Any) -> float | None:
    return None if v is None else float(v)


# --- complete cases ---

_Scores = tuple[tuple[str, tuple[tuple[str, "float | None"], ...]], ...]  # rows in order, (recording, score) sorted


def _normalised(scores: Mapping[str, Mapping[Any, float | None]]) -> _Scores:
    """The scores checked and made hashable: rows in the order given, each row's (recording, score)
    pairs sorted by recording, a missing or non-finite score as None."""
    if not isinstance(scores, Mapping):
        raise ValueError(f"scores must map each row's label to {{recording: score}}, got {type(scores).__name__}")
    out = []
    for label, per_recording in scores.items():
        if not isinstance(per_recording, Mapping):
            raise ValueError(f"scores[{label!r}] must map recording -> score, got {type(per_recording).__name__}")
        row = {}
        for recording, value in per_recording.items():
            try:
                value = math.nan if value is None else float(value)
            except (TypeError, ValueError):
                raise ValueError(f"scores[{label!r}][{recording!r}]: not a number ({value!r})") from None
            row[str(recording)] = value if math.isfinite(value) else None
        out.append((str(label), tuple(sorted(row.items()))))
    return tuple(out)


@dataclass(frozen=True)
class _Cases:
    labels: list[str]  # rows scored on more than half of the recordings, in the order given
    left_out: list[str]  # rows scored on at most half of the recordings (none included)
    recordings: list[str]  # complete, sorted
    dropped: list[Dropped]
    scores: np.ndarray  # (k, n): labels x recordings


def _complete_cases(scores: _Scores) -> _Cases:
    """The rows and recordings the statistics compare. A row scored on at most half of the recordings
    (one that failed on most of them) is left out, as a row without any score is, rather than drop
    the recordings it lacks from every other row's comparison: its failures cost only itself."""
    finite = {label: {rec: v for rec, v in row if v is not None} for label, row in scores}
    every = sorted({rec for _, row in scores for rec, _ in row})
    labels = [lab for lab, f in finite.items() if 2 * len(f) > len(every)]
    left_out = [lab for lab in finite if lab not in labels]
    recordings, dropped = [], []
    for recording in every:
        missing = tuple(lab for lab in labels if recording not in finite[lab])
        if missing:
            dropped.append(Dropped(recording, missing))
        else:
            recordings.append(recording)
    matrix = np.array([[finite[lab][rec] for rec in recordings] for lab in labels], dtype=float).reshape(
        len(labels), len(recordings))
    return _Cases(labels, left_out, recordings, dropped, matrix)


def no_statistics_reason(scores: Mapping[str, Mapping[Any, float | None]],
                         min_recordings: int = MIN_RECORDINGS) -> str | None:
    """One line saying why `paired_statistics(scores)` is None; None when it is not."""
    cases = _complete_cases(_normalised(scores))
    if not cases.labels:
        return "no row has a finite score"
    n = len(cases.recordings)
    if n >= min_recordings:
        return None
    why = f"{n} recording{'' if n == 1 else 's'} scored by every row, {min_recordings} needed"
    return why + (f" ({dropped_text(cases.dropped)})" if cases.dropped else "")


def dropped_text(dropped: Sequence[Dropped], limit: int = 3) -> str:
    """'2 dropped, a row without a score on each: broad/07 (ekf), broad/30 (ekf, vqf)'."""
    shown = ", ".join(f"{d.recording} ({', '.join(d.without_score)})" for d in dropped[:limit])
    more = f", +{len(dropped) - limit} more" if len(dropped) > limit else ""
    return f"{len(dropped)} dropped, a row without a score on each: {shown}{more}"


# --- the statistics ---

def paired_statistics(scores: Mapping[str, Mapping[Any, float | None]], metric: str = "score", *,
                      confidence_level: float = CONFIDENCE_LEVEL, n_resamples: int = N_RESAMPLES, seed: int = SEED,
                      alpha: float = ALPHA, tie_rtol: float = TIE_RTOL,
                      min_recordings: int = MIN_RECORDINGS) -> Statistics | None:
    """The statistics of a comparison (module docstring), or None with fewer than `min_recordings`
    complete recordings (`no_statistics_reason` says why).

    scores: {row label: {recording id: score}}, lower is better; a missing, None or non-finite
        score leaves the recording out (complete cases). Recording ids are compared as strings.
    metric: the name the result carries.
    Neither the order of the rows nor that of the recordings changes any number.
    """
    if not 0 < confidence_level < 1 or not 0 < alpha < 1:
        raise ValueError(f"confidence_level and alpha must lie in (0, 1), got {confidence_level} and {alpha}")
    if n_resamples < 1 or tie_rtol < 0 or min_recordings < 2:
        raise ValueError(f"need n_resamples >= 1, tie_rtol >= 0 and min_recordings >= 2, got {n_resamples}, "
                         f"{tie_rtol} and {min_recordings}")
    return _statistics(_normalised(scores), metric, confidence_level, n_resamples, seed, alpha, tie_rtol,
                       min_recordings)


@functools.lru_cache(maxsize=32)  # a run's table, results.json and report ask for the same statistics
def _statistics(scores: _Scores, metric: str, confidence_level: float, n_resamples: int, seed: int, alpha: float,
                tie_rtol: float, min_recordings: int) -> Statistics | None:
    cases = _complete_cases(scores)
    if not cases.labels or len(cases.recordings) < min_recordings:
        return None
    x, labels = cases.scores, cases.labels
    k, n = x.shape
    means = x.mean(axis=1)
    best = min(range(k), key=lambda i: (means[i], labels[i]))
    low, high = _bootstrap_mean_interval(x, confidence_level, n_resamples, seed)
    ranks = _average_ranks(x)
    wins, ties, losses, p = _against_best(x, best, tie_rtol)
    p_holm = _holm(p, best)
    friedman_statistic = friedman_p = nemenyi = cd = None
    if k >= 3:
        friedman_statistic, friedman_p = _friedman(x)
        nemenyi = _nemenyi(x, labels)
        cd = _critical_difference(k, n, alpha)
    rows = tuple(RowStatistics(labels[i], float(means[i]), low[i], high[i], float(ranks[i]), int(wins[i]),
                               int(ties[i]), int(losses[i]), None if i == best else p[i],
                               None if i == best else p_holm[i], i == best or p_holm[i] >= alpha)
                 for i in range(k))
    return Statistics(metric, rows, labels[best], tuple(cases.recordings), tuple(cases.dropped),
                      tuple(cases.left_out), friedman_statistic, friedman_p, nemenyi, cd, confidence_level,
                      n_resamples, seed, CI_METHOD, alpha, tie_rtol)


def _bootstrap_mean_interval(x: np.ndarray, confidence_level: float, n_resamples: int,
                             seed: int) -> tuple[list[float | None], list[float | None]]:
    """The BCa interval of each row's mean (Efron & Tibshirani 1993, ch. 14.3). x: (k, n) scores,
    rows x recordings. Per row, `scipy.stats.bootstrap` vectorised over the resamples, seeded
    alike: the same resamples of the recordings for every row, and a row's interval is exactly what
    SciPy gives for that row alone. (One call over all rows is no faster at these sizes, and its
    resample means differ in the last bit; BCa's bias correction counts the resample means below
    the sample's, some of which equal it exactly, so a bit can move the interval.) A row with one
    value on every recording has the interval [mean, mean] (every resample's mean; BCa's
    acceleration is 0/0 there)."""
    from scipy import stats

    low: list[float | None] = []
    high: list[float | None] = []
    for row in x:
        if np.ptp(row) == 0:
            low.append(float(row[0]))
            high.append(float(row[0]))
            continue
        with warnings.catch_warnings():  # a degenerate resample distribution: SciPy warns, the bounds are NaN
            warnings.simplefilter("ignore")
            ci = stats.bootstrap((row,), np.mean, vectorized=True, n_resamples=n_resamples,
                                 confidence_level=confidence_level, method=CI_METHOD,
                                 rng=np.random.default_rng(seed)).confidence_interval
        low.append(_num(float(ci.low)))
        high.append(_num(float(ci.high)))
    return low, high


def mean_of_means_interval(samples: Sequence[Sequence[float]], *, confidence_level: float = CONFIDENCE_LEVEL,
                           n_resamples: int = N_RESAMPLES, seed: int = SEED) -> tuple[float | None, float | None]:
    """The BCa interval of the mean of several samples' means (each sample, e.g. one dataset's
    recordings, counts once whatever its size), by the stratified bootstrap: every resample draws
    each sample's values from that sample alone, with replacement (Davison & Hinkley 1997,
    Bootstrap Methods and their Application, sec. 3.2; `scipy.stats.bootstrap` with several samples,
    unpaired), seeded as `paired_statistics`. With one sample it is that sample's interval of the
    mean, the interval `paired_statistics` gives a row alone. Values all equal: [mean, mean].

    samples: one sequence of finite scores per stratum, each of two values or more.
    """
    from scipy import stats

    arrays = [np.asarray(s, dtype=float) for s in samples]
    if not arrays or any(a.ndim != 1 or len(a) < 2 or not np.isfinite(a).all() for a in arrays):
        raise ValueError("mean_of_means_interval: every sample needs two finite values or more")
    if all(np.ptp(a) == 0 for a in arrays):
        value = float(np.mean([a[0] for a in arrays]))
        return value, value

    def statistic(*xs: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.mean([np.mean(x, axis=axis) for x in xs], axis=0)

    with warnings.catch_warnings():  # a degenerate resample distribution: SciPy warns, the bounds are NaN
        warnings.simplefilter("ignore")
        ci = stats.bootstrap(tuple(arrays), statistic, vectorized=True, paired=False, n_resamples=n_resamples,
                             confidence_level=confidence_level, method=CI_METHOD,
                             rng=np.random.default_rng(seed)).confidence_interval
    return _num(float(ci.low)), _num(float(ci.high))


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """(k,) average rank of each row over the recordings (Demsar 2006, sec. 3.2.2: R_j); 1 is the
    lowest score, tied scores share their mean rank."""
    from scipy.stats import rankdata

    return rankdata(x, axis=0, method="average").mean(axis=1)


def _against_best(x: np.ndarray, best: int, tie_rtol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Per row against row `best`: wins, ties, losses (counts over the recordings) and the
    two-sided Wilcoxon signed-rank p-value of the differences, a tie counted as zero (None for
    `best`; 1.0 when every recording ties)."""
    from scipy.stats import wilcoxon

    k, _ = x.shape
    diff = x - x[best]
    tie = np.abs(diff) <= tie_rtol * np.maximum(np.abs(x), np.abs(x[best]))
    wins, losses = ((diff < 0) & ~tie).sum(axis=1), ((diff > 0) & ~tie).sum(axis=1)
    p: list[float | None] = []
    for i in range(k):
        d = np.where(tie[i], 0.0, diff[i])
        if i == best:
            p.append(None)
        elif not d.any():
            p.append(1.0)
        else:
            p.append(float(wilcoxon(d).pvalue))
    return wins, tie.sum(axis=1), losses, p


def _holm(p: list[float | None], best: int) -> list[float | None]:
    """Holm's step-down adjustment (Holm 1979) of the p-values of the rows other than `best`
    (statsmodels' `multipletests`); None for `best`."""
    others = [i for i in range(len(p)) if i != best]
    out: list[float | None] = [None] * len(p)
    if not others:
        return out
    from statsmodels.stats.multitest import multipletests

    adjusted = multipletests([p[i] for i in others], method="holm")[1]
    for i, v in zip(others, adjusted):
        out[i] = float(v)
    return out


def _friedman(x: np.ndarray) -> tuple[float | None, float | None]:
    """Friedman's chi-square over the rows of x (k, n) and its p-value (`scipy.stats.friedmanchisquare`);
    None, None when every recording ties (the statistic is 0/0)."""
    from scipy.stats import friedmanchisquare

    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        result = friedmanchisquare(*x)
    return _num(float(result.statistic)), _num(float(result.pvalue))


def _nemenyi(x: np.ndarray, labels: list[str]) -> tuple[tuple[float, ...], ...]:
    """(k, k) p-values of Nemenyi's test between the rows (`scikit_posthocs.posthoc_nemenyi_friedman`
    on the recordings x rows block design), in the rows' order."""
    import pandas as pd
    import scikit_posthocs

    frame = pd.DataFrame(x.T, columns=range(len(labels)))
    p = scikit_posthocs.posthoc_nemenyi_friedman(frame).reindex(index=range(len(labels)), columns=range(len(labels)))
    return tuple(tuple(float(v) for v in row) for row in p.to_numpy())


def _critical_difference(k: int, n: int, alpha: float) -> float:
    """Nemenyi's critical difference of average ranks, CD = q_alpha sqrt(k (k + 1) / (6 N)), q_alpha
    the studentized range quantile over sqrt(2) (Demsar 2006, sec. 3.2.2)."""
    from scipy.stats import studentized_range

    q_alpha = float(studentized_range.ppf(1 - alpha, k, np.inf)) / math.sqrt(2)
    return q_alpha * math.sqrt(k * (k + 1) / (6 * n))


# --- a run's rows ---

@dataclass(frozen=True)
class Comparison:
    """One comparison of a run: a metric, over one group's recordings (`summary_groups`), of the
    rows that can be compared on it.

    group: the folder (None: the run has one group); imu: "6-D", "9-D" or "mixed" when the rows
        were split by it (the total and heading of a 6-D row are scored with its heading offset
        removed, a 9-D row's without: not comparable), None when they were not.
    labels: the rows compared, in run order.
    statistics: None with too few complete recordings; reason then says why in one line.
    """

    metric: str
    group: str | None
    imu: str | None
    labels: tuple[str, ...]
    statistics: Statistics | None
    reason: str | None = None

    @property
    def name(self) -> str:
        """'' for a run's only comparison of a metric, else 'broad, 9-D rows' and the like."""
        return ", ".join([*([self.group] if self.group else []), *([f"{self.imu} rows"] if self.imu else [])])

    def to_json(self) -> dict[str, Any]:
        return {"group": self.group, "imu": self.imu, "labels": list(self.labels),
                "statistics": None if self.statistics is None else self.statistics.to_json(), "reason": self.reason}

    @classmethod
    def from_json(cls, metric: str, d: Mapping[str, Any]) -> "Comparison":
        s = d.get("statistics")
        return cls(metric, d.get("group"), d.get("imu"), tuple(d["labels"]),
                   None if s is None else Statistics.from_json(s), d.get("reason"))


@dataclass(frozen=True)
class RunStatistics:
    """Every comparison of a run (`run_statistics`), metric by metric in `KINDS` order."""

    comparisons: tuple[Comparison, ...]

    def of(self, metric: str) -> tuple[Comparison, ...]:
        return tuple(c for c in self.comparisons if c.metric == metric)

    def to_json(self) -> dict[str, Any]:
        """{metric: [comparison, ...]} (docs/json-format.md, `statistics`)."""
        metrics = list(dict.fromkeys(c.metric for c in self.comparisons))
        return {m: [c.to_json() for c in self.of(m)] for m in metrics}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "RunStatistics":
        return cls(tuple(Comparison.from_json(m, c) for m, items in d.items() for c in items))


def run_statistics(groups: Iterable[tuple[str | None, Sequence[Result]]],
                   metrics: Sequence[str] = KINDS) -> RunStatistics:
    """The statistics of a run's rows, per metric and group, as the table's means are taken.

    groups: the rows in the groups their means are taken over,
        `fusion.evaluation.compare.summary_groups(results)` (or `[(None, results)]`).
    In a group, the recordings are those with a score on some row; a row scored on less than
    `MIN_COVERAGE` of a recording, or failed there, has no score on it (as in the means). 6-D and
    9-D rows are compared separately (`Comparison.imu`), for every metric: a 9-D row's inclination
    is helped by its magnetometer too. A comparison of one row ranks and tests nothing: it has no
    statistics, and its reason says so.
    """
    groups = [(g, list(members)) for g, members in groups]
    out = []
    for metric in metrics:
        if metric not in KINDS:
            raise ValueError(f"unknown metric {metric!r}; use one of {', '.join(KINDS)}")
        for group, members in groups:
            recordings = {r.dataset for r in members if r.rmse_deg}
            if not recordings:
                continue
            labels = list(dict.fromkeys(r.estimator for r in members))
            for imu, mine in _by_imu(members, labels):
                scores = {lab: {r.dataset: r.rmse_deg[metric] if r.in_means else None for r in members
                                if r.estimator == lab and r.dataset in recordings} for lab in mine}
                if len(mine) == 1:
                    out.append(Comparison(metric, group, imu, tuple(mine), None,
                                          f"one row ({mine[0]}): nothing to compare it with"))
                    continue
                stats = paired_statistics(scores, metric)
                out.append(Comparison(metric, group, imu, tuple(mine), stats,
                                      None if stats else no_statistics_reason(scores)))
    return RunStatistics(tuple(out))


def _by_imu(members: list[Result], labels: list[str]) -> list[tuple[str | None, list[str]]]:
    """The labels by the sensors their scored rows used ("9-D", "6-D", "mixed"), in run order;
    one class (None) when they all used the same."""
    def imu(label: str) -> str:
        mine = [r for r in members if r.estimator == label]
        used = {r.magnetometer for r in ([r for r in mine if r.rmse_deg] or mine)}
        return "9-D" if used == {True} else "6-D" if used == {False} else "mixed"

    classes: dict[str, list[str]] = {}
    for label in labels:
        classes.setdefault(imu(label), []).append(label)
    if len(classes) == 1:
        return [(None, labels)]
    return list(classes.items())


# --- means across datasets ---

def dataset_group(dataset: str) -> str:
    """The folder a recording id belongs to: "ece276a/3" -> "ece276a", "broad/06_..." -> "broad";
    "other" for ids without one (`sim`, files at the top of the data directory)."""
    return dataset.rsplit("/", 1)[0] if "/" in dataset else "other"


def mean_across_datasets(scores: Mapping[str, float]) -> float:
    """The one mean of every table, figure and sweep: of `scores` (recording id -> value), per dataset
    folder (`dataset_group`) the mean over its recordings, then the mean of those, each dataset counted
    once whatever its number of recordings (recordings of different sensors are never pooled); a plain
    mean with one folder. NaN without scores."""
    groups: dict[str, list[float]] = {}
    for rid, value in scores.items():
        groups.setdefault(dataset_group(rid), []).append(float(value))
    if not groups:
        return math.nan
    return math.fsum(math.fsum(v) / len(v) for v in groups.values()) / len(groups)


# --- the table ---

MARK = "*"


def table_column(run: RunStatistics, metric: str) -> tuple[str, dict[tuple[str | None, str], str], list[str]]:
    """What `fusion.evaluation.compare.format_table` adds for `metric`: the interval column's header,
    the cell of each mean row ((group, label) -> "[4.91, 5.80] *"; none when no comparison has
    statistics) and the notes under the table (one line per comparison)."""
    cells: dict[tuple[str | None, str], str] = {}
    notes = []
    for c in run.of(metric):
        where = f" ({c.name})" if c.name else ""
        s = c.statistics
        if s is None:
            notes.append(f"no statistics{where}: {c.reason}")
            continue
        marked = len(s.rows) >= 2
        for r in s.rows:
            interval = "[-, -]" if r.ci_low is None else f"[{r.ci_low:.2f}, {r.ci_high:.2f}]"
            cells[(c.group, r.label)] = interval + (f" {MARK}" if marked and r.not_worse else "  ")
        note = (f"{metric} 95% CI{where}: {s.ci_method} bootstrap interval of the mean over the {len(s.recordings)} "
                "recordings every row scored") + (f" ({dropped_text(s.dropped)})" if s.dropped else "") + (
                f"; scored on at most half of them, not ranked: {', '.join(s.left_out)}" if s.left_out else "")
        if marked:
            note += (f"; {MARK}: not significantly worse than {s.best} (best; Wilcoxon signed-rank, "
                     f"Holm p >= {s.alpha:g})")
        if s.friedman_p is not None:
            note += f"; Friedman p = {s.friedman_p:.2g}"
        notes.append(note)
    return f"{metric} 95% CI", cells, notes
