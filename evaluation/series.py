"""The per-recording time series a report's figures are drawn from, and their `.npz` files.

An output folder of `fusion compare --out DIR` holds one `series/NNN.npz` per recording, so
that `fusion report DIR` can draw the figures again without running any estimator. Arrays:

    id            ()       str, the dataset id
    imu_t         (N,)     float64 s, the IMU time stamps every estimate lives on
    gyr_valid     (N,)     bool, False where the gyro was marked unusable
    truth_t       (K,)     float64 s, VICON time stamps (K = 0 without ground truth)
    truth_quat    (K, 4)   float64 quat_wxyz R_world_body, NaN rows in tracking gaps; with
                            `--align`, the truth mapped into our frames (`A R_truth B`,
                            `fusion.evaluation.align`), what the estimates were scored against
    labels        (E,)     str, estimator specs as in results.json
    causal        (E,)     bool, False for smoothers
    quat          (E, N, 4) float32 quat_wxyz R_world_body of each estimator
    err_deg       (E, 3, N) float32 total/inclination/heading error, deg; NaN where not
                            scored (outside the truth span, in gaps; all NaN without truth)
    loss_<e>      (K_e,)   float64 cost per iteration of estimator e, where it reports one
    belief_<e>_*           what filter e believed, where it reports an error covariance
                            (`fusion.evaluation.consistency.Belief`): `_err` (N, 3) float32
                            attitude error against the truth, rad, body frame (NaN without
                            truth); `_sigma` (N, 3) float32 sqrt(P_ii), rad; `_nees`, `_nis`
                            (N,) float32; `_updated` (N,) bool; where recorded `_rest`,
                            `_guarded` (N,) bool and `_bias` (N, 3) float32 rad/s

float32 is plenty for plotting (1e-7 relative) and halves the files; the scores in
results.json come from the float64 computation.
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


def from_results(info, results: list, causal: dict[str, bool]) -> RecordingSeries:
    """Collect one recording's series from its `RecordingInfo` and `Result`s (with trajectories)."""
    n = len(info.imu_t)
    quat = np.empty((len(results), n, 4), np.float32)
    err = np.full((len(results), len(KINDS), n), np.nan, np.float32)
    losses: dict[int, np.ndarray] = {}
    beliefs: dict[int, consistency.Belief] = {}
    truth_at_imu = None  # the truth slerped onto the IMU stamps, once per recording, if a filter needs it
    for e, r in enumerate(results):
        if r.trajectory is None:
            raise ValueError(f"{info.id}: result {r.estimator!r} has no trajectory to plot")
        quat[e] = r.trajectory.quat_wxyz
        if r.score is not None:
            for k, kind in enumerate(KINDS):
                err[e, k, r.score.mask] = np.degrees(r.score.errors_rad[kind])
        loss = r.trajectory.diagnostics.get("loss") if r.trajectory.diagnostics else None
        if loss is not None:
            losses[e] = np.asarray(loss, dtype=float).ravel()
        if consistency.has_covariance(r.trajectory):
            if truth_at_imu is None and info.truth is not None:
                truth_at_imu = consistency.truth_on(info.truth, r.trajectory.t)
            beliefs[e] = consistency.from_trajectory(r.trajectory, truth_at_imu)
    truth = info.truth
    return RecordingSeries(
        info.id, np.asarray(info.imu_t), np.asarray(info.gyr_valid, bool),
        np.asarray(truth.t) if truth is not None else np.empty(0),
        np.asarray(truth.quat_wxyz) if truth is not None else np.empty((0, 4)),
        [r.estimator for r in results], [causal.get(r.estimator, True) for r in results],
        quat, err, losses, beliefs,
    )


_BELIEF_ARRAYS = (("err", "err_rad", np.float32), ("sigma", "sigma_rad", np.float32), ("nees", "nees", np.float32),
                  ("nis", "nis", np.float32), ("updated", "updated", bool), ("rest", "rest", bool),
                  ("guarded", "guarded", bool), ("bias", "bias_rad_s", np.float32))


def save(path: Path, s: RecordingSeries) -> None:
    arrays = dict(id=np.array(s.id), imu_t=s.imu_t, gyr_valid=s.gyr_valid, truth_t=s.truth_t,
                  truth_quat=s.truth_quat, labels=np.array(s.labels, dtype=str), causal=np.array(s.causal, bool),
                  quat=s.quat, err_deg=s.err_deg)
    arrays.update({f"loss_{e}": v for e, v in s.losses.items()})
    for e, belief in s.beliefs.items():
        for key, attr, dtype in _BELIEF_ARRAYS:
            value = getattr(belief, attr)
            if value is not None:
                arrays[f"belief_{e}_{key}"] = np.asarray(value, dtype=dtype)
    np.savez(path, **arrays)


def load(path: Path) -> RecordingSeries:
    with np.load(path, allow_pickle=False) as z:
        losses = {int(k[5:]): z[k] for k in z.files if k.startswith("loss_")}
        labels = [str(x) for x in z["labels"]]
        beliefs = {}
        for e in sorted({int(k.split("_")[1]) for k in z.files if k.startswith("belief_")}):
            fields = {attr: (z[f"belief_{e}_{key}"].astype(float if dtype is np.float32 else bool)
                             if f"belief_{e}_{key}" in z.files else None) for key, attr, dtype in _BELIEF_ARRAYS}
            beliefs[e] = consistency.Belief(**fields)
        return RecordingSeries(str(z["id"]), z["imu_t"], z["gyr_valid"], z["truth_t"], z["truth_quat"],
                               labels, [bool(x) for x in z["causal"]], z["quat"], z["err_deg"], losses, beliefs)
