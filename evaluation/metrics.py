"""Scoring an estimated trajectory against ground truth.

Protocol:
1. The truth is slerped onto the estimate's time stamps, inside the truth's span only; a
   time stamp that falls in a tracking gap (NaN truth rows, VICON in recordings 6 and 7) is
   skipped, never interpolated across or averaged.
2. Per sample, three angles (rad; the summaries in degrees):
   - total: the geodesic angle `|(R_gt^-1 R_est).magnitude()|`;
   - inclination: the angle between the true and the estimated gravity direction in the body
     frame, `angle(R_gt^-1 e_z, R_est^-1 e_z)`; what a 6-axis IMU can observe;
   - heading: the twist about world z of the world-frame error `R_est R_gt^-1`
     (swing-twist split), wrapped to [0, pi].
   All three are invariant under q -> -q. No alignment is applied: every estimator starts
   from the same initial orientation (see `fusion.datasets.initial_orientation`).
3. Summaries: RMSE and maximum of each over the scored samples.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from fusion.types import Trajectory

KINDS = ("total", "inclination", "heading")


def error_angles(r_true: Rotation, r_est: Rotation) -> dict[str, np.ndarray]:
    """Per-sample total, inclination and heading errors (rad) between two `Rotation` stacks."""
    total = (r_true.inv() * r_est).magnitude()
    up = np.array([0.0, 0.0, 1.0])
    g_true, g_est = r_true.inv().apply(up), r_est.inv().apply(up)
    # atan2(|a x b|, a . b) is accurate at small angles, where arccos is not.
    inclination = np.arctan2(np.linalg.norm(np.cross(g_true, g_est), axis=-1), np.einsum("...i,...i", g_true, g_est))
    err = (r_est * r_true.inv()).as_quat(scalar_first=True)  # world-frame error
    twist = 2.0 * np.arctan2(np.abs(err[..., 3]), np.abs(err[..., 0]))  # twist about z, in [0, pi]
    return {"total": total, "inclination": inclination, "heading": twist}


@dataclass(frozen=True, eq=False)
class Score:
    """Errors of one estimate against the truth.

    t: (M,) the scored time stamps (inside the truth span, outside tracking gaps).
    errors_rad: per kind, (M,) angles in rad.
    mask: (N,) bool over the estimate's samples: which ones were scored.
    """

    t: np.ndarray
    errors_rad: dict[str, np.ndarray]
    mask: np.ndarray
    rmse_deg: dict[str, float] = field(default_factory=dict)
    max_deg: dict[str, float] = field(default_factory=dict)

    @property
    def samples(self) -> int:
        return len(self.t)


def score(truth: Trajectory, estimate: Trajectory) -> Score:
    """Score `estimate` against `truth` (see the module docstring for the protocol)."""
    r_true, mask = truth.interpolate(estimate.t)
    finite = np.all(np.isfinite(estimate.quat_wxyz), axis=1)
    if r_true is None or not np.any(mask & finite):
        raise ValueError("the estimate and the ground truth share no valid time stamp")
    keep = finite[mask]  # a diverged estimate (NaN rows) would otherwise poison the RMSE
    if not keep.all():
        raise ValueError(f"the estimate has {int((~keep).sum())} non-finite orientations inside the scored span")
    r_est = Rotation.from_quat(estimate.quat_wxyz[mask], scalar_first=True)
    errors = error_angles(r_true, r_est)
    rmse = {k: float(np.degrees(np.sqrt(np.mean(v**2)))) for k, v in errors.items()}
    worst = {k: float(np.degrees(np.max(v))) for k, v in errors.items()}
    return Score(estimate.t[mask], errors, mask, rmse, worst)
