"""Ablations: one estimator over a grid of parameter values, or a named list of settings.

    fusion ablate --estimator ukf --param R=1e-4,1e-3,1e-2 --param sigma=kraft,julier --out DIR
    fusion ablate --preset sigma --out DIR

An ablation is a comparison whose estimator list is generated: `grid_specs` turns the
`--param` lists into the Cartesian product of specs (the first parameter varies slowest),
each labelled exactly as `fusion compare --estimators` would label it, so an ablation with
one value gives the same rows as `compare` with that parameter. The report then reads the
parameter values back from the labels (`fusion.evaluation.report.plots.label_params`).

`PRESETS` holds the course reports' questions as spec lists (data only; edit freely), and
`broad-sweep`, BROAD's parameter study (Laidig et al. 2021, "BROAD - a benchmark for robust
inertial orientation estimation", Data 6(7): 72): a grid over a filter's main parameters, run on
every trial. `sweep_summary` reads any ablation's rows as BROAD does: the best common setting
("TAGP", trial-agnostic good parameters: the one setting with the lowest mean error over all
recordings) and each recording's own best setting (the per-trial minimum).
"""
from __future__ import annotations

import itertools
import math
from typing import Any, Sequence

from fusion.estimators.params import EstimatorSpec, parse_specs

# The course reports' questions. Each is a list of spec texts as `--estimators` takes them.
PRESETS: dict[str, list[str]] = {
    # UKF vs plain integration of the gyro
    "ukf-vs-dr": ["dr", "ukf"],
    # sigma-point schemes
    "sigma": ["ukf:sigma=kraft", "ukf:sigma=julier", "ukf:sigma=merwe"],
    # with and without the accelerometer update
    "accel-update": ["ukf:acc=false", "ukf:acc=true"],
    # preconditioned projected gradient (geodesic or normalising step) vs Gauss-Newton, on one cost
    "smoother-solvers": ["gd", "gd:update=normalise", "gn"],
    # the weight of the motion term (seed weighting: accelerometer term weight 1)
    "motion-weight": ["gn:weighting=scalar,wm=1", "gn:weighting=scalar,wm=3", "gn:weighting=scalar,wm=10",
                      "gn:weighting=scalar,wm=30"],
}

# BROAD's sweep for `ekf` (`EKFParams`): Q, the gyro noise density in rad^2/s; R, the
# accelerometer noise density in g^2 s; tauc, the correlation time of the external acceleration
# in s. 3 x 5 x 2 = 30 settings; the defaults (Q=3e-4, R=3e-5, tauc=0.1) are among them.
BROAD_SWEEP: dict[str, list[str]] = {
    "Q": ["1e-4", "3e-4", "1e-3"],
    "R": ["1e-5", "3e-5", "1e-4", "3e-4", "1e-3"],
    "tauc": ["0.1", "0.5"],
}
PRESETS["broad-sweep"] = ["ekf:" + ",".join(f"{k}={v}" for k, v in zip(BROAD_SWEEP, combo))
                          for combo in itertools.product(*BROAD_SWEEP.values())]


def preset_specs(name: str) -> list[EstimatorSpec]:
    """The specs of a preset, checked against the registry (a clear error for a preset
    naming an estimator this installation does not have)."""
    from fusion import estimators
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; available: {', '.join(PRESETS)}")
    specs = [spec for text in PRESETS[name] for spec in parse_specs(text)]
    missing = list(dict.fromkeys(s.name for s in specs if s.name not in estimators.ESTIMATORS))
    if missing:
        raise ValueError(f"preset {name!r} needs estimator(s) {', '.join(missing)}, not registered here "
                         f"(available: {', '.join(estimators.ESTIMATORS)})")
    for spec in specs:
        try:
            estimators.build(spec)
        except ValueError as exc:
            raise ValueError(f"preset {name!r}: {exc}") from None
    return specs


def parse_param(text: str) -> tuple[str, list[str]]:
    """`R=1e-4,1e-3` -> ("R", ["1e-4", "1e-3"])."""
    key, sep, values = text.partition("=")
    items = [v.strip() for v in values.split(",") if v.strip()]
    if not sep or not key.strip() or not items:
        raise ValueError(f"--param {text!r}: expected NAME=VALUE[,VALUE...], e.g. R=1e-4,1e-3")
    if len(set(items)) != len(items):
        raise ValueError(f"--param {text!r}: a value is repeated")
    return key.strip(), items


def grid_specs(estimator: str, params: Sequence[tuple[str, Sequence[str]]]) -> list[EstimatorSpec]:
    """Every combination of the parameter values, as specs for `estimator` (a spec text,
    possibly with fixed overrides: `ukf:Q=1e-5`). The first parameter varies slowest."""
    (base,) = _one_spec(estimator)
    keys = [k for k, _ in params]
    if len(set(keys)) != len(keys):
        raise ValueError(f"--param names a parameter twice: {', '.join(keys)}")
    fixed = [k for k, _ in base.overrides if k in keys]
    if fixed:
        raise ValueError(f"parameter {fixed[0]!r} is both fixed in --estimator and swept by --param")
    return [EstimatorSpec(base.name, base.overrides + tuple(zip(keys, combo)))
            for combo in itertools.product(*(values for _, values in params))]


def _one_spec(text: str) -> list[EstimatorSpec]:
    specs = parse_specs(text)
    if len(specs) != 1:
        raise ValueError(f"--estimator {text!r}: name one estimator (use --preset or compare for several)")
    return specs


def sweep_summary(rows: Sequence[dict[str, Any]], kind: str = "total",
                  groups: dict[str, Sequence[str]] | None = None) -> dict[str, Any] | None:
    """BROAD's reading of an ablation (rows as in results.json; rows without truth or with low
    coverage left out, as in the means): the best common setting, the one with the lowest mean
    `kind` RMSE over the recordings (over those every setting was scored on; across datasets the
    table's mean, `fusion.evaluation.scoring.stats.mean_across_datasets`), and per recording its own
    best setting. None with fewer than two settings or no scored recording.

    Returns {"kind", "settings", "recordings", "best_common": {"estimator", "mean_rmse_deg"},
    "per_recording": [{"dataset", "best_estimator", "best_rmse_deg", "common_rmse_deg"}],
    "mean_best_per_recording_deg"}: the last is the mean of the per-recording minima, the
    bound a setting tuned per trial would reach.

    groups: recording -> the groups it belongs to (BROAD's `trials.json`:
    `fusion.formats.broad.trial_groups`); with it, "groups" lists each group's best common
    setting over its recordings (BROAD's TAGP per group: {"group", "recordings",
    "best_estimator", "mean_rmse_deg"}, in the order the groups first appear) and
    "trial_groups" keeps the mapping, so that a re-render computes the same. With recordings of two
    dataset folders or more, "datasets" gives each its own best common setting, its mean, and the
    mean there of the best common setting over all (`_per_dataset`).
    """
    from ..scoring.stats import mean_across_datasets

    labels = list(dict.fromkeys(r["estimator"] for r in rows))
    err: dict[tuple[str, str], float] = {}
    for r in rows:
        coverage = r.get("coverage")
        if r.get("rmse_deg") and (coverage is None or coverage >= _min_coverage()):
            err[(r["dataset"], r["estimator"])] = float(r["rmse_deg"][kind])
    datasets = [d for d in dict.fromkeys(r["dataset"] for r in rows) if all((d, lab) in err for lab in labels)]
    if len(labels) < 2 or not datasets:
        return None
    means = {lab: mean_across_datasets({d: err[(d, lab)] for d in datasets}) for lab in labels}  # the table's mean
    best = min(labels, key=lambda lab: means[lab])  # ties: the first listed
    per = []
    for d in datasets:
        own = min(labels, key=lambda lab: err[(d, lab)])
        per.append({"dataset": d, "best_estimator": own, "best_rmse_deg": err[(d, own)],
                    "common_rmse_deg": err[(d, best)]})
    out = {"kind": kind, "settings": len(labels), "recordings": len(datasets),
           "best_common": {"estimator": best, "mean_rmse_deg": means[best]},
           "per_recording": per,
           "mean_best_per_recording_deg": math.fsum(p["best_rmse_deg"] for p in per) / len(per)}
    if groups:
        members: dict[str, list[str]] = {}
        for d in datasets:
            for g in groups.get(d, ()):
                members.setdefault(g, []).append(d)
        out["groups"] = []
        for g, ds in members.items():
            group_means = {lab: math.fsum(err[(d, lab)] for d in ds) / len(ds) for lab in labels}
            top = min(labels, key=lambda lab: group_means[lab])
            out["groups"].append({"group": g, "recordings": len(ds), "best_estimator": top,
                                  "mean_rmse_deg": group_means[top]})
        out["trial_groups"] = {d: list(groups[d]) for d in datasets if d in groups}
    folders = _per_dataset(err, labels, datasets, best)
    if folders:
        out["datasets"] = folders
    return out


def _per_dataset(err: dict[tuple[str, str], float], labels: list[str], datasets: list[str],
                 best: str) -> list[dict[str, Any]]:
    """With recordings of two dataset folders or more (`fusion.evaluation.compare.dataset_group`):
    per folder, in run order, its own best common setting and mean, and the mean there of the best
    common setting over all recordings ("common_rmse_deg"): does a setting chosen on all the data
    hold on each dataset. [] with one folder."""
    from ..scoring.stats import dataset_group

    members: dict[str, list[str]] = {}
    for d in datasets:
        members.setdefault(dataset_group(d), []).append(d)
    if len(members) < 2:
        return []
    out = []
    for folder, ds in members.items():
        means = {lab: math.fsum(err[(d, lab)] for d in ds) / len(ds) for lab in labels}
        top = min(labels, key=lambda lab: means[lab])
        out.append({"dataset": folder, "recordings": len(ds), "best_estimator": top, "mean_rmse_deg": means[top],
                    "common_rmse_deg": means[best]})
    return out


def _min_coverage() -> float:
    from ..scoring.metrics import MIN_COVERAGE
    return MIN_COVERAGE


def format_sweep(summary: dict[str, Any]) -> str:
    """The lines `fusion ablate` prints under its table."""
    best = summary["best_common"]
    lines = [f"Sweep ({summary['settings']} settings x {summary['recordings']} recordings, {summary['kind']} RMSE in degrees)",
             f"best common setting (lowest mean over all recordings): {best['estimator']}  "
             f"mean {best['mean_rmse_deg']:.2f}",
             f"each recording's own best setting: mean {summary['mean_best_per_recording_deg']:.2f}"]
    width = max(len("dataset"), *(len(p["dataset"]) for p in summary["per_recording"]))
    head = f"{'dataset':<{width}}  {'own best':>8}  {'common':>6}  own best setting"
    lines += [head, "-" * len(head)]
    lines += [f"{p['dataset']:<{width}}  {p['best_rmse_deg']:8.2f}  {p['common_rmse_deg']:6.2f}  {p['best_estimator']}"
              for p in summary["per_recording"]]
    if summary.get("groups"):
        width = max(len("group"), *(len(g["group"]) for g in summary["groups"]))
        head = f"{'group':<{width}}  {'trials':>6}  {'mean':>6}  best common setting of the group (BROAD's trials.json)"
        lines += ["", head, "-" * len(head)]
        lines += [f"{g['group']:<{width}}  {g['recordings']:6d}  {g['mean_rmse_deg']:6.2f}  {g['best_estimator']}"
                  for g in summary["groups"]]
    if summary.get("datasets"):
        width = max(len("dataset"), *(len(g["dataset"]) for g in summary["datasets"]))
        head = (f"{'dataset':<{width}}  {'recs':>4}  {'own best':>8}  {'common':>6}  best common setting of the dataset "
                "(common: the best common setting over all recordings, on this dataset)")
        lines += ["", head, "-" * len(head)]
        lines += [f"{g['dataset']:<{width}}  {g['recordings']:4d}  {g['mean_rmse_deg']:8.2f}  {g['common_rmse_deg']:6.2f}"
                  f"  {g['best_estimator']}" for g in summary["datasets"]]
    return "\n".join(lines)
