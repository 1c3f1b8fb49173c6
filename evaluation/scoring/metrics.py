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
   All three are invariant under q -> -q. By default no alignment is applied: every
   estimator starts from the same initial orientation (see `fusion.datasets.initial_orientation`).
   With `--align` the caller first maps the truth into our frames, `A R_truth B`, with
   constant world and body rotations A, B fitted once per recording from the IMU and the
   truth alone (`fusion.evaluation.scoring.align`); every estimator is then scored against the same truth.
3. Summaries: RMSE and maximum of each over the scored samples, and the coverage: the scored
   samples as a fraction of the samples the protocol would score (all the estimate's samples;
   with "broad", those inside `movement`). A score on little of the recording (truth that
   overlaps the IMU by 15 ms scores 2 of 6,000 samples) says little about it: `MIN_COVERAGE`.

`protocol="broad"` scores as the BROAD benchmark does for 6-D estimates (Laidig et al.
2021): only the samples inside `movement` (BROAD's movement phases) are scored, and the
heading offset is removed first: the estimate is turned about world z by the circular mean,
over the scored samples, of the heading (twist) of the world-frame error `R_gt R_est^-1`.
Inclination is unchanged by that; heading is what remains after it, total the geodesic
angle after it. Without a `movement` mask every sample with truth is scored. A 9-D estimate
(one that used a magnetometer, `nine_d`) is scored as BROAD scores those: on the movement
samples, with no heading offset removed (the truth's heading agrees with magnetic north, so a
magnetometer makes the heading observable and its error is the estimator's).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from fusion import quaternion
from fusion.types import Trajectory

KINDS = ("total", "inclination", "heading")
# A score covering less than half of what the protocol scores is flagged and left out of the means:
# below half, the RMSE describes a minority of the recording (e.g. only the seconds before the
# heading has drifted) and is not comparable with full-coverage rows. The course recordings are
# covered 92-100 % by their VICON (tracking gaps and the ends outside VICON's span), BROAD 100 %.
MIN_COVERAGE = 0.5


def _wxyz(r: Rotation | np.ndarray) -> np.ndarray:
    """(M, 4) unit wxyz from a `Rotation` stack or raw quaternions (normalised, as `Rotation` does)."""
    if isinstance(r, Rotation):
        return r.as_quat(scalar_first=True)
    return quaternion.normalize(np.asarray(r, dtype=float))


def _angle(vector_norm: np.ndarray, scalar: np.ndarray) -> np.ndarray:
    """The rotation angle of a unit quaternion from |vector part| and its scalar part, in
    [0, pi] for q and -q alike: 2 atan2(|v|, |w|), accurate at small angles where 2 arccos(|w|)
    is not (the rule of `fusion.quaternion.to_rotvec`, the sign of w folded in)."""
    return 2.0 * np.arctan2(vector_norm, np.abs(scalar))


def error_angles(r_true: Rotation | np.ndarray, r_est: Rotation | np.ndarray) -> dict[str, np.ndarray]:
    """Per-sample total, inclination and heading errors (rad) between two stacks of orientations
    (`Rotation`s or (M, 4) wxyz arrays, `R_world_body`); quaternion algebra on whole arrays
    (`fusion.quaternion`), faster than SciPy's `Rotation` products."""
    q_true, q_est = _wxyz(r_true), _wxyz(r_est)
    body = quaternion.multiply(quaternion.conjugate(q_true), q_est)  # R_gt^-1 R_est
    total = _angle(np.linalg.norm(body[..., 1:], axis=-1), body[..., 0])
    g_true, g_est = quaternion.gravity_in_body(q_true), quaternion.gravity_in_body(q_est)
    # atan2(|a x b|, a . b) is accurate at small angles, where arccos is not.
    inclination = np.arctan2(np.linalg.norm(np.cross(g_true, g_est), axis=-1), np.einsum("...i,...i", g_true, g_est))
    world = quaternion.multiply(q_est, quaternion.conjugate(q_true))  # R_est R_gt^-1, world-frame error
    twist = _angle(np.abs(world[..., 3]), world[..., 0])  # swing-twist: the twist about z, in [0, pi]
    return {"total": total, "inclination": inclination, "heading": twist}


@dataclass(frozen=True, eq=False)
class Score:
    """Errors of one estimate against the truth.

    t: (M,) the scored time stamps (inside the truth span, outside tracking gaps).
    errors_rad: per kind, (M,) angles in rad.
    mask: (N,) bool over the estimate's samples: which ones were scored.
    eligible: how many samples the protocol would score (N, or the movement samples).
    """

    t: np.ndarray
    errors_rad: dict[str, np.ndarray]
    mask: np.ndarray
    rmse_deg: dict[str, float] = field(default_factory=dict)
    max_deg: dict[str, float] = field(default_factory=dict)
    eligible: int = 0

    @property
    def samples(self) -> int:
        return len(self.t)

    @property
    def coverage(self) -> float:
        """Scored samples / eligible samples, in [0, 1]."""
        return self.samples / self.eligible if self.eligible else 0.0


PROTOCOLS = ("full", "broad")


def mean_heading_offset(r_true: Rotation | np.ndarray, r_est: Rotation | np.ndarray) -> float:
    """Circular mean (rad) of the twist about world z of `R_gt R_est^-1` (BROAD's heading offset).
    r_true, r_est: `Rotation` stacks or (M, 4) wxyz arrays."""
    err = quaternion.multiply(_wxyz(r_true), quaternion.conjugate(_wxyz(r_est)))
    psi = 2.0 * np.arctan2(err[:, 3], err[:, 0])  # signed twist of each error, wrap-safe via sin/cos
    return float(np.arctan2(np.mean(np.sin(psi)), np.mean(np.cos(psi))))


def score(truth: Trajectory, estimate: Trajectory, protocol: str = "full", movement: np.ndarray | None = None,
          partial: bool = False, nine_d: bool = False) -> Score:
    """Score `estimate` against `truth` (see the module docstring for the protocols).

    protocol: "full" (every sample with truth) or "broad".
    movement: (N,) bool over the estimate's samples, the samples "broad" scores (None: all).
    partial: the estimate may have no orientation (NaN rows) at some samples, which are then not
        scored (and count against its coverage); otherwise a NaN row where the truth has one is an
        error (a diverged estimate).
    nine_d: the estimate used a magnetometer: "broad" removes no heading offset (module docstring).
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown scoring protocol {protocol!r}; use one of {', '.join(PROTOCOLS)}")
    r_true, mask = truth.interpolate(estimate.t)
    finite = np.all(np.isfinite(estimate.quat_wxyz), axis=1)
    eligible = len(mask)
    if protocol == "broad" and movement is not None:
        movement = np.asarray(movement, dtype=bool)
        if movement.shape != mask.shape:
            raise ValueError(f"movement mask has shape {movement.shape}, the estimate {mask.shape[0]} samples")
        if r_true is not None:
            inside = movement[mask]
            r_true = r_true[inside] if inside.any() else None
        mask = mask & movement
        eligible = int(movement.sum())
    if r_true is None or not np.any(mask & finite):
        raise ValueError("the estimate and the ground truth share no valid time stamp")
    keep = finite[mask]  # a diverged estimate (NaN rows) would otherwise poison the RMSE
    if partial and not keep.all():
        r_true = r_true[keep]
        mask = mask & finite
    elif not keep.all():
        raise ValueError(f"the estimate has {int((~keep).sum())} non-finite orientations inside the scored span")
    q_true, q_est = _wxyz(r_true), _wxyz(estimate.quat_wxyz[mask])
    if protocol == "broad" and not nine_d:  # remove the mean heading offset (6-D: heading is unobservable)
        q_est = quaternion.multiply(quaternion.from_rotvec(np.array([0.0, 0.0, mean_heading_offset(q_true, q_est)])),
                                    q_est)
    errors = error_angles(q_true, q_est)
    rmse = {k: float(np.degrees(np.sqrt(np.mean(v**2)))) for k, v in errors.items()}
    worst = {k: float(np.degrees(np.max(v))) for k, v in errors.items()}
    return Score(estimate.t[mask], errors, mask, rmse, worst, eligible)
