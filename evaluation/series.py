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
                            `fusion.evaluation.align`), what the estimates were scored against
    labels        (E,)     str, estimator specs as in results.json
    causal        (E,)     bool, False for smoothers
    quat          (E, N, 4) quat_wxyz R_world_body of each estimator
    err_deg       (E, 3, N) total/inclination/heading error, deg; NaN where not
                            scored (outside the truth span, in gaps; all NaN without truth)
    loss_<e>      (K_e,)   float64 cost per iteration of estimator e, where it reports one
    belief_<e>_*           what filter e believed, where it reports an error covariance
                            (`fusion.evaluation.consistency.Belief`): `_err` (N, 3) attitude
                            error against the truth, rad, body frame (NaN without truth);
                            `_sigma` (N, 3) sqrt(P_ii), rad; `_nees`, `_nis` (N,); `_updated`
                            (N,) bool; where recorded `_rest`, `_guarded` (N,) bool and `_bias`
                            (N, 3) rad/s

The file is a compressed npz (`np.savez_compressed`) under the names above. A file written
with `encoding` = "bit-deltas" (this version) stores each float array as the differences, along
time, of its values' bit patterns (an integer array of the same shape: consecutive samples
differ in their low bits only, which deflate packs tightly; `np.cumsum` along the time axis and
a view give the values back exactly):

    imu_t, truth_t                float64 (int64 deltas along axis 0): exact
    belief_<e>_err, _sigma, _nees, _nis, _bias
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

from . import consistency
from .metrics import KINDS


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
    return part


def job_part(trajectory, job_score, truth_at_imu) -> dict[str, np.ndarray]:
    """What one estimate adds to its recording's series: `quat` (N, 4) float32, `err_deg` (3, N)
    float32, `loss` where the estimator reports one, `belief_*` (without the estimator's index)
    where it reports a covariance; and `quat_wxyz` (N, 4) float64, the estimate itself (exported as
    a TUM file, not kept in the series).

    job_score: its `fusion.evaluation.metrics.Score` (None without truth); truth_at_imu: a callable
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
    return part


def from_results(rec, results: list, causal: dict[str, bool] | None = None) -> RecordingSeries:
    """One recording's series from its recording (`fusion.types.Recording`, with `--align` its
    aligned truth) and whole results of it (`fusion.evaluation.job.run_one`,
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
    for e, part in enumerate(parts):
        quat[e], err[e] = part["quat"], part["err_deg"]
        if "loss" in part:
            losses[e] = part["loss"]
        if "belief_err" in part:
            beliefs[e] = consistency.Belief(**{attr: (part[f"belief_{key}"].astype(float if dtype is np.float32 else bool)
                                                      if f"belief_{key}" in part else None)
                                               for key, attr, dtype in _BELIEF_ARRAYS})
    return RecordingSeries(str(recording["id"]), recording["imu_t"], recording["gyr_valid"], recording["truth_t"],
                           recording["truth_quat"], list(labels), list(causal), quat, err, losses, beliefs)


_BELIEF_ARRAYS = (("err", "err_rad", np.float32), ("sigma", "sigma_rad", np.float32), ("nees", "nees", np.float32),
                  ("nis", "nis", np.float32), ("updated", "updated", bool), ("rest", "rest", bool),
                  ("guarded", "guarded", bool), ("bias", "bias_rad_s", np.float32))


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
        return RecordingSeries(str(z["id"]), get("imu_t"), z["gyr_valid"], get("truth_t"), get("truth_quat"),
                               labels, [bool(x) for x in z["causal"]], get("quat"), get("err_deg"), losses, beliefs)


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
