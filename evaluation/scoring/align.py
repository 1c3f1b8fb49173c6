"""Two constant rotations that map a ground truth given in frames of its own onto ours,
fitted once per recording from the IMU's own measurements.

Public datasets often give motion-capture orientations `R_truth(t)` = R_truthworld_truthbody
in a world frame whose vertical is not z and for a marker body frame rotated against the IMU.
With

    A = R_ourworld_truthworld   (maps truth-world vectors into our z-up world)
    B = R_truthbody_imubody     (maps IMU-body vectors into the truth's body frame)

the truth expressed in our frames is

    R_aligned(t) = A R_truth(t) B        (= R_ourworld_imubody, what an estimate estimates)

and equivalently R_truth(t) = A^-1 R_aligned(t) B^-1. Scoring then compares every estimate
with the same `R_aligned`, so inclination still means the tilt from our world's z and heading
the twist about it.

`fit_alignment` uses only the recording (gyro, accelerometer, truth), never an estimate, so
an estimator's errors cannot leak into the alignment and every estimator of a recording is
scored against the same aligned truth.

1. B from angular rates. The truth's body rate omega_truth(tau_j), the rotation vector of
   R_truth(t_j)^-1 R_truth(t_{j+1}) over the step (`fusion.checks.vicon_body_rate`, on the
   truth's own clock, tau_j the step midpoints), equals B applied to the gyro rate at the same
   instant, omega_truth = B omega_gyro. The gyro's interval rates (`ImuSamples.interval_rates`,
   which honours the recording's `gyr_timing`) live on the IMU interval midpoints and are
   interpolated linearly to tau_j. B solves Wahba's problem over all pairs,
   min_B sum_j w_j |omega_truth_j - B omega_gyro_j|^2, by the SVD of the attitude profile matrix
   (Markley 1988, "Attitude determination using vector observations and the singular value
   decomposition", J. Astronautical Sciences 36(3), eqs. 14-19; SciPy's
   `Rotation.align_vectors`). Pairs where the gyro is invalid (either neighbour) or the truth
   step spans a gap are skipped. The weights are iteratively reweighted with Huber's weight
   min(1, k s / r_j) on the residual norm r_j, s the normalised median absolute residual
   (Huber 1964, "Robust estimation of a location parameter", Ann. Math. Statist. 35(1)), so
   saturated gyro samples, undetected freezes and truth glitches do not pull B.
2. A's tilt from the accelerometer. The specific force in the truth world,
   R_truth(t) B a(t) = g up_truthworld + (linear acceleration), averaged over the recording
   gives the truth world's up direction: the linear acceleration averages to the change of
   velocity over the duration, which is bounded. A is the smallest rotation taking that up
   direction to our +z (its axis is horizontal).
3. A's rotation about the vertical is not observable from a gyro and an accelerometer. Without a
   magnetometer we fit none: A is the smallest tilt (step 2). Scores do not depend on that choice
   when the estimators start from the aligned truth (`--init truth`, the default with truth, also
   under `--align`): a turn of A about z turns the aligned truth and the shared start alike.
   Like the unaligned scores, heading errors then are relative to the truth's heading at the
   first sample; the BROAD protocol removes each estimate's mean heading offset as usual.
   With a magnetometer, a 9-D estimate's heading is magnetic north's, which the truth's world
   (Vicon's, say) need not share: scored as it is, its heading error would be that constant angle
   between the two worlds, the same for every estimator (about 58 deg on RepoIMU), and whoever
   found north fastest would rank last. So A also turns the truth's world to magnetic north
   (`magnetic_north`): the field, rotated into the tilt-aligned truth's world, R(t) m(t), points
   north and down; its horizontal part, averaged over the samples whose field norm is within
   `UNDISTURBED_FIELD` of the median (a passing magnet left out), gives north's heading there, and
   A turns it onto our +y (ENU: x east, y north, z up). It is fitted from the recording's
   magnetometer and truth, never an estimate, once per recording, the same for every estimator
   (`north_deg`); 6-D scores do not change (they start from the aligned truth: above).

Observability. A recording that turns about one axis n only (a pendulum's swing, a wand turned
about its shaft, a turntable) does not fix B's turn about n: the rates are the same for any, and
neither the accelerometer nor the magnetometer can tell them apart when the truth's world is
fitted too (turning the mounting by phi about n is explained by the truth's world turned by phi,
for every world-fixed direction the IMU measures). It does not need to: whichever B the rates give,
A taking the averaged specific force to +z makes the aligned truth the true orientation turned
about the vertical, A R_truth(t) B = Rot(z, psi) R(t) (R(t) turning about n commutes with a turn
about n), and a constant turn about the vertical changes no score: the estimators start from the
aligned truth, and a 9-D row's north is fitted (step 3). `tests/test_align.py` checks this on a
swing with B 54 deg off. Only a recording without rotation, or with fewer than `MIN_PAIRS`
usable rate pairs, is refused.

Quality (`Alignment.problem`, and the table's alignment rows): the median rate residual against the
median rate and the averaged specific force's norm (the criteria: beyond them the truth and the
IMU disagree about the motion itself), and, reported beside them, how far B fitted on the first
half of the recording and on the second differ (`halves_deg`): a few tenths of a degree on BROAD and
the T-stick, 2-130 deg on RepoIMU's pendulum, whose swing leaves B's turn about its axis weakly
determined: its absolute inclination scores carry that, the same for every estimator.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fusion.checks import FlatTopDetector, vicon_body_rate
from fusion.types import ImuSamples, Trajectory

MIN_PAIRS = 3
# An alignment a recording cannot be scored through (`Alignment.problem`). On the shared recordings a
# good fit leaves a median rate residual of 2-43 % of the median rate (the course's held and frozen gyro
# samples and its 1-2 deg frames near the top, BROAD 2-30 %, RepoIMU's T-stick 2-15 % and its pendulum
# 12-43 %) and an averaged specific force within 0.02 g of 1 g; the fits that fail have 58-75 % (three
# pendulum segments, the T-stick's Test05_Trial2) or 0.71 g.
MAX_RELATIVE_RESIDUAL = 0.5  # median rate residual / median truth rate
GRAVITY_RANGE_G = (0.9, 1.1)  # the averaged specific force's norm
UNDISTURBED_FIELD = 0.1  # relative: a magnetometer sample within this of the median field norm counts for north
HUBER_K = 2.5  # residuals beyond 2.5 robust sigmas are down-weighted
MAX_ITERATIONS = 100
SCALE_AXIS_RATIO = 1e-2  # fit a gyro scale factor only on axes with 1 % of the largest axis' rate power


@dataclass(frozen=True, eq=False)
class Alignment:
    """The constant rotations between the truth's frames and ours (module docstring).

    world: A = R_ourworld_truthworld (a tilt only: the smallest rotation taking the truth
        world's up direction to our z).
    body: B = R_truthbody_imubody.
    rate_pairs: how many (truth rate, gyro rate) pairs B was fitted on.
    rate_residual_deg_s: median of |omega_truth - B omega_gyro| over those pairs, deg/s.
    gravity_g: norm of the averaged specific force, in g (about 1 for a good fit).
    truth_rate_deg_s: median of |omega_truth| over those pairs, deg/s (the residual's scale).
    halves_deg: how far B fitted on each half of the recording differ, deg (module docstring,
        Quality); None when a half does not determine it.
    north_deg: the turn about the vertical, deg, by which A takes the truth's world to magnetic
        north (module docstring, step 3); None without a magnetometer (A is then a tilt only).
    gyro_scale: the per-axis gyro scale factors fitted with B (truth rate / gyro rate on each
        IMU axis; a by-product, not applied to any estimator).
    """

    world: Rotation
    body: Rotation
    rate_pairs: int
    rate_residual_deg_s: float
    gravity_g: float
    gyro_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    truth_rate_deg_s: float = float("nan")
    halves_deg: float | None = None
    north_deg: float | None = None

    def problem(self) -> str | None:
        """Why the recording cannot be scored through this alignment (one line), or None: the gyro
        leaves more than `MAX_RELATIVE_RESIDUAL` of the truth's rates unexplained, or the averaged
        specific force is not gravity (`GRAVITY_RANGE_G`): the truth and the IMU disagree about
        the motion itself, and any score would measure that, not an estimator."""
        parts = []
        relative = self.rate_residual_deg_s / self.truth_rate_deg_s if self.truth_rate_deg_s > 0 else 0.0
        if relative > MAX_RELATIVE_RESIDUAL:
            parts.append(f"the gyro leaves {self.rate_residual_deg_s:.1f} deg/s of the truth's rates unexplained "
                         f"(median residual, {100 * relative:.0f} % of the median rate; at most "
                         f"{100 * MAX_RELATIVE_RESIDUAL:.0f} %)")
        if not GRAVITY_RANGE_G[0] <= self.gravity_g <= GRAVITY_RANGE_G[1]:
            parts.append(f"the averaged specific force is {self.gravity_g:.3f} g, not gravity (expected "
                         f"{GRAVITY_RANGE_G[0]:g}-{GRAVITY_RANGE_G[1]:g} g)")
        return "; ".join(parts) or None

    def apply(self, truth: Trajectory) -> Trajectory:
        """The truth in our frames, `A R_truth B` (a new `Trajectory`; NaN rows stay NaN)."""
        out = np.full_like(truth.quat_wxyz, np.nan)
        ok = truth.valid
        if ok.any():
            rot = self.world * Rotation.from_quat(truth.quat_wxyz[ok], scalar_first=True) * self.body
            out[ok] = rot.as_quat(scalar_first=True)
        return Trajectory(truth.t, out, truth.diagnostics)

    def to_json(self) -> dict[str, Any]:
        """`world_deg`, `body_deg`: rotation vectors (axis * angle) in degrees; their norms; the
        fit's diagnostics."""
        world, body = self.world.as_rotvec(degrees=True), self.body.as_rotvec(degrees=True)
        return {"world_deg": [float(x) for x in world], "body_deg": [float(x) for x in body],
                "world_angle_deg": float(np.linalg.norm(world)), "body_angle_deg": float(np.linalg.norm(body)),
                "rate_pairs": self.rate_pairs, "rate_residual_deg_s": self.rate_residual_deg_s,
                "truth_rate_deg_s": self.truth_rate_deg_s, "gravity_g": self.gravity_g,
                "gyro_scale": list(self.gyro_scale), "halves_deg": self.halves_deg,
                "north_deg": self.north_deg, "problem": self.problem()}


def _interp_rates(t_query: np.ndarray, t: np.ndarray, rate: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of (K, 3) `rate` at (M,) `t_query`; the mask says where both
    neighbours are valid and the query is inside the span."""
    right = np.clip(np.searchsorted(t, t_query, side="right"), 1, len(t) - 1)
    left = right - 1
    frac = ((t_query - t[left]) / (t[right] - t[left]))[:, None]
    out = rate[left] + (rate[right] - rate[left]) * frac
    ok = valid[left] & valid[right] & (t_query >= t[0]) & (t_query <= t[-1])
    return out, ok


def rate_pairs(imu: ImuSamples, truth: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Matching angular rates at the truth's step midpoints (module docstring, step 1).

    Returns `(truth_rate, gyro_rate)`: (M, 3) rad/s each, the truth's body rate (truth body
    frame) and the gyro's (IMU body frame), only where both are usable: the gyro valid and not on a
    flat top (`fusion.checks.FlatTopDetector`: a clipped reading is not the rate, though the
    estimators integrate it), the truth without a gap.
    """
    if len(imu) < 3 or len(truth) < 2:
        return np.empty((0, 3)), np.empty((0, 3))
    tau, omega = vicon_body_rate(truth)
    rate, valid = imu.interval_rates()
    mid = 0.5 * (imu.t[:-1] + imu.t[1:])
    clipped = FlatTopDetector().mask(imu.gyr_rad_s).any(axis=1)
    clipped[1:] |= clipped[:-1]  # and the sample after a flat top (the last before it is within its band)
    first = 1 if imu.gyr_timing == "end" else 0  # the sample each interval's rate is (`ImuSamples.interval_rates`)
    valid = valid & np.all(np.isfinite(rate), axis=1) & ~clipped[first:first + len(rate)]
    gyro, ok = _interp_rates(tau, mid, rate, valid)
    ok &= np.all(np.isfinite(omega), axis=1)
    return omega[ok], gyro[ok]


def fit_body(truth_rate: np.ndarray, gyro_rate: np.ndarray) -> tuple[Rotation, np.ndarray, np.ndarray]:
    """B with `truth_rate ~ B diag(scale) gyro_rate`: Wahba's problem with per-axis gyro scale
    factors and Huber reweighting (module docstring, step 1). truth_rate, gyro_rate: (M, 3)
    rad/s. Returns B, the (3,) scale factors and the (M,) residual norms, rad/s.

    Raises ValueError for fewer than `MIN_PAIRS` pairs or no rotation at all. Rates about a single
    axis leave B's turn about it free (module docstring, Observability): one of them is returned.
    """
    n = len(truth_rate)
    if n < MIN_PAIRS:
        raise ValueError(f"it needs at least {MIN_PAIRS} truth steps with a valid gyro rate "
                         f"(truth rows on both sides, gyro valid), got {n}")
    if not np.any(gyro_rate):
        raise ValueError("the recording does not rotate, so no body rotation can be fitted to its rates")
    power = np.sum(gyro_rate**2, axis=0)
    scalable = power > SCALE_AXIS_RATIO * power.max()  # axes with enough motion to fit a scale on
    weights, scale, body = np.ones(n), np.ones(3), Rotation.identity()
    for _ in range(MAX_ITERATIONS):
        with warnings.catch_warnings():  # one axis only: "not uniquely defined", and any solution does (above)
            warnings.simplefilter("ignore", UserWarning)
            body_new, _ = Rotation.align_vectors(truth_rate, gyro_rate * scale, weights=weights)  # Markley 1988
        in_imu = body_new.inv().apply(truth_rate)  # the truth's rate on the IMU axes
        scale_new = scale.copy()
        with np.errstate(invalid="ignore", divide="ignore"):  # an axis without motion: 0 / 0, not scaled
            scale_new[scalable] = ((weights[:, None] * in_imu * gyro_rate).sum(axis=0)
                                   / (weights[:, None] * gyro_rate**2).sum(axis=0))[scalable]  # per-axis least squares
        residual = np.linalg.norm(truth_rate - body_new.apply(gyro_rate * scale_new), axis=1)
        sigma = 1.4826 * np.median(residual)  # robust sigma (normalised median absolute deviation)
        weights = np.minimum(1.0, HUBER_K * sigma / np.maximum(residual, 1e-300)) if sigma > 0 else np.ones(n)
        step = max((body_new * body.inv()).magnitude(), np.max(np.abs(scale_new - scale)))
        body, scale = body_new, scale_new
        if step < 1e-10:
            break
    return body, scale, residual


def halves_angle_deg(truth_rate: np.ndarray, gyro_rate: np.ndarray) -> float | None:
    """How far B fitted on the first half of the rate pairs and on the second half differ, deg
    (module docstring, Quality); None when a half does not determine it."""
    half = len(truth_rate) // 2
    try:
        first, _, _ = fit_body(truth_rate[:half], gyro_rate[:half])
        second, _, _ = fit_body(truth_rate[half:], gyro_rate[half:])
    except ValueError:
        return None
    return float(np.degrees((first * second.inv()).magnitude()))


def magnetic_north(imu: ImuSamples, truth: Trajectory, world: Rotation, body: Rotation) -> float | None:
    """The turn about the vertical (rad) that takes the truth's world, tilt-aligned by `world`, to
    magnetic north (module docstring, step 3): the horizontal field of R(t) m(t) = world R_truth(t)
    body m(t), averaged over the undisturbed samples, turned onto +y. None without a magnetometer
    (or without a valid sample inside the truth's span)."""
    if not imu.has_mag:
        return None
    r_truth, mask = truth.interpolate(imu.t)
    if r_truth is None:
        return None
    ok = imu.mag_valid[mask]
    if not ok.any():
        return None
    field = (world * r_truth[ok] * body).apply(imu.mag_ut[mask][ok])  # (M, 3) in the tilt-aligned truth's world
    norm = np.linalg.norm(field, axis=1)
    undisturbed = np.abs(norm - np.median(norm)) <= UNDISTURBED_FIELD * np.median(norm)
    horizontal = field[undisturbed, :2].mean(axis=0)
    if not np.linalg.norm(horizontal) > 0:
        return None
    return float(np.pi / 2 - np.arctan2(horizontal[1], horizontal[0]))  # Rz(this) turns the field's azimuth onto +y


def truth_up(imu: ImuSamples, truth: Trajectory, body: Rotation) -> np.ndarray:
    """(3,) the averaged specific force in the truth world, g: `mean_t R_truth(t) B a(t)`
    over the IMU samples inside the truth's span (module docstring, step 2)."""
    r_truth, mask = truth.interpolate(imu.t)
    if r_truth is None:
        raise ValueError("no IMU sample falls inside the ground truth's span")
    return np.mean((r_truth * body).apply(imu.acc_g[mask]), axis=0)


def fit_alignment(imu: ImuSamples, truth: Trajectory) -> Alignment:
    """A and B of one recording from its gyro, accelerometer and truth (module docstring).

    imu: calibrated samples (gyro rad/s and accelerometer g, IMU body frame).
    truth: R_truthworld_truthbody on the truth's clock, NaN rows in gaps.
    Raises ValueError when the recording does not determine them.
    """
    truth_rate, gyro_rate = rate_pairs(imu, truth)
    body, scale, residual = fit_body(truth_rate, gyro_rate)
    up = truth_up(imu, truth, body)
    gravity = float(np.linalg.norm(up))
    if not gravity > 0.1:
        raise ValueError(f"the averaged specific force is {gravity:.3f} g, not gravity; "
                         "is the accelerometer in g?")
    world, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up / gravity])  # smallest rotation up -> +z
    north = magnetic_north(imu, truth, world, body)
    if north is not None:
        north = float(np.angle(np.exp(1j * north)))  # in (-pi, pi]
        world = Rotation.from_rotvec([0.0, 0.0, north]) * world
    return Alignment(world, body, len(truth_rate), float(np.degrees(np.median(residual))), gravity,
                     tuple(float(x) for x in scale), float(np.degrees(np.median(np.linalg.norm(truth_rate, axis=1)))),
                     halves_angle_deg(truth_rate, gyro_rate), None if north is None else float(np.degrees(north)))
