"""The per-recording time series a report's figures are drawn from, and their `.npz` files.

An output folder of `fusion compare --out DIR` holds one `series/NNN.npz` per recording, so
that `fusion report DIR` can draw the figures again without running any estimator. Arrays
(as `load` returns them):

    id            ()       str, the dataset id
    imu_t         (N,)     float64 s, the IMU time stamps every estimate lives on
    gyr_valid     (N,)     bool, False where the gyro was marked unusable
    truth_t       (K,)     float64 s, the truth's time stamps (K = 0 without ground truth)
    truth_quat    (K, 4)   quat_wxyz R_world_body of the truth, NaN rows in tracking gaps; with
                            `--align`, the truth mapped into our frames (`A R_truth B`,
                            `fusion.evaluation.scoring.align`), what the estimates were scored against
    labels        (E,)     str, estimator specs as in results.json
    causal        (E,)     bool, False for smoothers
    quat          (E, N, 4) quat_wxyz R_world_body of each estimator
    err_deg       (E, 3, N) total/inclination/heading error, deg; NaN where not
                            scored (outside the truth span, in gaps; all NaN without truth)
    loss_<e>      (K_e,)   float64 cost per iteration of estimator e, where it reports one
    belief_<e>_*           what filter e believed, where it reports an error covariance
                            (`fusion.evaluation.scoring.consistency.Belief`): `_err` (N, 3) attitude
                            error against the truth, rad, body frame (NaN without truth);
                            `_sigma` (N, 3) sqrt(P_ii), rad; `_nees`, `_nis` (N,); `_updated`
                            (N,) bool; where recorded `_rest`, `_guarded` (N,) bool, `_bias`
                            (N, 3) rad/s and `_scale_llr` (N,), the scale test's ln L
    flag_<e>_<name>        a per-sample flag of estimator e (`flags_of`: its (N,) bool
                            diagnostics, e.g. `mag_used`, VQF's `rest_detected`, Fusion's
                            `accelerometer_ignored`), where it is on at least once: np.packbits
                            of the (N,) bool array (N/8 bytes)
    event_names   (M,)     str, the recording's events (`events_of`: rest, gyro freeze, gyro
                            invalid, no truth, magnetic disturbance, movement, ...), one per span
    event_spans_s (M, 2)   float64 s after the first IMU sample, each event's start and stop
                            (both absent in a file written before events were kept)

The file is a compressed npz (`np.savez_compressed`) under the names above. A file written
with `encoding` = "bit-deltas" (this version) stores each float array as the differences, along
time, of its values' bit patterns (an integer array of the same shape: consecutive samples
differ in their low bits only, which deflate packs tightly; `np.cumsum` along the time axis and
a view give the values back exactly):

    imu_t, truth_t                float64 (int64 deltas along axis 0): exact
    belief_<e>_err, _sigma, _nees, _nis, _bias, _scale_llr
                                  float32 (int32 deltas along axis 0): exact, as before
    truth_quat (axis 0), quat (axis 1), err_deg (axis 2)
                                  float16 (int16 deltas): what the figures need (3 significant
                                  digits, 0.03 deg on an orientation, finer than a pixel)

`load` returns float64 times and float32 arrays. A file without `encoding` (written before this
version: plain float32/float64 arrays) reads as it was written. The scores in results.json come
from the float64 computation, and the consistency table from the float32 beliefs, as before.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.checks import check_recording, runs

from ..scoring import consistency
from ..scoring.metrics import KINDS


@dataclass(frozen=True, eq=False)
class RecordingSeries:
    """One recording's plot data (see the module docstring for shapes and units)."""

    id: str
    imu_t: np.ndarray
    gyr_valid: np.ndarray
    truth_t: np.ndarray
    truth_quat: np.ndarray
    labels: list[str]
    causal: list[bool]
    quat: np.ndarray
    err_deg: np.ndarray
    losses: dict[int, np.ndarray] = field(default_factory=dict)
    beliefs: dict[int, consistency.Belief] = field(default_factory=dict)
    flags: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)  # estimator -> name -> (N,) bool
    events: dict[str, list[tuple[float, float]]] | None = None  # name -> spans, s after imu_t[0]; None: not kept

    @property
    def has_truth(self) -> bool:
        return len(self.truth_t) > 0


def recording_part(rec, truth_at_imu=None) -> dict[str, np.ndarray]:
    """The arrays of one recording that its series needs besides the estimates: `id`, `imu_t`,
    `gyr_valid`, `truth_t`, `truth_quat` (a `fusion.types.Recording`, its truth already mapped
    into our frames with `--align`), and `truth_at_imu` (N, 4) float64, the truth slerped onto the
    IMU stamps (what the estimates are scored against; NaN rows where there is none), when
    `truth_at_imu` (a callable giving it) is given."""
    truth = rec.truth
    part = dict(id=np.array(rec.id), imu_t=np.asarray(rec.imu.t), gyr_valid=np.asarray(rec.imu.gyr_valid, bool),
                truth_t=np.asarray(truth.t) if truth is not None else np.empty(0),
                truth_quat=np.asarray(truth.quat_wxyz) if truth is not None else np.empty((0, 4)))
    if truth_at_imu is not None:
        part["truth_at_imu"] = np.asarray(truth_at_imu(), dtype=float)
    part.update(_event_arrays(events_of(rec)))
    return part


def events_of(rec) -> dict[str, list[tuple[float, float]]]:
    """The recording's events as (start, stop) spans, s since its first IMU sample, by name (only
    those that occur): `fusion.checks.check_recording`'s rests, gyro freezes, samples beyond the
    gyro's range, time-stamp gaps, truth gaps and magnetic disturbances; the samples the estimators
    were told the gyro is invalid (`gyr_valid`); BROAD's movement phases (`Recording.movement`)."""
    check = check_recording(rec)
    t = np.asarray(rec.imu.t, float) - float(rec.imu.t[0])

    def spans(intervals) -> list[tuple[float, float]]:
        return [(float(iv.start_s), float(iv.stop_s)) for iv in intervals]

    def mask_spans(mask: np.ndarray) -> list[tuple[float, float]]:
        return [(float(t[a]), float(t[min(b, len(t) - 1)])) for a, b in runs(mask)]

    out = {"rest": spans(r.interval for r in check.rests),
           "gyro freeze": spans(f.interval for f in check.freezes),
           "gyro invalid": mask_spans(~np.asarray(rec.imu.gyr_valid, bool)),
           "gyro beyond range": spans(check.range.gyro_beyond_range()) if check.range is not None else [],
           "time-stamp gap": spans(check.timing.gaps),
           "no truth": spans(check.vicon.gaps) if check.vicon is not None else [],
           "magnetic disturbance": spans(check.magnetometer.disturbed) if check.magnetometer is not None else [],
           "movement": mask_spans(rec.movement) if rec.movement is not None else []}
    return {name: v for name, v in out.items() if v}


# diagnostics a `consistency.Belief` already holds (its `rest` and `guarded`): not repeated as flags
_IN_BELIEF = ("at_rest", "bias_guarded")


def flags_of(trajectory) -> dict[str, np.ndarray]:
    """The per-sample flags of an estimate that are on at least once, by name, (N,) bool: every
    (N,) bool array among its diagnostics (`fusion.types.Trajectory`) but those its `Belief` holds
    (a filter with a covariance: `at_rest`, `bias_guarded`), and the outcome of a filter's scale
    test (`fusion.estimators.filters.ekf`, "Scale test"): `scale_error_accepted` or `gyro_calibrated_accepted`,
    on from the sample where Wald's test decided (its `scale_llr`, frozen from then on, and
    `scale_decision`, 1 or -1)."""
    d = trajectory.diagnostics or {}
    n = len(trajectory)
    skip = _IN_BELIEF if consistency.has_covariance(trajectory) else ()
    out = {}
    for key, value in d.items():
        if key not in skip and isinstance(value, np.ndarray) and value.dtype == bool and value.shape == (n,) \
                and value.any():
            out[key] = value.copy()
    llr, decision = d.get("scale_llr"), d.get("scale_decision")
    if decision in (1, -1) and llr is not None and np.shape(llr) == (n,) and n:
        llr = np.asarray(llr, float)
        changed = np.flatnonzero(llr[1:] != llr[:-1])  # frozen once decided: the last change is the decision
        on = np.zeros(n, bool)
        on[changed[-1] + 1 if len(changed) else 0:] = True
        out["scale_error_accepted" if decision == 1 else "gyro_calibrated_accepted"] = on
    return out


def job_part(trajectory, job_score, truth_at_imu) -> dict[str, np.ndarray]:
    """What one estimate adds to its recording's series: `quat` (N, 4) float32, `err_deg` (3, N)
    float32, `loss` where the estimator reports one, `belief_*` (without the estimator's index)
    where it reports a covariance, `flag_<name>` (N,) bool for each of its flags (`flags_of`); and `quat_wxyz` (N, 4) float64, the estimate itself (exported as
    a TUM file, not kept in the series).

    job_score: its `fusion.evaluation.scoring.metrics.Score` (None without truth); truth_at_imu: a callable
    giving the truth slerped onto the IMU stamps (`consistency.truth_on`), called only for a filter
    with a covariance, or None without truth.
    """
    n = len(trajectory)
    err = np.full((len(KINDS), n), np.nan, np.float32)
    if job_score is not None:
        for k, kind in enumerate(KINDS):
            err[k, job_score.mask] = np.degrees(job_score.errors_rad[kind])
    part = {"quat": np.asarray(trajectory.quat_wxyz, np.float32), "err_deg": err,
            "quat_wxyz": np.asarray(trajectory.quat_wxyz, dtype=float)}  # full precision, for the TUM export
    loss = trajectory.diagnostics.get("loss") if trajectory.diagnostics else None
    if loss is not None:
        part["loss"] = np.asarray(loss, dtype=float).ravel()
    if consistency.has_covariance(trajectory):
        belief = consistency.from_trajectory(trajectory, truth_at_imu() if truth_at_imu else None)
        for key, attr, dtype in _BELIEF_ARRAYS:
            value = getattr(belief, attr)
            if value is not None:
                part[f"belief_{key}"] = np.asarray(value, dtype=dtype)
    part.update({f"flag_{name}": flag for name, flag in flags_of(trajectory).items()})
    return part


def from_results(rec, results: list, causal: dict[str, bool] | None = None) -> RecordingSeries:
    """One recording's series from its recording (`fusion.types.Recording`, with `--align` its
    aligned truth) and whole results of it (`fusion.evaluation.run.job.run_one`,
    `fusion.evaluation.compare.compare`: with trajectories); causal: per label, False for
    smoothers (default: all causal)."""
    truth_at_imu = (lambda: consistency.truth_on(rec.truth, rec.imu.t)) if rec.truth is not None else None
    for r in results:
        if r.trajectory is None:
            raise ValueError(f"{rec.id}: result {r.estimator!r} has no trajectory to plot")
    labels = [r.estimator for r in results]
    return assemble(recording_part(rec), labels, [(causal or {}).get(label, True) for label in labels],
                    [job_part(r.trajectory, r.score, truth_at_imu) for r in results])


def assemble(recording: dict[str, np.ndarray], labels: list[str], causal: list[bool],
             parts: list[dict[str, np.ndarray]]) -> RecordingSeries:
    """One recording's series from its `recording_part` and one `job_part` per estimator (in the
    order of `labels`)."""
    n = len(recording["imu_t"])
    quat = np.empty((len(parts), n, 4), np.float32)
    err = np.empty((len(parts), len(KINDS), n), np.float32)
    losses: dict[int, np.ndarray] = {}
    beliefs: dict[int, consistency.Belief] = {}
    flags: dict[int, dict[str, np.ndarray]] = {}
    for e, part in enumerate(parts):
        quat[e], err[e] = part["quat"], part["err_deg"]
        if "loss" in part:
            losses[e] = part["loss"]
        mine = {k[5:]: np.asarray(v, bool) for k, v in part.items() if k.startswith("flag_")}
        if mine:
            flags[e] = mine
        if "belief_err" in part:
            beliefs[e] = consistency.Belief(**{attr: (part[f"belief_{key}"].astype(float if dtype is np.float32 else bool)
                                                      if f"belief_{key}" in part else None)
                                               for key, attr, dtype in _BELIEF_ARRAYS})
    return RecordingSeries(str(recording["id"]), recording["imu_t"], recording["gyr_valid"], recording["truth_t"],
                           recording["truth_quat"], list(labels), list(causal), quat, err, losses, beliefs, flags,
                           _events(recording.get("event_names"), recording.get("event_spans_s")))


def _event_arrays(events: dict[str, list[tuple[float, float]]]) -> dict[str, np.ndarray]:
    """The `event_names` (M,) and `event_spans_s` (M, 2) arrays of an events' dict (`_events` reads
    them back)."""
    flat = [(name, span) for name, spans in events.items() for span in spans]
    return {"event_names": np.array([name for name, _ in flat], dtype=str),
            "event_spans_s": np.array([span for _, span in flat], dtype=float).reshape(-1, 2)}


def _events(names: np.ndarray | None, spans: np.ndarray | None) -> dict[str, list[tuple[float, float]]] | None:
    """The events' dict from their `event_names` and `event_spans_s` arrays (None: not kept)."""
    if names is None or spans is None:
        return None
    out: dict[str, list[tuple[float, float]]] = {}
    for name, (a, b) in zip(names, np.asarray(spans, float).reshape(-1, 2)):
        out.setdefault(str(name), []).append((float(a), float(b)))
    return out


_BELIEF_ARRAYS = (("err", "err_rad", np.float32), ("sigma", "sigma_rad", np.float32), ("nees", "nees", np.float32),
                  ("nis", "nis", np.float32), ("updated", "updated", bool), ("rest", "rest", bool),
                  ("guarded", "guarded", bool), ("bias", "bias_rad_s", np.float32),
                  ("scale_llr", "scale_llr", np.float32))


def save(path: Path, s: RecordingSeries) -> None:
    """Write one recording's series as a compressed npz (module docstring for the encoding)."""
    arrays: dict[str, np.ndarray] = dict(id=np.array(s.id), encoding=np.array(ENCODING),
                                         gyr_valid=np.asarray(s.gyr_valid, bool), labels=np.array(s.labels, dtype=str),
                                         causal=np.array(s.causal, bool))
    for name, values in (("imu_t", s.imu_t), ("truth_t", s.truth_t), ("truth_quat", s.truth_quat), ("quat", s.quat),
                         ("err_deg", s.err_deg)):
        arrays[name] = _bit_deltas(values, *_ENCODED[name])
    arrays.update({f"loss_{e}": np.asarray(v, float) for e, v in s.losses.items()})
    for e, belief in s.beliefs.items():
        for key, attr, dtype in _BELIEF_ARRAYS:
            value = getattr(belief, attr)
            if value is not None:
                arrays[f"belief_{e}_{key}"] = (_bit_deltas(value, np.float32, 0) if dtype is np.float32
                                               else np.asarray(value, dtype=dtype))
    for e, flags in s.flags.items():
        arrays.update({f"flag_{e}_{name}": np.packbits(np.asarray(flag, bool)) for name, flag in flags.items()})
    if s.events is not None:
        arrays.update(_event_arrays(s.events))
    np.savez_compressed(path, **arrays)


def load(path: Path) -> RecordingSeries:
    """One recording's series as `save` wrote it, or as an older version wrote it (plain arrays)."""
    with np.load(path, allow_pickle=False) as z:
        encoded = "encoding" in z.files
        if encoded and str(z["encoding"]) != ENCODING:
            raise ValueError(f"{path}: series encoding {str(z['encoding'])!r} is not one this version reads "
                             f"({ENCODING!r}); write it again with this version")

        def get(name: str, dtype: type = np.float32, axis: int = 0) -> np.ndarray:
            if not encoded:
                return z[name]
            kind, axis = _ENCODED.get(name, (dtype, axis))
            return _values(z[name], kind, axis)

        losses = {int(k[5:]): z[k] for k in z.files if k.startswith("loss_")}
        labels = [str(x) for x in z["labels"]]
        beliefs = {}
        for e in sorted({int(k.split("_")[1]) for k in z.files if k.startswith("belief_")}):
            fields = {attr: ((get(f"belief_{e}_{key}").astype(float) if dtype is np.float32
                              else z[f"belief_{e}_{key}"].astype(bool))
                             if f"belief_{e}_{key}" in z.files else None) for key, attr, dtype in _BELIEF_ARRAYS}
            beliefs[e] = consistency.Belief(**fields)
        n = len(z["gyr_valid"])
        flags: dict[int, dict[str, np.ndarray]] = {}
        for k in z.files:
            if k.startswith("flag_"):
                _, e, name = k.split("_", 2)
                flags.setdefault(int(e), {})[name] = np.unpackbits(z[k], count=n).astype(bool)
        events = _events(z["event_names"], z["event_spans_s"]) if "event_names" in z.files else None
        return RecordingSeries(str(z["id"]), get("imu_t"), z["gyr_valid"], get("truth_t"), get("truth_quat"),
                               labels, [bool(x) for x in z["causal"]], get("quat"), get("err_deg"), losses, beliefs,
                               flags, events)


# --- the encoding (module docstring) ---

ENCODING = "bit-deltas"
# array -> (the float type its values are kept in, its time axis); the beliefs' float arrays: float32, axis 0
_ENCODED: dict[str, tuple[type, int]] = {"imu_t": (np.float64, 0), "truth_t": (np.float64, 0),
                                         "truth_quat": (np.float16, 0), "quat": (np.float16, 1),
                                         "err_deg": (np.float16, 2)}
_BITS = {np.float64: np.int64, np.float32: np.int32, np.float16: np.int16}


def _bit_deltas(values: np.ndarray, kind: type, axis: int) -> np.ndarray:
    """`values` as `kind`, as the differences along `axis` of their bit patterns (same shape;
    integer wrap-around on both sides makes it exact)."""
    bits = np.asarray(values, dtype=kind).view(_BITS[kind])
    return np.diff(bits, axis=axis, prepend=np.zeros_like(bits.take([0], axis=axis)) if bits.shape[axis] else bits)


def _values(deltas: np.ndarray, kind: type, axis: int) -> np.ndarray:
    """The values `_bit_deltas` stored (float32 for float16, else `kind`)."""
    bits = np.cumsum(deltas, axis=axis, dtype=_BITS[kind])
    values = bits.view(kind)
    return values.astype(np.float32) if kind is np.float16 else values
