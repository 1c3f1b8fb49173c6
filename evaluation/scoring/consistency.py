"""Does a filter know how wrong it is? Its covariance and innovations checked against the truth.

A recursive filter reports, besides its estimate, what it believes about its own error: the
error-state covariance P_k and, at every accelerometer update, the innovation y_k with its
predicted covariance S_k. A filter is *consistent* when those beliefs match what happens
(Bar-Shalom, Li & Kirubarajan 2001, "Estimation with Applications to Tracking and
Navigation", Wiley, Sec. 5.4, "Consistency of state estimators": the estimation errors are
zero-mean with covariance P_k, the innovations zero-mean and white with covariance S_k). The
statistics here are the tests of that section, for one run of one filter on one recording:

- Attitude error e_k (rad, per body axis): `q_true = q_est exp(e / 2)`, the body-frame
  rotation vector the filters' covariance rows 0-2 describe
  (`fusion.quaternion.relative_rotvec`), against the envelope +-3 sqrt(P_ii). Under the
  hypothesis "e_k ~ N(0, P_k)" each component is inside +-3 sigma with probability 99.73 %.
  This fraction only detects overconfidence: an underconfident filter is always "inside".
- NEES, the normalised estimation error squared e_k^T P_att^-1 e_k over the 3x3 attitude
  block (Bar-Shalom et al. 2001, Sec. 5.4): chi-square with 3 degrees of freedom when
  consistent, mean 3; far below 3 is underconfident, far above overconfident.
- NIS, the normalised innovation squared y_k^T S_k^-1 y_k of the accelerometer update, as
  the filters record it (`nis`; Bar-Shalom et al. 2001, Sec. 5.4): chi-square with 3
  degrees of freedom (the accelerometer's three axes); the two-sided 95 % band is
  [chi2_3^-1(0.025), chi2_3^-1(0.975)] = [0.216, 9.35], and about 95 % of the updates should
  fall inside it. Its time average over the K updates of a run, under the same hypothesis and
  white innovations, is chi-square with 3K degrees of freedom divided by K (the single-run
  time-average test of the same section), so the band of the mean NIS is
  [chi2_3K^-1(0.025) / K, chi2_3K^-1(0.975) / K], narrow for long recordings (2.94-3.06 for
  K = 6,000). Real innovations are not white (hand accelerations last longer than a sample),
  so this band is a strict yardstick; the mean's distance from 3 says more than the verdict.
  The NIS needs no truth: it tests the filter against its own measurements.

P_k is the covariance the filters record after the update at sample k, so e_k is taken at
the same instant. Bar-Shalom et al. are cited by their section (5.4, "Consistency of state
estimators"), not by equation or subsection numbers; the statistics themselves are defined
above in full.

What the numbers cannot separate:

- Heading (the rotation about the vertical) is unobservable from an accelerometer: gravity
  does not change under it. Its variance grows as a random walk (Q dt per step) and no
  measurement shrinks it (only correlations with the tilt can, which `heading_free` cuts), so
  the envelope of the axis that points up (body z for a level board; the others share it as
  the board tilts) widens all the time. Being inside that envelope says the filter knows it
  does not know, not that the heading is good.
- The "error" is the estimate against the truth slerped onto the IMU's time stamps: VICON's
  own error, the marker-to-IMU mounting rotation (unless `--align` fitted it), a residual clock
  offset between IMU and VICON (an offset dt looks like an error of |omega| dt, several degrees
  in fast motion) and the interpolation all enter it. An error outside the envelope can be the
  truth's; the NIS test has no such term.
- A single run: the samples of one recording are strongly correlated in time, so the
  fractions vary more between recordings than independent samples would.

Everything here is numpy/SciPy (no plotting): `fusion.evaluation.report.plots` draws it and
`fusion.evaluation.report.render` tabulates it; the maths is usable on its own:

    from fusion.evaluation.scoring.consistency import from_trajectory, summarize
    belief = from_trajectory(trajectory, truth_quat_wxyz)   # None without a covariance
    print(summarize(belief).inside_3sigma)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from fusion import quaternion as quat
from fusion.types import Trajectory

NIS_DOF = 3  # the accelerometer update: three axes
BAND_PROBABILITY = 0.95  # the two-sided acceptance region of the chi-square tests
N_SIGMA = 3.0  # the envelope drawn and counted: +-3 sqrt(P_ii)


def chi2_band(dof: int, probability: float = BAND_PROBABILITY) -> tuple[float, float]:
    """Two-sided acceptance region (lo, hi) of one chi-square(dof) sample: P(lo <= x <= hi) = probability."""
    tail = 0.5 * (1.0 - probability)
    return float(chi2.ppf(tail, dof)), float(chi2.ppf(1.0 - tail, dof))


def mean_band(count: int, dof: int = NIS_DOF, probability: float = BAND_PROBABILITY) -> tuple[float, float]:
    """Acceptance region of the mean of `count` independent chi-square(dof) samples: the sum is
    chi-square(count * dof) (the single-run time-average test, Bar-Shalom et al. 2001, Sec. 5.4).
    (nan, nan) for count 0."""
    if count <= 0:
        return float("nan"), float("nan")
    lo, hi = chi2_band(count * dof, probability)
    return lo / count, hi / count


def truth_on(truth: Trajectory, t: np.ndarray) -> np.ndarray:
    """(N, 4) quat_wxyz of the truth slerped onto the time stamps `t` (N,) s, NaN rows where it is
    not available (outside its span, in tracking gaps: `Trajectory.interpolate`, the same slerp the
    scoring uses)."""
    t = np.asarray(t, dtype=float)
    out = np.full((len(t), 4), np.nan)
    rot, mask = truth.interpolate(t)
    if rot is not None:
        out[mask] = rot.as_quat(scalar_first=True)
    return out


def attitude_error(est_quat_wxyz: np.ndarray, true_quat_wxyz: np.ndarray) -> np.ndarray:
    """(N, 3) rad, body frame: e with `q_true = q_est exp(e / 2)` (the filters' error state);
    NaN rows where either orientation is NaN. Invariant under q -> -q of either input."""
    est = np.asarray(est_quat_wxyz, dtype=float)
    true = np.asarray(true_quat_wxyz, dtype=float)
    if est.shape != true.shape or est.ndim != 2 or est.shape[1] != 4:
        raise ValueError(f"attitude_error: need two (N, 4) quaternion arrays, got {est.shape} and {true.shape}")
    return quat.relative_rotvec(est, true)  # NaN rows where either input is NaN


def has_covariance(trajectory: Trajectory) -> bool:
    """Whether the trajectory carries a per-sample error-state covariance `cov` (N, n, n), n >= 3."""
    cov = (trajectory.diagnostics or {}).get("cov")
    if cov is None:
        return False
    shape = np.shape(cov)
    return len(shape) == 3 and shape[0] == len(trajectory) and shape[1] == shape[2] >= 3


@dataclass(frozen=True, eq=False)
class Belief:
    """What a filter believed at each sample, and the error it made (one recording).

    err_rad: (N, 3) attitude error e, rad, body frame (`attitude_error`); NaN rows without truth.
    sigma_rad: (N, 3) sqrt(P_ii) of the attitude rows, rad.
    nees: (N,) e^T P_att^-1 e, NaN rows without truth.
    nis: (N,) normalised innovation squared of the accelerometer update, NaN without an update.
    updated: (N,) bool, an accelerometer update was made at this sample (row 0, the reset: False).
    rest: (N,) bool, a zero-rate (rest) bias update was made; None if the filter has none.
    guarded: (N,) bool, the chi-square guard held the bias and scale; None if it has none.
    bias_rad_s: (N, 3) gyro-bias estimate, rad/s, body frame; None if not estimated.
    scale_llr: (N,) ln L of the filter's sequential test on the gyro's scale factors (Wald 1945;
        `fusion.estimators.filters.ekf`, "Scale test"), frozen once it decided, NaN where it does not run;
        None if the filter has no such test.
    """

    err_rad: np.ndarray
    sigma_rad: np.ndarray
    nees: np.ndarray
    nis: np.ndarray
    updated: np.ndarray
    rest: np.ndarray | None = None
    guarded: np.ndarray | None = None
    bias_rad_s: np.ndarray | None = None
    scale_llr: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.nis)

    @property
    def skipped(self) -> np.ndarray:
        """(N,) bool, a step made no accelerometer update (row 0, the reset, is not a step)."""
        skipped = ~self.updated
        skipped[:1] = False
        return skipped


def nees(err_rad: np.ndarray, cov_att: np.ndarray) -> np.ndarray:
    """(N,) e_k^T P_k^-1 e_k of (N, 3) errors and (N, 3, 3) covariances; NaN where e or P is not
    finite (a singular P gives its pseudo-inverse's value)."""
    e = np.asarray(err_rad, dtype=float)
    P = np.asarray(cov_att, dtype=float)
    out = np.full(len(e), np.nan)
    good = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(P), axis=(1, 2))
    if not good.any():
        return out
    eg, Pg = e[good], P[good]
    try:
        x = np.linalg.solve(Pg, eg[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        x = np.einsum("nij,nj->ni", np.linalg.pinv(Pg, hermitian=True), eg)
    out[good] = np.einsum("ni,ni->n", eg, x)
    return out


def from_trajectory(trajectory: Trajectory, truth_quat_wxyz: np.ndarray | None) -> Belief | None:
    """The `Belief` of a filter's trajectory; None when it carries no covariance (`has_covariance`).

    truth_quat_wxyz: (N, 4) the truth at the trajectory's time stamps (`truth_on`), NaN rows where
        it has none; None for a recording without truth (the errors are then all NaN).
    Diagnostics read: `cov` (attitude rows 0-2), `nis`, `acc_var_g2` (NaN: no update), `at_rest`,
    `bias_guarded`, `gyr_bias_rad_s`, `scale_llr`; the last four are None in the `Belief` when not recorded.
    """
    if not has_covariance(trajectory):
        return None
    d = trajectory.diagnostics
    n = len(trajectory)
    cov_att = np.asarray(d["cov"], dtype=float)[:, :3, :3]
    sigma = np.sqrt(np.clip(np.diagonal(cov_att, axis1=1, axis2=2), 0.0, None))
    if truth_quat_wxyz is None:
        err = np.full((n, 3), np.nan)
    else:
        truth_quat_wxyz = np.asarray(truth_quat_wxyz, dtype=float)
        if truth_quat_wxyz.shape != (n, 4):
            raise ValueError(f"truth_quat_wxyz must be (N, 4) with N = {n}, got {truth_quat_wxyz.shape}")
        err = attitude_error(trajectory.quat_wxyz, truth_quat_wxyz)

    def per_sample(key: str, dtype: type, shape: tuple[int, ...] = ()) -> np.ndarray | None:
        value = d.get(key)
        if value is None or np.shape(value) != (n, *shape):
            return None
        return np.array(value, dtype=dtype)

    nis = per_sample("nis", float)
    nis = np.full(n, np.nan) if nis is None else nis
    acc_var = per_sample("acc_var_g2", float)
    updated = np.isfinite(nis) if acc_var is None else np.isfinite(acc_var)
    updated[0] = False  # row 0 is the state after the reset: no update was due
    return Belief(err, sigma, nees(err, cov_att), nis, updated, per_sample("at_rest", bool),
                  per_sample("bias_guarded", bool), per_sample("gyr_bias_rad_s", float, (3,)),
                  per_sample("scale_llr", float))


@dataclass(frozen=True)
class Summary:
    """The consistency numbers of one `Belief` (fractions in [0, 1], NaN where undefined).

    samples: the recording's samples (the reset included).
    samples_with_truth: samples whose error is known (truth available).
    inside_3sigma: (x, y, z) fraction of those with |e_i| <= 3 sqrt(P_ii); 0.9973 if consistent.
    nees_mean: mean NEES over them; 3 if consistent.
    updates: accelerometer updates with a finite NIS.
    nis_inside: fraction of those inside `chi2_band(3)`; 0.95 if consistent.
    nis_mean, nis_mean_band: mean NIS and its acceptance region (`mean_band`).
    skipped: samples after the reset without an accelerometer update (gated, invalid or
        non-finite accelerometer, accelerometer off).
    rest, guarded: samples with a rest bias update; with the chi-square guard holding the bias
        (None where the filter records no such thing).
    """

    samples: int
    samples_with_truth: int
    inside_3sigma: tuple[float, float, float]
    nees_mean: float
    updates: int
    nis_inside: float
    nis_mean: float
    nis_mean_band: tuple[float, float]
    skipped: int
    rest: int | None
    guarded: int | None

    @property
    def nis_mean_inside(self) -> bool:
        """Whether the mean NIS lies in its acceptance region (False without updates)."""
        lo, hi = self.nis_mean_band
        return bool(lo <= self.nis_mean <= hi)


def summarize(belief: Belief) -> Summary:
    """The `Summary` of one filter on one recording (see the module docstring for the tests)."""
    known = np.all(np.isfinite(belief.err_rad), axis=1) & np.all(np.isfinite(belief.sigma_rad), axis=1)
    count = int(known.sum())
    if count:
        inside = np.abs(belief.err_rad[known]) <= N_SIGMA * belief.sigma_rad[known]
        fractions = tuple(float(v) for v in inside.mean(axis=0))
        finite_nees = belief.nees[known][np.isfinite(belief.nees[known])]
        nees_mean = float(finite_nees.mean()) if finite_nees.size else float("nan")
    else:
        fractions, nees_mean = (float("nan"),) * 3, float("nan")
    nis = belief.nis[np.isfinite(belief.nis)]
    lo, hi = chi2_band(NIS_DOF)
    n = len(belief)
    return Summary(
        samples=n,
        samples_with_truth=count,
        inside_3sigma=fractions,
        nees_mean=nees_mean,
        updates=int(nis.size),
        nis_inside=float(np.mean((nis >= lo) & (nis <= hi))) if nis.size else float("nan"),
        nis_mean=float(nis.mean()) if nis.size else float("nan"),
        nis_mean_band=mean_band(int(nis.size)),
        skipped=int(belief.skipped.sum()),
        rest=None if belief.rest is None else int(belief.rest.sum()),
        guarded=None if belief.guarded is None else int(belief.guarded.sum()),
    )
