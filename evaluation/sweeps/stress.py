"""Stress: every estimator under controlled sensor faults, as dose-response curves (`fusion stress`).

    fusion stress --estimators ekf,vqf,madgwick --dataset 'broad/*' --out runs/stress
    fusion stress --estimators ekf --dataset 'ece276a/*' --fault gyro-bias-step=1,2,5 --fault drops

A stress run is a comparison whose recordings are varied: each recording is run clean (as loaded)
and under every fault of `fusion.faults.KINDS` asked for (`--fault KIND=LEVELS`, repeatable; a kind
alone: its five documented severities; none given: every kind at its five), each estimator on each
(recording, fault, severity): its jobs are recording x fault x estimator on the one runner
(`fusion.evaluation.run.runner.run`, `faults`), journalled and resumable as a compare run's. The
faults are applied in the process that runs the job, to the recording it loaded once
(`fusion.faults.apply`, seeded by the recording and the kind: the results do not depend on
`--jobs`). A magnetometer fault is run only on recordings with a magnetometer (and not with
`--mag off`). An estimator that fails or diverges on a cell costs that cell's row only.

What is reported (`stress_summary`, `robustness`), per dataset folder (recordings of different
sensors are never pooled, as in `fusion compare`), per fault and estimator:

- the dose-response: at each severity, the mean over the recordings of the `primary` RMSE (total
  by default) and its 95 % interval (BCa bootstrap over the recordings, as the compare table's:
  `fusion.evaluation.scoring.stats.mean_of_means_interval`), with the clean mean as severity 0. The
  recordings of an estimator's curve are those it was scored on clean and run under the fault (a
  magnetometer fault: those with one), the same at every severity (paired); a cell that failed
  there is counted (`failed`) and left out of that point's mean;
- its robustness: the mildest tested severity at which the mean reaches twice the clean mean (or
  at which a cell failed: a divergence is a breakdown), or "beyond the range" when none does.
  Tested severities only, no interpolation between them: "2 deg/s" means 1 deg/s was below
  twice the clean error and 2 deg/s was not.

The clean rows alone are what `fusion compare` would give (the same jobs): the run's table starts
with them (`fusion.evaluation.compare.format_table`), and its results document's statistics are
theirs.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from fusion.faults import CLEAN, KINDS, NONE, Fault, applies

from ..run.settings import COMPUTED, Option, RunSettings
from ..scoring.metrics import KINDS as METRICS

BREAKDOWN = 2.0  # a fault "breaks" an estimator when its mean error reaches this multiple of its clean error


@dataclass(frozen=True)
class StressSettings(RunSettings):
    """A stress run's settings: `RunSettings`' (those `fusion compare` offers, but --panorama), and
    the faults. faults: `--fault` texts, `KIND=L1,L2,...` (severities in the kind's unit) or `KIND`
    (its documented levels); None: every kind at its documented levels (`plan`)."""

    faults: tuple[str, ...] | None = field(default=None, metadata={"part": COMPUTED, "cli": Option(
        "--fault", "a fault and its severities, KIND=L1,L2,... in the kind's unit, or KIND alone for its five "
        "documented ones; repeatable (default: every kind at its five; the kinds, their units and severities: "
        "below)", kind="append", metavar="KIND[=LEVELS]", commands=("stress",))})

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.faults is not None:
            texts = (self.faults,) if isinstance(self.faults, str) else tuple(str(f) for f in self.faults)
            object.__setattr__(self, "faults", texts)
        plan(self.faults)  # a misspelt kind or a bad level fails here, before any work

    def plan(self) -> list[tuple[str, tuple[float, ...]]]:
        return plan(self.faults)


# The fields of `RunSettings` a stress run has no use for: a panorama per cell, an ablation's per-recording
# figures, the trajectories of every cell.
NOT_OFFERED = ("panorama", "per_recording", "tum")


def parse_fault(text: str) -> tuple[str, tuple[float, ...]]:
    """`gyro-bias-step=1,2,5` -> ("gyro-bias-step", (1.0, 2.0, 5.0)); `drops` -> ("drops", its levels);
    the levels ordered from the mildest (`FaultKind.ordered`), each checked (`fusion.faults.Fault`)."""
    kind, sep, values = (part.strip() for part in str(text).partition("="))
    if kind not in KINDS:
        raise ValueError(f"--fault {text!r}: unknown fault {kind!r}; available: {', '.join(KINDS)}")
    if not sep:
        return kind, KINDS[kind].levels
    try:
        levels = [float(v) for v in values.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--fault {text!r}: expected KIND=L1,L2,... with numbers in {KINDS[kind].unit}, e.g. "
                         f"{kind}={','.join(f'{v:g}' for v in KINDS[kind].levels[:3])}") from None
    if not levels:
        raise ValueError(f"--fault {text!r}: no severity given (or give {kind} alone for its documented ones)")
    if len(set(levels)) != len(levels):
        raise ValueError(f"--fault {text!r}: a severity is repeated")
    for level in levels:
        try:
            Fault(kind, level)
        except ValueError as exc:
            raise ValueError(f"--fault {text!r}: {exc}") from None
    return kind, tuple(KINDS[kind].ordered(levels))


def plan(faults: Sequence[str] | None) -> list[tuple[str, tuple[float, ...]]]:
    """The faults of a run and their severities, in `KINDS` order: those `faults` names (`parse_fault`),
    or every kind at its documented levels."""
    if faults is None:
        return [(name, k.levels) for name, k in KINDS.items()]
    parsed = [parse_fault(text) for text in faults]
    kinds = [kind for kind, _ in parsed]
    twice = next((k for k in kinds if kinds.count(k) > 1), None)
    if twice:
        raise ValueError(f"--fault names {twice} twice; give its severities once, comma-separated")
    if not parsed:
        raise ValueError("--fault: name at least one fault (or leave the option out for every kind)")
    given = dict(parsed)
    return [(name, given[name]) for name in KINDS if name in given]


def variants(the_plan: Sequence[tuple[str, Sequence[float]]], items: Sequence[Any], mag: bool = True
             ) -> list[list[Fault]]:
    """Per recording (a dataset `Source` or a loaded `Recording`), the faults it runs under: clean
    first, then each fault of the plan at each severity, but the magnetometer's on a recording
    without one (as its format says: `fusion.formats.base.Holds`) or with `mag` off."""
    out = []
    for item in items:
        has_mag = mag and _has_magnetometer(item)
        out.append([CLEAN] + [Fault(kind, level) for kind, levels in the_plan for level in levels
                              if has_mag or not KINDS[kind].needs_magnetometer])
    return out


def check_variants(the_plan: Sequence[tuple[str, Sequence[float]]], per_item: Sequence[Sequence[Fault]]) -> None:
    """A note for each fault of the plan that no recording runs under (a magnetometer fault without a
    magnetometer), and a ValueError when that leaves no fault at all."""
    from fusion.selection import note

    run = {f.kind for faults in per_item for f in faults}
    missing = [kind for kind, _ in the_plan if kind not in run]
    if missing and len(missing) == len(the_plan):
        raise ValueError(f"--fault {', '.join(missing)}: no selected recording has a magnetometer (or --mag off), "
                         "and these faults change the magnetometer; nothing to stress")
    for kind in missing:
        note(f"{kind}: not run: no selected recording has a magnetometer (or --mag off)")


def _has_magnetometer(item: Any) -> bool:
    from fusion.types import Recording

    if isinstance(item, Recording):
        return applies("mag-dipole", item)
    from fusion.formats import FORMATS

    fmt = FORMATS.get(item.kind)
    if fmt is None:
        return False
    try:
        return bool(fmt.holds(item).magnetometer)
    except (ValueError, OSError):  # a file that cannot be read: its rows will say so, whatever the fault
        return False


# --- the summary ---

def clean_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of the clean run (fault kind "none"), as results.json holds them."""
    return [r for r in rows if (r.get("fault") or {}).get("kind", NONE) == NONE]


def _group(dataset: str) -> str:
    from ..compare import dataset_group

    return dataset_group(dataset)


def _scored(r: dict[str, Any]) -> bool:
    from ..scoring.metrics import MIN_COVERAGE

    return bool(r.get("rmse_deg")) and (r.get("coverage") is None or r["coverage"] >= MIN_COVERAGE)


def stress_summary(rows: Sequence[dict[str, Any]], metric: str = "total", intervals: bool = True) -> dict[str, Any]:
    """The dose-response of a stress run's rows (results.json rows, each with its `fault`; module
    docstring). Returns results.json's `stress`: {"metric", "datasets": [{"dataset", "recordings",
    "faults": [{"kind", "unit", "sensor", "model", "lower_is_worse", "severities", "estimators":
    [{"estimator", "recordings", "clean": point, "points": [point per severity]}]}]}]}, a point
    being {"severity", "mean_deg", "ci95_deg" ([low, high] or null), "scored", "failed"}; severities
    from the mildest. `intervals` False leaves the intervals out (null)."""
    if metric not in METRICS:
        raise ValueError(f"unknown metric {metric!r}; use one of {', '.join(METRICS)}")
    groups = list(dict.fromkeys(_group(r["dataset"]) for r in rows))
    labels = list(dict.fromkeys(r["estimator"] for r in rows))
    kinds = [k for k in KINDS if any((r.get("fault") or {}).get("kind") == k for r in rows)]
    out = []
    for g in groups:
        mine = [r for r in rows if _group(r["dataset"]) == g]
        cell: dict[tuple[str, str, str, float], dict[str, Any]] = {}
        for r in mine:
            f = r.get("fault") or {"kind": NONE, "severity": 0.0}
            cell[(r["dataset"], r["estimator"], f["kind"], float(f["severity"]))] = r
        recordings = list(dict.fromkeys(r["dataset"] for r in mine))
        faults = []
        for kind in kinds:
            k = KINDS[kind]
            levels = k.ordered(sorted({sev for (_, _, fk, sev) in cell if fk == kind}))
            if not levels:
                continue
            ests = []
            for label in labels:
                # the recordings this estimator was scored on clean and run under this fault (a magnetometer
                # fault: those with one)
                run_under = {d for (d, lab, fk, _) in cell if lab == label and fk == kind}
                base = [d for d in recordings if d in run_under and (d, label, NONE, 0.0) in cell
                        and _scored(cell[(d, label, NONE, 0.0)])]
                if not run_under:
                    continue
                ests.append({"estimator": label, "recordings": len(base),
                             "clean": _point(0.0, [cell[(d, label, NONE, 0.0)] for d in base], metric, intervals),
                             "points": [_point(level, [cell.get((d, label, kind, level)) for d in base], metric,
                                               intervals) for level in levels]})
            faults.append({"kind": kind, "unit": k.unit, "sensor": k.sensor, "model": k.model,
                           "lower_is_worse": k.lower_is_worse, "severities": list(levels), "estimators": ests})
        out.append({"dataset": g, "recordings": len(recordings), "faults": faults})
    return {"metric": metric, "datasets": out}


def _point(severity: float, rows: list[dict[str, Any] | None], metric: str, intervals: bool) -> dict[str, Any]:
    """One point of a curve: the rows of its recordings (None: no row, e.g. a run stopped early)."""
    from ..scoring.stats import MIN_RECORDINGS, mean_of_means_interval

    values = [float(r["rmse_deg"][metric]) for r in rows if r is not None and _scored(r)]
    failed = sum(1 for r in rows if r is None or not _scored(r))
    ci = None
    if intervals and len(values) >= MIN_RECORDINGS:
        low, high = mean_of_means_interval([values])
        ci = None if low is None or high is None else [low, high]
    return {"severity": severity, "mean_deg": float(np.mean(values)) if values else None, "ci95_deg": ci,
            "scored": len(values), "failed": failed}


def robustness(summary: dict[str, Any]) -> dict[str, Any]:
    """results.json's `robustness`: per dataset folder, estimator and fault, the mildest severity at
    which the mean error reaches `BREAKDOWN` times the clean mean or a cell failed (`breaks_at`,
    null: beyond the tested range), with the clean mean, the mean there (or at the worst severity)
    and their ratio. {"metric", "criterion", "entries": [{"dataset", "estimator", "fault", "unit",
    "clean_deg", "breaks_at", "at_deg", "ratio", "failed", "worst"}]}."""
    entries = []
    for d in summary["datasets"]:
        for f in d["faults"]:
            for e in f["estimators"]:
                clean = e["clean"]["mean_deg"]
                hit = None
                for p in e["points"]:
                    if p["failed"] or (clean is not None and p["mean_deg"] is not None
                                       and p["mean_deg"] >= BREAKDOWN * clean):
                        hit = p
                        break
                shown = hit or (e["points"][-1] if e["points"] else None)
                at = shown["mean_deg"] if shown else None
                entries.append({"dataset": d["dataset"], "estimator": e["estimator"], "fault": f["kind"],
                                "unit": f["unit"], "clean_deg": clean,
                                "breaks_at": hit["severity"] if hit else None,
                                "at_deg": at, "ratio": at / clean if at is not None and clean else None,
                                "failed": hit["failed"] if hit else 0,
                                "worst": f["severities"][-1] if f["severities"] else None})
    return {"metric": summary["metric"], "criterion": (
        f"the mildest tested severity at which the mean {summary['metric']} RMSE over the recordings reaches "
        f"{BREAKDOWN:g} times the clean mean, or a cell fails; none: beyond the tested range ('> the worst "
        "tested')"), "entries": entries}


# --- text ---

def _sev(v: float) -> str:
    return f"{v:g}"


def format_stress(summary: dict[str, Any], robust: dict[str, Any]) -> str:
    """The dose-response tables and the robustness summary, as `fusion stress` prints them under the
    clean table."""
    metric = summary["metric"]
    lines = []
    several = len(summary["datasets"]) > 1
    for d in summary["datasets"]:
        where = f" on {d['dataset']}" if several else ""
        lines += [f"Dose-response{where}: mean {metric} RMSE (deg) over the recordings at each severity "
                  f"(clean: no fault; its 95% intervals in results.json and the report; "
                  f"! = twice the clean mean or more, xN = N cells failed)"]
        for f in d["faults"]:
            head = [f"{f['kind']} ({f['unit']})", "clean", *(_sev(v) for v in f["severities"])]
            body = []
            for e in f["estimators"]:
                clean = e["clean"]["mean_deg"]
                cells = [_cell(e["clean"], None)] + [_cell(p, clean) for p in e["points"]]
                body.append([e["estimator"], *cells])
            lines += [""] + _columns(head, body)
            lines.append(f"  {f['model']}")
        lines += ["", _robust_title(metric, where)]
        lines += _robust_table([x for x in robust["entries"] if x["dataset"] == d["dataset"]],
                               [f["kind"] for f in d["faults"]])
    return "\n".join(lines)


def _cell(p: dict[str, Any], clean: float | None) -> str:
    text = "-" if p["mean_deg"] is None else f"{p['mean_deg']:.2f}"
    if clean and p["mean_deg"] is not None and p["mean_deg"] >= BREAKDOWN * clean:
        text += "!"
    if p["failed"]:
        text += f" x{p['failed']}"
    return text


def _robust_title(metric: str, where: str) -> str:
    return (f"Robustness{where}: the mildest tested severity at which the mean {metric} RMSE reaches "
            f"{BREAKDOWN:g}x the clean mean (or a cell fails); '>' = beyond the tested range (the worst severity "
            "shown)")


def robust_cell(x: dict[str, Any], unit: bool = False) -> str:
    """A robustness entry as text: `2`, `> 10` (beyond the range), `2 (fails)`; with `unit`, `2 deg/s`."""
    u = f" {x['unit']}" if unit else ""
    if x["breaks_at"] is None:
        return f"> {_sev(x['worst'])}{u}" if x["worst"] is not None else "-"
    return f"{_sev(x['breaks_at'])}{u}" + (" (fails)" if x["failed"] else "")


def robust_rows(entries: list[dict[str, Any]], kinds: list[str]) -> tuple[list[str], list[list[str]]]:
    """The robustness summary as a table, a fault per row (with its unit) and an estimator per
    column, the clean errors (deg) first: (header, rows)."""
    labels = list(dict.fromkeys(x["estimator"] for x in entries))
    by = {(x["estimator"], x["fault"]): x for x in entries}
    clean = {label: next((x["clean_deg"] for x in entries if x["estimator"] == label and x["clean_deg"] is not None),
                         None) for label in labels}
    body = [["clean error (deg)", *("-" if clean[label] is None else f"{clean[label]:.2f}" for label in labels)]]
    for kind in kinds:
        unit = next((x["unit"] for x in entries if x["fault"] == kind), "")
        body.append([f"{kind} ({unit})", *(robust_cell(by[(label, kind)]) if (label, kind) in by else "-"
                                           for label in labels)])
    return ["fault (unit)", *labels], body


def _robust_table(entries: list[dict[str, Any]], kinds: list[str]) -> list[str]:
    return _columns(*robust_rows(entries, kinds))


def _columns(head: list[str], body: list[list[str]], left: int = 1) -> list[str]:
    """Aligned columns: the first `left` to the left, the others (numbers) to the right."""
    widths = [max(len(row[i]) for row in [head, *body]) for i in range(len(head))]

    def line(row: list[str]) -> str:
        return "  ".join(c.ljust(w) if i < left else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))).rstrip()

    return [line(head), line(["-" * w for w in widths]), *(line(r) for r in body)]


def fault_table() -> str:
    """Every kind: name, unit, documented severities, sensor, model, reference (README, `--help`)."""
    head = ["fault", "unit", "severities", "sensor", "model"]
    body = [[k.name, k.unit, ", ".join(_sev(v) for v in k.levels), k.sensor, k.model] for k in KINDS.values()]
    return "\n".join(_columns(head, body, left=len(head)))

