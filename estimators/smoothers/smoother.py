"""What the batch smoothers `gn` and `gd` share: their parameters, the start trajectory and
`BatchSmoother.estimate`.

Both minimise a cost of `fusion.estimators.smoothers.cost`; `SmootherParams.weights()` turns the
parameters into its `Weights`. Their cost defaults are the same (the noise-model weighting with
the robust loss, the velocity model and gyro calibration variables); they differ in their
solver (Levenberg-Marquardt in `fusion.estimators.smoothers.gn`, preconditioned gradient descent with a
line search in `fusion.estimators.smoothers.gd`) and in the solver's settings. Both start from dead
reckoning re-levelled with the accelerometer (`levelled`).

The initial estimator is one of a few recursive filters (`INIT_ESTIMATORS`), imported from their
modules directly, so this module does not depend on the registry in `fusion.estimators`.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np
from scipy.special import chdtri

from fusion import quaternion as quat
from fusion.checks import dropout_mask
from fusion.quaternion import rotation_matrix
from fusion.types import ImuSamples, Trajectory

from ..base import Estimator
from ..dr import DeadReckoning
from ..filters.steps._error_state import axes_mask
from ..filters.ekf import EKF
from ..filters.steps._rest import REST_ACC_G, REST_GYR_RAD_S, REST_TIME_S
from ..filters.ukf import UKF, UKFBias
from ..params import SMOOTHER_FORMER_STD, FormerSpellings, make_params, parse_specs
from ..search import Tunable
from .cost import AXES, LOSSES, Linearization, SmootherProblem, Weights, sample_durations
from .mag import MagSettings, heading_correction, measurements
from .solve import solve_normal_equations, theta_posterior_std

# Estimators that may start the optimisation (`SmootherParams.init`), by registry name.
INIT_ESTIMATORS: dict[str, type[Estimator]] = {"dr": DeadReckoning, "ukf": UKF, "ukf-bias": UKFBias, "ekf": EKF}


@dataclass(frozen=True)
class SmootherParams(FormerSpellings):
    """Parameters shared by `gn` and `gd` (the cost), plus the initialisation.

    Every noise and prior parameter is a variance, as in the filters (`FilterParams`, with the
    same names where the two mean the same), and noise levels are variance densities of
    continuous-time white noise, so one value means the same at any sampling rate (see
    `fusion.estimators.smoothers.cost.Weights`); the former standard-deviation spellings (sg,
    sa, p0, sdrop, sv, vb, srest, mwalk, bias_prior_rad_s, scale_prior) are accepted for one
    release, squared, with a warning (`fusion.estimators.params.FORMERLY_STD`):
    process_noise_rad2_s (Q): gyro noise density, rad^2/s; a step of dt s has angle variance
        Q dt.
    acc_noise_g2_s (R): accelerometer noise density, g^2 s; a sample standing for dt s has
        variance R / dt.
    loss: robust loss on the accelerometer residual: "huber", "cauchy", "geman-mcclure", "none".
    loss_scale_g (huber, the alias it had when the loss was always Huber): the loss's scale on
        the accelerometer residual norm, g (inf: plain least squares).
    init_var_rad2 (P0): variance of the anchor of the first orientation at the initial one, rad^2.
    dropout_noise_rad2_s (Qdrop): angle random walk density where `gyr_valid` is False, rad^2/s.
    use_gyr_valid (dropout): honour `imu.gyr_valid` (False: integrate every sample).
    find_freezes (freezes): with use_gyr_valid, gyro freezes that nobody flagged (`--dropouts
        off`, or an IMU whose freezes the loader does not know) are found over the whole
        recording (`fusion.checks.detect_freezes`: all gyro channels flat while the accelerometer
        moves) and treated as invalid, as the filters' online check (`stuck`) treats them; on
        samples whose freezes are already flagged it finds the same ones.
    bias_axes (bias): gyro bias variables, e.g. "xy" ("" or "none": none). scale_axes (scale):
        scale errors, likewise.
    init_bias_var_rad2_s2 (Pb0), init_scale_var (Ps0): prior variance of those variables
        around zero, (rad/s)^2 and dimensionless.
    scale_release_ratio (release): a requested scale error is estimated only if the recording
        determines it: its posterior std at the stage-1 solution (scales held at zero) is
        below this fraction of its prior std (`released_scales`); the others stay zero.
        Stage 1 ends at `tol` or after half of `max_iter`; stage 2 then has at least `max_iter`.
    scale_significance (sig): released scale errors are kept only if they lower the cost
        significantly at this level (a likelihood-ratio test, `BatchSmoother.significant_scales`;
        1: no test).
    scale_max: a scale error estimated beyond this (in either direction) is not a gyro's but
        the fit absorbing motion the cost does not model; that axis is solved again with its
        scale error held at zero (diagnostics "scale_rejected").
    velocity_acc_noise_g2_s (Qv), velocity_bound_m2_s (Rv): the horizontal velocity model (see
        `fusion.estimators.smoothers.cost`), g^2 s and m^2/s; inf switches it off.
    rest_gyr_rad_s, rest_acc_g, rest_time_s: rest detection (the filters' `RestDetector`, with
        their thresholds); rest_noise_rad2_s (Rrest): density of the gyro reading at rest in
        the rest term (`smoothers.cost`), rad^2/s. Where the recording is at rest, the biases with a
        variable are pulled to what the gyro reads there; an axis without one takes that
        reading as a fixed bias. Rest detection is off with weighting="scalar" or no bias axes.

    Defaults, one set for every IMU: the accelerometer is trusted as a gravity sensor only on
    average (R = 0.04 g^2 s, a standard deviation density of 0.2 g sqrt(s): a hand-held or
    body-worn motion's linear accelerations are tenths of a g, correlated over fractions of a
    second), while the velocity model keeps the world-frame linear acceleration's integral
    bounded (the fact VQF's inertial-frame low-pass rests on: Laidig & Seel 2023); the x and y
    gyro biases and scale errors are variables (prior standard deviations 0.05 rad/s and 10 %,
    a consumer MEMS gyro's tolerances), the z bias is read at
    rest (as VQF's rest bias estimation, Sec. 3.4, does), and the rest term is loose (Rrest =
    1e-4 rad^2/s): a MEMS bias moves between rests, and a tight term forces one constant
    bias on the motion between them. A z bias variable would see the z axis's scale error and
    the dropouts on the course board, which spoil its heading. Scale errors are kept only where
    the recording determines them and they lower the cost significantly: on the course board
    (x and y read 8 and 5 % high) they do, on BROAD's IMU (well within 1 %) only on one trial;
    without the significance test, the fast-translation trial fits -5 and -4 % and loses 0.3
    deg of inclination. The figures these defaults reach are in the README's Results section
    and `docs/results.md`, with the commands.
    weighting: "noise" (information matrices from the noise variances above) or "scalar" (one
        scalar weight per term: motion `scalar_motion_weight`, accelerometer 1, no robust loss,
        no velocity model). "seed", its former name, is still accepted, with a warning.
    scalar_motion_weight (wm): the motion term's weight with weighting="scalar".
    init: estimator whose output starts the optimisation ("dr", "ukf", ...).
    init_level_s (level): re-level the start every this many seconds with the accelerometer
        (`levelled`; 0: the init estimator's output as it is).
    max_iter (iters), tol: stopping rule (relative cost decrease below tol). At 1e-4 what is
        left is mostly the heading of long recordings, which a gyro and an accelerometer barely
        observe: with 1e-5, `gn` takes 43 iterations instead of 28 on an hour at 100 Hz
        (`benchmarks/bench_long.py`), for the same BROAD and course scores.
    presolve_tol_rad (ptol): on a recording with a magnetometer (mag_term="cost"), the 6-D solve
        that the magnetometer's measurements are taken at holds the scale errors at zero and
        stops as soon as an accepted step changes no sample's inclination by more than this,
        rad (`inclination_step`; 0: it solves to `tol`, in two stages). Those measurements see
        the 6-D solution's inclination only (`smoothers.mag.measurements`), and the 9-D solve
        that follows estimates the calibration again and converges the heading; what the 6-D
        solve would still do after the inclination has settled is mostly a slow drift of its
        heading, which only the velocity model observes (through the horizontal accelerations
        it rotates): 4 of its 30 iterations on BROAD trial 15.
    progress: tqdm bar over iterations on stderr (shown only on a terminal).
    impl: "compiled" (default: cost, linearisation and solves in the numba kernels of
        `fusion.estimators.smoothers._compiled`) or "numpy" (the reference they are checked
        against: `SmootherProblem` and the banded LAPACK solves). The two differ in rounding only.

    The magnetometer (9-D; recordings with one, `--mag off` or none: the 6-D result unchanged)
    corrects the heading only. By default (mag_term="cost") its heading residual is a term of
    the cost (`smoothers.cost`, the magnetometer term), with the gates, hard-iron fit and measured
    headings of `fusion.estimators.smoothers.mag.measurements` taken at the 6-D solution (solved
    until its inclination has settled, `presolve_tol_rad`), which the cost is then solved again
    from; the motion term then sets how fast the heading may follow the magnetometer (sqrt(Rm /
    Q), about 30 s). mag_term="stage"
    instead corrects the 6-D solution afterwards (`smoothers.mag.heading_correction`: a
    heading-error random walk of density Qm, started at the anchor's variance `init_var_rad2`,
    smoothed over the same headings), a rotation about the world vertical that leaves the
    inclination exactly as in 6-D.
    mag_term (mterm): "cost" or "stage", as above.
    mag_heading_noise_rad2_s (Rm): density of the magnetometer's heading measurement, rad^2 s
        (sample variance Rm / dt).
    mag_heading_walk_rad2_s (Qm): mag_term="stage" only: density of the 6-D solution's
        heading-error random walk, rad^2/s; more than the gyro's noise density, since it also
        carries what the 6-D cost leaves unmodelled about the vertical (the z gyro's scale
        error, its bias between rests). With Rm it sets the stage's time constant,
        sqrt(Rm / Qm) (about 10 s).
    mag_rate_rad_s (mrate): that variance grows as (1 + (w / mrate)^2), w the rate about the
        vertical, rad/s (a magnetometer lagging the gyro; inf: constant).
    mag_loss (mloss), mag_loss_scale_rad (mhuber): robust loss on the heading residual and its
        scale, rad ("none": plain least squares).
    mag_norm_gate_frac (mnorm), mag_dip_gate_rad (mdip): a sample counts while its norm is
        within this fraction of the reference norm and its dip within this of the reference
        dip, rad (the references: medians of the recording's own undisturbed samples) ...
    mag_min_undisturbed_s (mtime): ... in an uninterrupted run of such samples this long, s.
    mag_hard_iron (mhi): fit a magnet carried with the sensor (a sphere fit over each disturbed
        stretch, else over windows of mag_hard_iron_window_s (mhiw) s) and use its samples
        with the offset removed; the fit is trusted with an RMS residual below
        mag_hard_iron_residual_ut (mhires) uT and a spread of at least mag_hard_iron_coverage
        (mhicov) of its radius (the filters' `_magnetometer.hard_iron_fit`).
    The magnetometer's defaults are the filters' (`BiasFilterParams`) where they mean the same.
    """

    owner: ClassVar[str] = "gn"  # the registry name in messages
    former_std: ClassVar[tuple[str, ...]] = SMOOTHER_FORMER_STD  # `AcceptsFormerSpellings`

    # Search ranges (`fusion.estimators.search`): noise densities two decades either side of the
    # default; the grid (Q x R x huber, 27 settings) a factor of about 3 (R: 4) either side. R's grid
    # is the standard deviation densities 0.1, 0.2 and 0.4 g sqrt(s); the loss scale's spans a decade
    # either side of 0.1 g, the size of a hand's linear accelerations (tenths of a g).
    process_noise_rad2_s: float = field(default=1e-4, metadata={
        "alias": "Q", "search": Tunable(1e-6, 1e-2, grid=(3e-5, 1e-4, 3e-4))})
    acc_noise_g2_s: float = field(default=0.04, metadata={
        "alias": "R", "search": Tunable(4e-4, 4.0, grid=(0.01, 0.04, 0.16))})
    loss: Literal["huber", "cauchy", "geman-mcclure", "none"] = "huber"
    loss_scale_g: float = field(default=0.1, metadata={
        "alias": "huber", "search": Tunable(0.01, 1.0, grid=(0.03, 0.1, 0.3))})
    init_var_rad2: float = field(default=1e-4, metadata={"alias": "P0"})
    dropout_noise_rad2_s: float = field(default=0.09, metadata={"alias": "Qdrop"})
    use_gyr_valid: bool = field(default=True, metadata={"alias": "dropout"})
    find_freezes: bool = field(default=True, metadata={"alias": "freezes"})
    bias_axes: str = field(default="xy", metadata={"alias": "bias"})
    scale_axes: str = field(default="xy", metadata={"alias": "scale"})
    init_bias_var_rad2_s2: float = field(default=2.5e-3, metadata={"alias": "Pb0"})
    init_scale_var: float = field(default=1e-2, metadata={"alias": "Ps0"})
    scale_max: float = 0.2
    scale_release_ratio: float = field(default=0.5, metadata={"alias": "release"})
    scale_significance: float = field(default=0.05, metadata={"alias": "sig"})
    # two decades either side of the defaults, no grid
    velocity_acc_noise_g2_s: float = field(default=1e-4, metadata={"alias": "Qv", "search": Tunable(1e-6, 1e-2)})
    velocity_bound_m2_s: float = field(default=0.25, metadata={"alias": "Rv", "search": Tunable(2.5e-3, 25.0)})
    rest_gyr_rad_s: float = REST_GYR_RAD_S
    rest_acc_g: float = REST_ACC_G
    rest_time_s: float = REST_TIME_S
    rest_noise_rad2_s: float = field(default=1e-4, metadata={"alias": "Rrest"})
    weighting: Literal["noise", "scalar", "seed"] = "noise"
    scalar_motion_weight: float = field(default=10.0, metadata={"alias": "wm"})
    init: str = "dr"
    init_level_s: float = field(default=10.0, metadata={"alias": "level"})
    max_iter: int = field(default=50, metadata={"alias": "iters"})
    tol: float = 1e-4
    presolve_tol_rad: float = field(default=math.radians(0.01), metadata={"alias": "ptol"})
    progress: bool = True
    impl: Literal["compiled", "numpy"] = "compiled"
    # two decades either side (benchmarks/broad_9d_smoothers.py --leave-one-out tries 0.03-0.3); the
    # unit is rad^2 s, not the rad^2/s its suffix reads as elsewhere (a measurement's density)
    mag_heading_noise_rad2_s: float = field(default=0.1, metadata={
        "alias": "Rm", "unit": "rad^2 s", "search": Tunable(1e-3, 10.0, magnetometer=True)})
    mag_heading_walk_rad2_s: float = field(default=9e-4, metadata={"alias": "Qm"})
    mag_rate_rad_s: float = field(default=2.0, metadata={"alias": "mrate"})
    mag_loss: Literal["huber", "cauchy", "geman-mcclure", "none"] = field(default="huber", metadata={"alias": "mloss"})
    mag_loss_scale_rad: float = field(default=0.1, metadata={"alias": "mhuber"})
    mag_norm_gate_frac: float = field(default=0.1, metadata={"alias": "mnorm"})
    mag_dip_gate_rad: float = field(default=math.radians(10.0), metadata={"alias": "mdip"})
    mag_min_undisturbed_s: float = field(default=3.0, metadata={"alias": "mtime"})
    mag_hard_iron: bool = field(default=True, metadata={"alias": "mhi"})
    mag_hard_iron_window_s: float = field(default=10.0, metadata={"alias": "mhiw"})
    mag_hard_iron_residual_ut: float = field(default=2.0, metadata={"alias": "mhires"})
    mag_hard_iron_coverage: float = field(default=0.3, metadata={"alias": "mhicov"})
    mag_term: Literal["cost", "stage"] = field(default="cost", metadata={"alias": "mterm"})

    def __post_init__(self) -> None:
        if self.weighting == "seed":  # the former name of "scalar", to be removed
            warnings.warn('weighting="seed" is now called "scalar"; "seed" will be removed in the next release',
                          FutureWarning, stacklevel=3)
            object.__setattr__(self, "weighting", "scalar")
        for name in ("process_noise_rad2_s", "acc_noise_g2_s", "loss_scale_g", "init_var_rad2", "dropout_noise_rad2_s",
                     "init_bias_var_rad2_s2", "init_scale_var", "scalar_motion_weight", "velocity_acc_noise_g2_s",
                     "velocity_bound_m2_s", "rest_noise_rad2_s"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"{name}={value!r}: must be positive")
            if value == np.inf and name not in ("acc_noise_g2_s", "loss_scale_g", "velocity_acc_noise_g2_s",
                                                "velocity_bound_m2_s"):  # inf: no such term (R: no accelerometer)
                raise ValueError(f"{name}={value!r}: must be finite")
        for name in ("bias_axes", "scale_axes"):  # "none" (as typed on a command line) is ""
            if getattr(self, name) == "none":
                object.__setattr__(self, name, "")
            axes_mask(getattr(self, name), name)
        if not 0 <= self.init_level_s < np.inf:
            raise ValueError(f"init_level_s={self.init_level_s!r}: must be >= 0 and finite (0: off)")
        if 0 < self.init_level_s < 0.1:  # one window per level step: a shorter one averages no motion out
            raise ValueError(f"init_level_s={self.init_level_s!r}: must be 0 (off) or at least 0.1 s")
        for name in ("rest_gyr_rad_s", "rest_acc_g", "rest_time_s", "scale_max"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)!r}: must be positive (rest_time_s=inf: no rest detection)")
        for name in ("rest_gyr_rad_s", "rest_acc_g"):
            if getattr(self, name) == np.inf:
                raise ValueError(f"{name}={getattr(self, name)!r}: must be finite (rest_time_s=inf: no rest detection)")
        if not 0 < self.scale_significance <= 1:
            raise ValueError(f"scale_significance={self.scale_significance!r}: must be in (0, 1] (1: no test)")
        if not 0 < self.scale_release_ratio <= 1:
            raise ValueError(f"scale_release_ratio={self.scale_release_ratio!r}: must be in (0, 1]")
        if self.max_iter < 1:
            raise ValueError(f"max_iter={self.max_iter}: must be at least 1")
        if not 0 <= self.tol < np.inf:
            raise ValueError(f"tol={self.tol!r}: must be >= 0 and finite")
        if not 0 <= self.presolve_tol_rad < np.inf:
            raise ValueError(f"presolve_tol_rad={self.presolve_tol_rad!r}: must be >= 0 and finite (0: solve to tol)")
        if self.impl not in ("compiled", "numpy"):
            raise ValueError(f"impl={self.impl!r}: must be compiled or numpy")
        for name in ("mag_heading_noise_rad2_s", "mag_heading_walk_rad2_s", "mag_loss_scale_rad", "mag_norm_gate_frac", "mag_dip_gate_rad",
                     "mag_hard_iron_window_s", "mag_hard_iron_residual_ut", "mag_hard_iron_coverage"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 < value < np.inf):
                raise ValueError(f"{name}={value!r}: must be a finite number > 0")
        if not self.mag_rate_rad_s > 0:
            raise ValueError(f"mag_rate_rad_s={self.mag_rate_rad_s!r}: must be > 0 (inf: no rate term)")
        if not 0 <= self.mag_min_undisturbed_s < np.inf:
            raise ValueError(f"mag_min_undisturbed_s={self.mag_min_undisturbed_s!r}: must be >= 0 and finite")
        if self.mag_term not in ("stage", "cost"):
            raise ValueError(f"mag_term={self.mag_term!r}: must be stage or cost")
        if self.mag_loss not in LOSSES:
            raise ValueError(f"mag_loss={self.mag_loss!r}: expected one of {', '.join(LOSSES)}")

    def mag_settings(self) -> MagSettings:
        """The magnetometer stage's settings (`fusion.estimators.smoothers.mag`)."""
        return MagSettings(
            heading_noise_rad2_s=self.mag_heading_noise_rad2_s, heading_walk_rad2_s=self.mag_heading_walk_rad2_s,
            init_var_rad2=self.init_var_rad2, rate_rad_s=self.mag_rate_rad_s, loss=self.mag_loss,
            loss_scale_rad=self.mag_loss_scale_rad, norm_gate_frac=self.mag_norm_gate_frac,
            dip_gate_rad=self.mag_dip_gate_rad, min_undisturbed_s=self.mag_min_undisturbed_s,
            hard_iron=self.mag_hard_iron, hard_iron_window_s=self.mag_hard_iron_window_s,
            hard_iron_residual_ut=self.mag_hard_iron_residual_ut, hard_iron_coverage=self.mag_hard_iron_coverage,
        )

    def weights(self) -> Weights:
        """The cost's `Weights` (one scalar weight per term when weighting="scalar")."""
        scalar = self.weighting == "scalar"
        return Weights(
            process_noise_rad2_s=self.process_noise_rad2_s, acc_noise_g2_s=self.acc_noise_g2_s,
            loss="none" if scalar else self.loss, loss_scale_g=np.inf if scalar else self.loss_scale_g,
            init_var_rad2=self.init_var_rad2, dropout_noise_rad2_s=self.dropout_noise_rad2_s,
            motion_weight=self.scalar_motion_weight if scalar else None, acc_weight=1.0 if scalar else None,
            bias_axes=self.bias_axes, scale_axes=self.scale_axes,
            init_bias_var_rad2_s2=self.init_bias_var_rad2_s2, init_scale_var=self.init_scale_var,
            velocity_acc_noise_g2_s=np.inf if scalar else self.velocity_acc_noise_g2_s,
            velocity_bound_m2_s=np.inf if scalar else self.velocity_bound_m2_s,
            rest_noise_rad2_s=self.rest_noise_rad2_s,
        )


def initial_trajectory(init: str, owner: str, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> np.ndarray:
    """(T, 4) starting point: the output of the recursive estimator `init` (e.g. "dr", "ukf:R=1e-3").

    `init` is one of `INIT_ESTIMATORS` with optional parameters, as on the command line.
    """
    (spec,) = parse_specs(init)
    if spec.name == owner:
        raise ValueError(f"{owner}: init={init!r} would initialise the smoother with itself")
    try:
        cls = INIT_ESTIMATORS[spec.name]
    except KeyError:
        raise ValueError(f"{owner}: init={init!r}: expected one of {', '.join(INIT_ESTIMATORS)}") from None
    est = cls(make_params(cls.Params, spec.overrides, owner=spec.name))
    quat_wxyz = np.array(est.estimate(imu, init_quat_wxyz).quat_wxyz, dtype=float)
    if not np.all(np.isfinite(quat_wxyz)):
        raise ValueError(f"{owner}: initial estimator {init!r} returned non-finite orientations")
    return quat_wxyz / np.linalg.norm(quat_wxyz, axis=1, keepdims=True)


def levelled(imu: ImuSamples, quat_wxyz: np.ndarray, window_s: float) -> np.ndarray:
    """(T, 4) the trajectory quat_wxyz (T, 4) with its tilt corrected window by window.

    Over a window of `window_s` seconds the world-frame specific force R(q_t) a_t averages
    to gravity, e_z (a hand's or a body's linear acceleration averages out: its velocity
    stays bounded). Each window is turned, as a whole, by the smallest rotation that takes its
    average direction to e_z (a rotation about a horizontal axis: the heading is kept). This
    undoes a gyro-integrated start's tilt drift, which on a long recording reaches 180 deg
    (an upside-down start, from which the accelerometer's pull, proportional to the sine of
    the tilt error, cannot bring the smoother back). The first window keeps the given initial
    orientation; the jumps between windows are left to the smoother. O(T), vectorised.
    """
    R = rotation_matrix(quat_wxyz)
    acc_ok = np.all(np.isfinite(imu.acc_g), axis=1)
    acc = np.where(acc_ok[:, None], imu.acc_g, 0.0)
    f_world = (R @ acc[:, :, None])[:, :, 0]  # g
    weight = sample_durations(imu.t) * acc_ok
    window = np.floor((imu.t - imu.t[0]) / window_s).astype(int)
    n = window[-1] + 1
    mean = np.stack([np.bincount(window, weights=weight * f_world[:, j], minlength=n) for j in range(3)], axis=1)
    norm = np.linalg.norm(mean, axis=1)
    up = mean / np.where(norm > 0, norm, 1.0)[:, None]
    axis = np.cross(up, [0.0, 0.0, 1.0])  # rotation taking `up` to e_z: about up x e_z by the angle between them
    sin = np.linalg.norm(axis, axis=1)
    angle = np.arctan2(sin, up[:, 2])
    rotvec = axis * (angle / np.where(sin > 0, sin, 1.0))[:, None]
    rotvec[(norm == 0) | (sin == 0)] = 0.0
    correction = quat.from_rotvec(rotvec)  # world frame: applied on the left
    out = np.array(quat_wxyz, dtype=float)
    later = window > 0  # the first window keeps the given start
    out[later] = quat.normalize(quat.multiply(correction[window[later]], out[later]))
    return out


def progress_bar(enabled: bool, total: int, desc: str):
    """A tqdm bar on stderr, shown only on a terminal (disable=None), or a no-op."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, file=sys.stderr, disable=None if enabled else True, leave=False)


class SolverLog:
    """What both solvers record at the start and after every accepted step: the cost ("loss"),
    the largest deviation of a quaternion's norm from 1 ("norm_error"; the retraction keeps it
    at rounding level) and the time since the start ("elapsed_s"). measure: the function that
    measures it (the ops' `norm_error`; None: `norm_error`)."""

    def __init__(self, cost: float, q: np.ndarray, measure=None) -> None:
        self._start = time.perf_counter()
        self._norm_error = norm_error if measure is None else measure
        self.loss, self.norm_error, self.elapsed_s = [cost], [self._norm_error(q)], [0.0]

    def record(self, cost: float, q: np.ndarray) -> None:
        self.loss.append(cost)
        self.norm_error.append(self._norm_error(q))
        self.elapsed_s.append(time.perf_counter() - self._start)

    def diagnostics(self, iterations: int, converged: bool) -> dict:
        return {"loss": np.array(self.loss), "elapsed_s": np.array(self.elapsed_s),
                "norm_error": np.array(self.norm_error), "iterations": iterations, "converged": converged}


def norm_error(q: np.ndarray) -> float:
    """max |(|q_t|) - 1| over q (T, 4): how far the retraction has let the quaternions drift off the sphere."""
    return float(np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)))


def solution_diagnostics(problem: SmootherProblem, theta: np.ndarray, theta_std: np.ndarray, released: np.ndarray,
                         v: np.ndarray) -> dict:
    """A solution's diagnostics, the same for `gn` and `gd`: the calibration variables `theta`
    (split into "gyr_bias_rad_s" and "gyr_scale_error", with their names, posterior std
    `theta_std` and prior std), which scale errors were released (`released`) and the
    velocity `v` ("velocity_m_s", m/s)."""
    bias, scale = problem.split_theta(theta)
    return {"gyr_bias_rad_s": bias, "gyr_scale_error": scale, "theta_names": problem.theta_names(), "theta": theta,
            "theta_std": theta_std, "theta_prior_std": 1.0 / np.sqrt(problem.w_theta), "scale_released": released,
            "velocity_m_s": v}


def inclination_step(q: np.ndarray, delta: np.ndarray) -> float:
    """The largest change of inclination (rad) that the rotation steps delta (T, 3) (body frame,
    `retract`'s) make at q (T, 4): each step's part about a horizontal axis, |delta - (delta.v) v|
    with v = R(q)^T e_z the vertical in the body frame (a turn about v changes only the heading)."""
    across = np.cross(delta, quat.gravity_in_body(q))  # |delta x v| = |delta - (delta.v) v|, v a unit vector
    return float(np.sqrt(np.max(np.einsum("ti,ti->t", across, across), initial=0.0)))


def retract(q: np.ndarray, delta: np.ndarray, update: str = "geodesic") -> np.ndarray:
    """Move q (T, 4) by the tangent steps delta (T, 3) rad, body frame, and stay on the sphere:
    "geodesic" q * exp([0, delta / 2]) (the exponential map), "normalise" normalise(q + q *
    [0, delta / 2]) (the projection retraction; Absil, Mahony & Sepulchre 2008, "Optimization
    Algorithms on Matrix Manifolds", sec. 4.1)."""
    if update == "geodesic":
        return quat.retract(q, delta)
    tangent = 0.5 * quat.multiply(q, np.concatenate([np.zeros((len(q), 1)), delta], axis=1))
    return quat.normalize(q + tangent)


class ReferenceOps:
    """What the solvers do with the cost, in numpy: the reference of the compiled kernels
    (`smoothers._compiled.CompiledOps`, the same interface).

    `linearize` takes the `shift` and `free` of the solve that will follow only as a hint (the
    kernels eliminate in the same pass); `solve` is the damped Gauss-Newton step of `gn`."""

    def __init__(self, problem: SmootherProblem) -> None:
        self.problem = problem
        self.norm_error = norm_error

    def cost(self, q: np.ndarray, theta: np.ndarray, v: np.ndarray) -> float:
        return self.problem.cost(q, theta, v)

    def trial(self, q: np.ndarray, v: np.ndarray, theta: np.ndarray, d_q: np.ndarray, d_theta: np.ndarray, alpha: float,
              update: str = "geodesic") -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(q, v, theta) moved by alpha times the step (d_q (T, B), d_theta (P,)), q retracted
        by `update` (`retract`), and the cost there: (q_new, v_new, theta_new, cost)."""
        q_new = retract(q, alpha * d_q[:, :3], update)
        v_new = v + alpha * d_q[:, 3:]
        theta_new = theta + alpha * d_theta
        return q_new, v_new, theta_new, self.problem.cost(q_new, theta_new, v_new)

    def slope(self, lin: Linearization, d_q: np.ndarray, d_theta: np.ndarray) -> float:
        """g.p: lin's gradient along the step (d_q (T, B), d_theta (P,))."""
        return float(np.sum(lin.grad_q * d_q) + lin.grad_theta @ d_theta)

    def linearize(self, q: np.ndarray, theta: np.ndarray, v: np.ndarray, hessian: bool = True, shift: float | None = None,
                  free: np.ndarray | None = None, gradient: bool = True) -> Linearization:
        """`SmootherProblem.linearize` (shift, free: the next solve's; gradient=False: the caller
        does not read grad_q; hints for the kernels)."""
        return self.problem.linearize(q, theta, hessian=hessian, v=v)

    def solve(self, lin: Linearization, shift: float, free: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """-(H + shift diag(H))^-1 g for the calibration variables `free` ((P,) bool; None: all;
        the others get no step): ((T, B), (P,))."""
        if free is None:
            return solve_normal_equations(lin, shift)
        d_theta = np.zeros(len(lin.grad_theta))
        sub = dataclasses.replace(lin, grad_theta=lin.grad_theta[free], cross=lin.cross[:, :, free],
                                  theta_block=lin.theta_block[np.ix_(free, free)])
        d_q, d_theta[free] = solve_normal_equations(sub, shift)
        return d_q, d_theta

    def theta_std(self, q: np.ndarray, theta: np.ndarray, v: np.ndarray, lin: Linearization | None = None) -> np.ndarray:
        """(P,) the calibration variables' posterior std at (q, theta, v) (`theta_posterior_std`;
        lin: the linearisation there, with its Hessian, if the caller has it)."""
        return theta_posterior_std(self.problem.linearize(q, theta, v=v) if lin is None else lin)


class BatchSmoother(Estimator):
    """What `gn` and `gd` share: the problem set-up, the start trajectory and `estimate`;
    each supplies `solve(problem, q) -> (q, diagnostics)`, which works on the cost through
    `operations(problem)`: the compiled kernels or their numpy reference (`impl`)."""

    Params = SmootherParams
    causal = False
    name = ""
    magnetometer = True  # 9-D where the recording has a magnetometer: the heading term (`smoothers.mag`)

    def __init__(self, params=None) -> None:
        super().__init__(params)
        if self.params.impl == "compiled":
            from . import _compiled as _compiled_smoother  # numba is imported when a compiled smoother is built

            _compiled_smoother.load()  # compile or load the kernels here, not in the first (timed) estimate

    def operations(self, problem: SmootherProblem, blocks: bool = False):
        """The cost's operations for `solve`: `ReferenceOps` (impl="numpy") or the kernels'
        `CompiledOps` (blocks: its linearisations carry the Hessian's blocks too)."""
        if self.params.impl == "numpy":
            return ReferenceOps(problem)
        from ._compiled import CompiledOps

        return CompiledOps(problem, blocks=blocks)

    def problem(self, imu: ImuSamples, init_quat_wxyz: np.ndarray, scale_axes: str | None = None) -> SmootherProblem:
        """The cost of `imu`; scale_axes: the scale-error variables (None: the parameters')."""
        p = self.params if scale_axes is None else dataclasses.replace(self.params, scale_axes=scale_axes)
        rest = None
        if p.weighting == "noise" and p.bias_axes:
            from ..filters.steps._compiled_rest import rest_steps  # numba is imported on first use only

            rest = rest_steps(imu, p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s)
        return SmootherProblem.from_imu(imu, init_quat_wxyz, p.weights(), use_valid=p.use_gyr_valid, rest=rest)

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        p = self.params
        if len(imu) < 2:
            raise ValueError(f"{imu.source}: the smoother needs at least 2 samples, got {len(imu)}")
        if p.use_gyr_valid and p.find_freezes:
            imu = imu.replace(gyr_valid=dropout_mask(imu))  # freezes nobody flagged (`find_freezes`)
        problem = self.problem(imu, init_quat_wxyz)
        # 9-D with the heading term: the 6-D solve only has to settle the inclination (`presolve_tol_rad`)
        presolve = self.magnetometer and imu.has_mag and p.mag_term == "cost" and p.presolve_tol_rad > 0
        q, diagnostics = self.solve(problem, self.start(imu, init_quat_wxyz), presolve=presolve)
        q, diagnostics = self.significant_scales(problem, q, diagnostics)
        # A scale error beyond `scale_max` is not a gyro's: the fit has used it to absorb motion the
        # cost does not model (e.g. fast translation). Those axes are solved again with it held at 0.
        _, scale = problem.split_theta(diagnostics["theta"])
        implausible = "".join(a for a in p.scale_axes if abs(scale[AXES.index(a)]) > p.scale_max)
        if implausible:
            kept = "".join(a for a in p.scale_axes if a not in implausible)
            problem = self.problem(imu, init_quat_wxyz, scale_axes=kept)
            q, diagnostics = self.solve(problem, self.start(imu, init_quat_wxyz), presolve=presolve)  # the same start, again
            q, diagnostics = self.significant_scales(problem, q, diagnostics)
            diagnostics["scale_rejected"] = implausible
        if self.magnetometer and imu.has_mag:
            if p.mag_term == "stage":
                # 9-D: the heading-only correction of the 6-D solution (`smoothers.mag`)
                q, mag_diagnostics = heading_correction(imu, q, p.mag_settings())
                diagnostics.update(mag_diagnostics)
            else:
                # 9-D: the heading term in the cost, measured at the 6-D solution, solved again from there
                psi, info, mag_diagnostics = measurements(imu, q, p.mag_settings())
                if mag_diagnostics["mag_used"].any():
                    problem = problem.with_magnetometer(info, psi, q, p.mag_loss, p.mag_loss_scale_rad)
                if presolve or mag_diagnostics["mag_used"].any():  # without a heading term: the 6-D solve, to `tol`
                    q, diagnostics = self.solve(problem, q)
                    q, diagnostics = self.significant_scales(problem, q, diagnostics)
                diagnostics.update(mag_diagnostics)
        return Trajectory(imu.t, q, diagnostics=diagnostics)

    def start(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> np.ndarray:
        """(T, 4) the start of the optimisation: the `init` estimator's output, re-levelled every
        `init_level_s` seconds (`levelled`); with impl="compiled", dead reckoning and the
        levelling by the kernels (`smoothers._compiled_start.dead_reckoned`, `.levelled_trajectory`)."""
        p = self.params
        imu_init = imu.replace(gyr_valid=problem_valid(imu, p))
        if p.impl == "numpy":
            q = initial_trajectory(p.init, self.name, imu_init, init_quat_wxyz)
            return levelled(imu, q, p.init_level_s) if p.init_level_s > 0 else q
        from . import _compiled_start as kernels

        if p.init.strip() == "dr":
            q = kernels.dead_reckoned(imu_init, init_quat_wxyz)
            if not np.all(np.isfinite(q[-1])):
                raise ValueError(f"{self.name}: initial estimator {p.init!r} returned non-finite orientations")
        else:
            q = initial_trajectory(p.init, self.name, imu_init, init_quat_wxyz)
        return kernels.levelled_trajectory(imu, q, p.init_level_s) if p.init_level_s > 0 else q

    def significant_scales(self, problem: SmootherProblem, q: np.ndarray, diagnostics: dict) -> tuple[np.ndarray, dict]:
        """Keep the released scale errors only if they lower the cost significantly; otherwise
        return the stage-1 solution (scale errors at zero).

        Stage 1 is the model without the released scale errors, nested in stage 2's, and the
        cost is a negative log-likelihood (up to a constant), so 2 (c_1 - c_2) is the likelihood-
        ratio statistic, chi-square with k (the released scale errors) degrees of freedom if
        they are zero (Wilks 1938, "The large-sample distribution of the likelihood ratio for
        testing composite hypotheses", Ann. Math. Statist. 9). The scale errors are kept if it
        exceeds the chi-square quantile at 1 - `scale_significance`. The noise densities are
        set loose for robustness, which makes the statistic smaller than a calibrated one, so
        the test keeps fewer scale errors than its nominal level: on a recording where the
        fit could use a scale error to absorb unmodelled motion, it asks for the evidence of a
        real one. Diagnostics: "scale_lr" (the statistic; nan without a release), and
        "scale_released" all False when rejected ("loss" still records every iteration; the
        returned solution then has the cost where stage 1 ended).
        """
        stage1 = diagnostics.pop("stage1", None)
        released = np.asarray(diagnostics.get("scale_released", np.zeros(0)), bool)
        diagnostics["scale_lr"] = math.nan
        if stage1 is None or not released.any():
            return q, diagnostics
        q1, theta1, v1, cost1, theta_std1 = stage1
        lr = 2.0 * (cost1 - float(diagnostics["loss"][-1]))
        diagnostics["scale_lr"] = lr
        if lr > chdtri(int(released.sum()), self.params.scale_significance):
            return q, diagnostics
        diagnostics.update(solution_diagnostics(problem, theta1, theta_std1, np.zeros_like(released), v1))
        return q1, diagnostics

    def solve(self, problem: SmootherProblem, q: np.ndarray, presolve: bool = False) -> tuple[np.ndarray, dict]:
        """Minimise `problem` from q (T, 4); presolve: stop each stage once a step changes no
        sample's inclination by more than `presolve_tol_rad` (`inclination_step`), or at `tol`."""
        raise NotImplementedError


def problem_valid(imu: ImuSamples, p: SmootherParams) -> np.ndarray:
    """The validity mask the initialisation uses (all True when dropouts are switched off)."""
    return imu.gyr_valid if p.use_gyr_valid else np.ones(len(imu), bool)
