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
from dataclasses import dataclass
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
from ..filters.filter_params import HARD_IRON_FIT, VQF, BiasFilterParams
from ..filters.steps._rest import REST_ACC_G, REST_GYR_RAD_S, REST_TIME_S
from ..filters.ukf import UKF, UKFBias
from ..params import SMOOTHER_FORMER_STD, FormerSpellings, make_params, param, param_as, parse_specs
from ..search import Tunable
from .cost import AXES, LOSSES, Linearization, SmootherProblem, Weights, sample_durations
from .mag import MagSettings, heading_correction, measurements
from .solve import solve_normal_equations, theta_posterior_std

# The references the fields cite (each field's "reference" metadata, `fusion list gn`).
ARW = "IEEE Std 952-1997, Annex C (the angle random walk)"
M_ESTIMATORS = ('Huber 1964; Geman & McClure 1987; as tabulated by Zhang 1997, "Parameter estimation techniques: a '
                'tutorial with application to conic fitting", Image and Vision Computing 15')
RTS = ('Rauch, Tung & Striebel 1965, "Maximum likelihood estimates of linear dynamic systems", AIAA Journal 3(8)')

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
    release, squared, with a warning (`fusion.estimators.params.FORMERLY_STD`). Each field's unit,
    meaning, reference and valid range are at the field (`fusion list gn`). The axis options are
    `baxes` and `saxes` (`bias` and `scale`, their former aliases, are the filters' switches).

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
    The magnetometer's defaults are the filters' (`BiasFilterParams`) where they mean the same.

    Stopping: stage 1 (scale errors held at zero) ends at `tol` or after half of `max_iter`;
    stage 2, with the released scale errors, then has at least `max_iter`. At tol = 1e-4 what is
    left is mostly the heading of long recordings, which a gyro and an accelerometer barely
    observe: with 1e-5, `gn` takes 43 iterations instead of 28 on an hour at 100 Hz
    (`benchmarks/bench_long.py`), for the same BROAD and course scores. The 6-D solve under a
    magnetometer stops early (`presolve_tol_rad`) because the magnetometer's measurements see the
    6-D solution's inclination only (`smoothers.mag.measurements`), and the 9-D solve that follows
    estimates the calibration again and converges the heading; what the 6-D solve would still do
    after the inclination has settled is mostly a slow drift of its heading, which only the
    velocity model observes (through the horizontal accelerations it rotates): 4 of its 30
    iterations on BROAD trial 15.
    """

    owner: ClassVar[str] = "gn"  # the registry name in messages
    former_std: ClassVar[tuple[str, ...]] = SMOOTHER_FORMER_STD  # `AcceptsFormerSpellings`

    # Search ranges (`fusion.estimators.search`): noise densities two decades either side of the
    # default; the grid (Q x R x huber, 27 settings) a factor of about 3 (R: 4) either side. R's grid
    # is the standard deviation densities 0.1, 0.2 and 0.4 g sqrt(s); the loss scale's spans a decade
    # either side of 0.1 g, the size of a hand's linear accelerations (tenths of a g).
    process_noise_rad2_s: float = param(
        1e-4, alias="Q", unit="rad^2/s", valid="> 0, finite", reference=ARW,
        meaning="Gyro noise density: a step of dt s has the angle variance Q dt in the motion term.",
        search=Tunable(1e-6, 1e-2, grid=(3e-5, 1e-4, 3e-4)))
    acc_noise_g2_s: float = param(
        0.04, alias="R", unit="g^2 s", valid="> 0; inf: no accelerometer term",
        meaning="Accelerometer noise density: a sample standing for dt s has the variance R / dt.",
        search=Tunable(4e-4, 4.0, grid=(0.01, 0.04, 0.16)))
    loss: Literal["huber", "cauchy", "geman-mcclure", "none"] = param(
        "huber", unit="", valid="huber | cauchy | geman-mcclure | none", reference=M_ESTIMATORS,
        meaning="The robust loss on the accelerometer residual's norm (none: plain least squares).")
    loss_scale_g: float = param(
        0.1, alias="huber", unit="g", valid="> 0; inf: plain least squares", reference=M_ESTIMATORS,
        meaning="The robust loss's scale on the accelerometer residual's norm (the alias is the one it had when the "
                "loss was always Huber's).",
        search=Tunable(0.01, 1.0, grid=(0.03, 0.1, 0.3)))
    init_var_rad2: float = param(1e-4, alias="P0", unit="rad^2", valid="> 0, finite",
                                 meaning="Variance of the anchor that holds the first orientation at the initial one.")
    dropout_noise_rad2_s: float = param(
        0.09, alias="Qdrop", unit="rad^2/s", valid="> 0, finite",
        meaning="Angle random-walk density of the motion term on the steps whose gyro sample is invalid.")
    use_gyr_valid: bool = param(True, alias="dropout", unit="", valid="true | false",
                                meaning="Honour `imu.gyr_valid` (false integrates every sample as valid).")
    find_freezes: bool = param(
        True, alias="freezes", unit="", valid="true | false; applies only with use_gyr_valid",
        meaning="Find the gyro freezes that nobody flagged over the whole recording (`fusion.checks.detect_freezes`: "
                "all channels flat while the accelerometer moves) and treat them as invalid, as the filters' online "
                "check (stuck) does.")
    bias_axes: str = param(
        "xy", alias="baxes", formerly=("bias",), unit="", valid="distinct letters from xyz, or none",
        meaning="The body axes with a gyro-bias variable; an axis without one takes the gyro's reading at rest as "
                "a fixed bias.")
    scale_axes: str = param(
        "xy", alias="saxes", formerly=("scale",), unit="", valid="distinct letters from xyz, or none",
        meaning="The body axes with a gyro scale-error variable.")
    init_bias_var_rad2_s2: float = param(
        2.5e-3, alias="Pb0", unit="rad^2/s^2", valid="> 0, finite",
        meaning="Prior variance of each gyro-bias variable around zero.")
    init_scale_var: float = param(1e-2, alias="Ps0", unit="1", valid="> 0, finite",
                                  meaning="Prior variance of each scale-error variable around zero.")
    scale_max: float = param(
        0.2, unit="1", valid="> 0",
        meaning="A scale error estimated beyond this, in either direction, is taken for the fit absorbing motion the "
                "cost does not model, and that axis is solved again with its scale error held at zero (diagnostics "
                "scale_rejected).")
    scale_release_ratio: float = param(
        0.5, alias="release", unit="1", valid="(0, 1]",
        meaning="A requested scale error is estimated only if the recording determines it, its posterior standard "
                "deviation at the stage-1 solution (scales held at zero) being below this fraction of its prior "
                "one (`released_scales`); the others stay zero.")
    scale_significance: float = param(
        0.05, alias="sig", unit="1", valid="(0, 1]; 1: no test",
        meaning="Released scale errors are kept only if they lower the cost significantly at this level, by a "
                "likelihood-ratio test (`BatchSmoother.significant_scales`).")
    # two decades either side of the defaults, no grid
    velocity_acc_noise_g2_s: float = param(
        1e-4, alias="Qv", unit="g^2 s", valid="> 0; inf: no velocity model", reference=VQF + ", Sec. 3.2",
        meaning="Density of the white acceleration noise in the velocity model's integration of the world-frame "
                "acceleration into the horizontal velocity (`fusion.estimators.smoothers.cost`).",
        search=Tunable(1e-6, 1e-2))
    velocity_bound_m2_s: float = param(
        0.25, alias="Rv", unit="m^2/s", valid="> 0; inf: no velocity model", reference=VQF + ", Sec. 3.2",
        meaning="Density of the pseudo-measurement v = 0 on the horizontal velocity in the velocity model, which "
                "keeps the integral of the linear acceleration bounded.",
        search=Tunable(2.5e-3, 25.0))
    rest_gyr_rad_s: float = param_as(BiasFilterParams, "rest_gyr_rad_s", REST_GYR_RAD_S,
                                     valid="> 0, finite")
    rest_acc_g: float = param_as(BiasFilterParams, "rest_acc_g", REST_ACC_G, valid="> 0, finite")
    rest_time_s: float = param_as(BiasFilterParams, "rest_time_s", REST_TIME_S)
    rest_noise_rad2_s: float = param(
        1e-4, alias="Rrest", unit="rad^2/s", valid="> 0, finite", reference=VQF + ", Sec. 3.4",
        meaning="Density of the gyro reading at rest in the rest term, which pulls the biases with a variable to "
                "what the gyro reads where the recording is at rest (off with weighting=scalar or no bias axes).")
    weighting: Literal["noise", "scalar", "seed"] = param(
        "noise", unit="", valid="noise | scalar (seed: its former name, with a warning)",
        meaning="noise weighs each term by the information of the noise variances above, scalar by one weight per "
                "term (motion scalar_motion_weight, accelerometer 1, no robust loss, no velocity model).")
    scalar_motion_weight: float = param(10.0, alias="wm", unit="1", valid="> 0, finite",
                                        meaning="The motion term's weight with weighting=scalar.")
    init: str = param("dr", unit="", valid="dr | ukf | ukf-bias | ekf",
                      meaning="The estimator whose output starts the optimisation.")
    init_level_s: float = param(
        10.0, alias="level", unit="s", valid="0, or >= 0.1 and finite; 0: off",
        meaning="Re-level the start with the accelerometer every this many seconds (`levelled`; 0 keeps the init "
                "estimator's output as it is).")
    max_iter: int = param(50, alias="iters", unit="", valid="a whole number >= 1",
                          meaning="The solve stops after this many iterations at most.")
    tol: float = param(
        1e-4, unit="1", valid=">= 0, finite",
        meaning="The solve stops when an iteration lowers the cost by less than this fraction.")
    presolve_tol_rad: float = param(
        math.radians(0.01), alias="ptol", unit="rad", valid=">= 0, finite; 0: solve to tol",
        meaning="On a recording with a magnetometer (mag_term=cost), the 6-D solve that the magnetometer's "
                "measurements are taken at holds the scale errors at zero and stops as soon as an accepted step "
                "changes no sample's inclination by more than this (`inclination_step`).")
    progress: bool = param(True, unit="", valid="true | false",
                           meaning="Show a tqdm bar over the iterations on stderr (on a terminal only).")
    impl: Literal["compiled", "numpy"] = param(
        "compiled", unit="", valid="compiled | numpy",
        meaning="compiled runs the cost, linearisation and solves in the numba kernels of "
                "`fusion.estimators.smoothers._compiled`, numpy the reference they are checked against "
                "(`SmootherProblem` and the banded LAPACK solves); the two differ in rounding only.")
    # two decades either side (benchmarks/broad_9d_smoothers.py --leave-one-out tries 0.03-0.3); the
    # unit is rad^2 s, not the rad^2/s its suffix reads as elsewhere (a measurement's density)
    mag_heading_noise_rad2_s: float = param(
        0.1, alias="Rm", unit="rad^2 s", valid="> 0, finite", reference=VQF + ", Sec. 3.3 (heading-only correction)",
        meaning="Density of the magnetometer's heading measurement: a sample has the variance Rm / dt.",
        search=Tunable(1e-3, 10.0, magnetometer=True))
    mag_heading_walk_rad2_s: float = param(
        9e-4, alias="Qm", unit="rad^2/s", valid="> 0, finite; applies only with mag_term=stage", reference=RTS,
        meaning="Density of the 6-D solution's heading-error random walk that the stage smooths, more than the gyro's "
                "noise density since it also carries what the 6-D cost leaves unmodelled about the vertical; with Rm "
                "it sets the stage's time constant, sqrt(Rm / Qm) (about 10 s).")
    mag_rate_rad_s: float = param(
        2.0, alias="mrate", unit="rad/s", valid="> 0; inf: a constant variance",
        meaning="The heading measurement's variance grows as (1 + (w / mrate)^2), w the rate about the vertical, for "
                "a magnetometer that lags the gyro.")
    mag_loss: Literal["huber", "cauchy", "geman-mcclure", "none"] = param(
        "huber", alias="mloss", unit="", valid="huber | cauchy | geman-mcclure | none", reference=M_ESTIMATORS,
        meaning="The robust loss on the heading residual (none: plain least squares).")
    mag_loss_scale_rad: float = param(0.1, alias="mhuber", unit="rad", valid="> 0, finite", reference=M_ESTIMATORS,
                                      meaning="The robust loss's scale on the heading residual.")
    mag_norm_gate_frac: float = param(
        0.1, alias="mnorm", unit="fraction", valid="> 0, finite", reference=VQF + ", Sec. 3.3",
        meaning="A magnetometer sample counts while its norm is within this fraction of the reference norm (the "
                "median of the recording's own undisturbed samples).")
    mag_dip_gate_rad: float = param(
        math.radians(10.0), alias="mdip", unit="rad", valid="> 0, finite", reference=VQF + ", Sec. 3.3",
        meaning="A magnetometer sample counts while its dip is within this of the reference dip (the median of the "
                "recording's own undisturbed samples).")
    mag_min_undisturbed_s: float = param(
        3.0, alias="mtime", unit="s", valid=">= 0, finite", reference=VQF + ", Sec. 3.3",
        meaning="A magnetometer sample counts only in an uninterrupted run of samples inside the norm and dip gates "
                "this long.")
    mag_hard_iron: bool = param(
        True, alias="mhi", unit="", valid="true | false", reference=HARD_IRON_FIT,
        meaning="Fit a magnet carried with the sensor (a sphere fit over each disturbed stretch, else over windows "
                "of mag_hard_iron_window_s) and use its samples with the offset removed; the mag_hard_iron_* "
                "fields apply only with it.")
    mag_hard_iron_window_s: float = param(
        10.0, alias="mhiw", unit="s", valid="> 0, finite", reference=HARD_IRON_FIT,
        meaning="Length of the windows the hard-iron sphere is fitted over outside the disturbed stretches.")
    mag_hard_iron_residual_ut: float = param(
        2.0, alias="mhires", unit="uT", valid="> 0, finite",
        meaning="The hard-iron fit is trusted while its RMS residual is below this.")
    mag_hard_iron_coverage: float = param(
        0.3, alias="mhicov", unit="1", valid="> 0, finite",
        meaning="The hard-iron fit is trusted only while the samples' spread is at least this fraction of its "
                "radius.")
    mag_term: Literal["cost", "stage"] = param(
        "cost", alias="mterm", unit="", valid="cost | stage", reference=RTS + " (stage)",
        meaning="cost makes the heading residual a term of the cost, solved again from the 6-D solution; stage "
                "corrects the 6-D solution afterwards by a rotation about the world vertical (a smoothed "
                "heading-error random walk), leaving the inclination exactly as in 6-D.")

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
