"""The `ahrs` package's single-sample attitude determinations (Garcia, https://ahrs.readthedocs.io,
version 0.4) behind our `Estimator` interface: each sample's orientation from that sample's
accelerometer and magnetometer alone, no gyro, no memory, the methods textbooks contrast with
filtering: Davenport's q method (Davenport 1968), QUEST (Shuster & Oh 1981), OLEQ (Zhou et al.
2018), FLAE (Wu et al. 2018), FQA (Yun et al. 2008), SAAM (Wu et al. 2018), TRIAD (Black 1964),
FAMC (Liu et al. 2018) and the accelerometer's tilt with a compass heading (`Tilt`).

Each runs the library's own batch call (its `Q`, or TRIAD's `A`) on every usable sample of the
recording, with the accelerometer in m/s^2 and the magnetometer in mT, the units its documentation
names (Davenport's weights act on the raw vectors: with the defaults the accelerometer's term, some
96 (m/s^2)^2, outweighs the field's 0.05 mT, and the field sets the heading only; every other method
normalises both). The frames, found by feeding each exact readings of random orientations (an ENU
world, a field dipping 67 deg) and checked by `tests/test_more_peers.py`: Tilt, FAMC, Davenport's q
method, QUEST and FLAE return `R_world_body` in a z-up world with x north (NWU), SAAM its inverse
in NWU, TRIAD the inverse in our ENU (given the references below), OLEQ `R_world_body` in ENU
(`frame="ENU"`), FQA `R_world_body` in NED; the adapter turns each into ENU (x east, y north, z up),
the frame of BROAD's truth.

The magnetic reference. Where a method takes one, it is the field measured on the recording: north
and the dip d (`fusion.checks.check_magnetometer`, as for the EKF), given in each method's own way:
Davenport and QUEST `magnetic_dip=-d` (their reference `[cos, 0, sin]` of the dip is in a z-up world:
a northern field points down), FLAE `magnetic_dip=d` (its `[cos d, 0, -sin d]`), OLEQ
`magnetic_ref=d` with `frame="ENU"` (`[0, cos d, -sin d]`), TRIAD `v1 = [0, 0, 1]` (the accelerometer's
specific force in a z-up world) and `v2 = [0, cos d, -sin d]` (ENU), FQA `mag_ref = [cos d, 0, sin d]`
(NED; it uses the reference's horizontal direction only). The libraries' defaults are Munich's
field from their geomagnetic model, some in a frame that disagrees with their own gravity
reference (NED's down-pointing field against a z-up gravity); SAAM, FAMC and Tilt take none.

6-D (no magnetometer, or `--mag off`). Tilt and FQA have an accelerometer-only mode (Tilt without
`mag`; FQA with an all-zero magnetometer sample, its "no field" branch): the heading is that of the
body x axis, set to zero. The other methods need a second vector: the adapter gives them a
*virtual field* `v = cos(D) h - sin(D) a`, with a the normalised accelerometer and h the body x
axis's horizontal projection `e_x - (e_x . a) a`, normalised (`e_y`'s where e_x is within 0.06 deg
of the vertical): a field along the body x axis's heading, dipping D = 60 deg (`VIRTUAL_DIP_DEG`, a
mid-latitude field's dip), read against a northern reference of the same dip. It agrees exactly
with the accelerometer (the angle between the two is the same in body and world), so every method
returns the accelerometer's inclination and the body x axis's zero heading, as Tilt does, whatever
its weights, to the method's own accuracy at such a site. (With a horizontal virtual field, dip 0,
FLAE's closed form fails on 70 % of random orientations; with 60 deg it works as in 9-D.)
In 6-D the estimate is then turned once about the vertical so that its heading at the first usable
sample after the seed equals the initial orientation's (`align_heading`), as offlineVQF's is; in 9-D the magnetometer
sets the heading.

Rows: row 0 is the initial orientation, as for every causal estimator here; row k >= 1 is the
method on sample k. A sample without a usable accelerometer sample (non-finite or zero) or, in 9-D,
magnetometer sample (invalid), or on which the method returns no finite orientation (a degenerate
geometry, e.g. the field along gravity), repeats the previous row. The gyro is not used: an invalid
gyro sample changes nothing.

Library traps: `FQA.estimate(acc)` and `FQA(acc=...)` without `mag` raise (they check `mag` before
its `None` branch), hence the zero sample; `TRIAD(v2=<dip as a float>)` is refused by its own input
check, hence the vectors; OLEQ starts its power iteration from `np.random.random` and stops after 21
steps, often far from converged (tens of degrees on exact readings): the adapter seeds NumPy's global
generator (`seed`, default 0) for the call and restores its state afterwards, so that a run repeats;
FLAE's default `method="symbolic"` is accurate to some 0.1-1 deg on exact readings, `"eig"` to
rounding; Davenport's method keeps the eigenvector's sign from `np.linalg.eig`.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any, ClassVar, Literal

import numpy as np

from fusion import quaternion as quat
from fusion.types import ImuSamples, Trajectory

from ..base import Estimator
from ..params import param
from ..search import Tunable
from .ahrs_filters import _check_impl
from .vqf_fusion import _RZ90, _acc_m_s2, _check_length, _non_negative, _require, align_heading

MT_PER_UT = 1e-3
# 180 deg about (x + y) / sqrt(2): NED (x north, y east, z down) -> ENU (x east, y north, z up)
_NED_TO_ENU = np.array([0.0, np.sqrt(0.5), np.sqrt(0.5), 0.0])
_NEAR_VERTICAL = 1e-3  # |e_x - (e_x . a) a| below this: e_x within 0.06 deg of the accelerometer's axis
VIRTUAL_DIP_DEG = 60.0  # the 6-D virtual field's dip (module docstring)


def virtual_field(acc: np.ndarray, dip_deg: float = VIRTUAL_DIP_DEG) -> np.ndarray:
    """(N, 3) the 6-D virtual field (module docstring), unit vectors, body frame, for each
    accelerometer sample `acc` (N, 3), any unit, non-zero: along the horizontal projection of the
    body x axis (of the body y axis where x is within 0.06 deg of the accelerometer's axis), dipping
    `dip_deg` below the horizontal (against the accelerometer's up)."""
    a = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    h = np.eye(3)[0] - a[:, :1] * a
    near = np.linalg.norm(h, axis=1) < _NEAR_VERTICAL
    h[near] = np.eye(3)[1] - a[near, 1:2] * a[near]
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    d = np.radians(dip_deg)
    return np.cos(d) * h - np.sin(d) * a


def measured_dip_deg(imu: ImuSamples) -> float:
    """The field's dip on the recording, deg, positive down (`fusion.checks.check_magnetometer`; 0 when
    it cannot be measured)."""
    from fusion.checks import check_magnetometer

    check = check_magnetometer(imu)
    return float(check.dip_median_deg) if check.dip_median_deg is not None else 0.0


def _hold(init_quat_wxyz: np.ndarray, est: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """(N, 4): row 0 the seed, row k the estimate k where `usable[k]`, else row k - 1."""
    out = np.array(est, dtype=float)
    out[0] = init_quat_wxyz
    rows = np.where(usable, np.arange(len(est)), 0)
    rows[0] = 0
    return out[np.maximum.accumulate(rows)]


class SingleSampleEstimator(Estimator):
    """A method that determines each sample's orientation from that sample's accelerometer (and
    magnetometer) alone (module docstring). Subclasses write `_solve`. Where the parameters have
    `impl` (every method here but SAAM and Tilt, whose library calls are vectorised already), `impl=compiled`
    (the default) runs the library's `estimate` on all samples at once in its twin
    (`peers._compiled_ahrs_single`: `_twins`; the same numbers to 1e-9, `tests/test_compiled_peers.py`),
    `impl=library` calls the library (the reference)."""

    single_sample: ClassVar[bool] = True  # `fusion list` groups these apart from the filters
    magnetometer = True
    _name: ClassVar[str] = ""
    _native_6d: ClassVar[bool] = False  # an accelerometer-only mode of the library's own

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        self._filters = _require("ahrs.filters", "ahrs", self._name)
        impl = getattr(self.params, "impl", "library")
        _check_impl(self._name, impl)
        self._twins: ModuleType | None = None
        if impl == "compiled":
            from . import _compiled_ahrs_single  # numba is imported when a compiled peer is built

            _compiled_ahrs_single.load()
            self._twins = _compiled_ahrs_single

    def _solve(self, acc_m_s2: np.ndarray, mag_mt: np.ndarray | None, dip_deg: float) -> np.ndarray:
        """(M, 4) `R_world_body` in ENU for M samples (acc (M, 3) m/s^2, non-zero; mag (M, 3) mT,
        non-zero, or None: the library's accelerometer-only mode), from the library's batch call;
        `dip_deg`: the reference field's dip, deg, positive down (`VIRTUAL_DIP_DEG` for the virtual field)."""
        raise NotImplementedError

    def solve(self, acc_m_s2: np.ndarray, mag_mt: np.ndarray | None, dip_deg: float) -> np.ndarray:
        """`_solve` on all M samples at once (the library's batch call); where that raises (a
        singular matrix on one degenerate sample stops the library's whole loop), on each half
        again, so that only the samples on which the library itself fails are NaN rows. The
        samples are independent: a part's rows are what the whole call would have given."""
        try:
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                return np.asarray(self._solve(acc_m_s2, mag_mt, dip_deg), dtype=float).reshape(len(acc_m_s2), 4)
        except (np.linalg.LinAlgError, ValueError, ZeroDivisionError, FloatingPointError):
            if len(acc_m_s2) == 1:
                return np.full((1, 4), np.nan)
        half = len(acc_m_s2) // 2
        parts = [(slice(0, half), ), (slice(half, None), )]
        return np.vstack([self.solve(acc_m_s2[s], None if mag_mt is None else mag_mt[s], dip_deg) for (s,) in parts])

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        _check_length(imu, self._name)
        n = len(imu)
        acc = _acc_m_s2(imu.acc_g)
        usable = np.any(acc != 0.0, axis=1)
        if imu.has_mag:
            mag = np.where(imu.mag_valid[:, None], imu.mag_ut, 0.0)
            usable &= np.any(mag != 0.0, axis=1)
            dip = measured_dip_deg(imu)
        usable[0] = False  # row 0 is the seed: the method runs on samples 1.. (OLEQ's random draws start there)
        est = np.full((n, 4), np.nan)
        if np.any(usable):
            if imu.has_mag:
                est[usable] = self.solve(acc[usable], mag[usable] * MT_PER_UT, dip)
            elif self._native_6d:
                est[usable] = self.solve(acc[usable], None, 0.0)
            else:
                est[usable] = self.solve(acc[usable], virtual_field(acc[usable]), VIRTUAL_DIP_DEG)
        usable &= np.all(np.isfinite(est), axis=1)
        if not imu.has_mag and np.any(usable):  # heading at the first usable sample = the seed's
            est[usable] = align_heading(est[usable], np.asarray(init_quat_wxyz, dtype=float), 0)
        return Trajectory(imu.t, _hold(init_quat_wxyz, est, usable))


def _nwu(q: np.ndarray) -> np.ndarray:
    return quat.multiply(_RZ90, np.asarray(q, dtype=float))


def _weights(owner: str, acc_weight: float, mag_weight: float) -> None:
    _non_negative(owner, acc_weight=acc_weight, mag_weight=mag_weight)
    if not acc_weight > 0:
        raise ValueError(f"{owner}: acc_weight must be positive, got {acc_weight}")


_ZHOU = "Zhou et al. 2018 (OLEQ)"


def _impl() -> Any:
    """The `impl` field of the single-sample ahrs peers."""
    return param("compiled", unit="", valid="compiled | library",
                 meaning="compiled runs the library's `estimate` on all samples at once as its twin in "
                         "`peers._compiled_ahrs_single`, library the library's batch call (the reference).")


# Magnetometer weight, searched in 9-D only (in 6-D the virtual field agrees with the accelerometer
# and no weight changes the estimate): the library's default and a decade either side, log scale.
def _mag_weight_search(default: float) -> Tunable:
    return Tunable(default * 1e-3, default * 1e3, log=True, grid=(default * 0.1, default, default * 10.0),
                   magnetometer=True)


# ------------------------------------------------------------------------------ Davenport's q method


@dataclass(frozen=True)
class DavenportParams:
    """`ahrs.filters.Davenport` parameters (its defaults), documented at the fields."""

    acc_weight: float = param(
        1.0, unit="1", valid="> 0", reference="Davenport 1968 (the q method)",
        meaning="The weight of the accelerometer's term in the attitude profile matrix B (the library's weights; it "
                "does not normalise the vectors, module docstring).")
    mag_weight: float = param(
        1.0, unit="1", valid=">= 0", reference="Davenport 1968 (the q method)",
        search=Tunable(1e-2, 1e6, log=True, grid=(1.0, 100.0, 1e4), magnetometer=True),
        meaning="The weight of the magnetometer's term in the attitude profile matrix B (the library's weights).")
    gravity_m_s2: float | None = param(
        None, alias="gravity", unit="m/s^2", valid="> 0, or none for the library's default",
        meaning="The gravity reference's length (the library's gravity; none: its default, the normal gravity at "
                "Munich).")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _weights("davenport", self.acc_weight, self.mag_weight)


class DavenportPeer(SingleSampleEstimator):
    """Davenport's q method (Davenport 1968), from the `ahrs` package.

    The eigenvector of the largest eigenvalue of K, per sample, `ahrs.filters.Davenport`."""

    Params = DavenportParams
    _name = "davenport"

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        p = self.params
        kw = {} if p.gravity_m_s2 is None else {"gravity": p.gravity_m_s2}
        if self._twins is not None:  # the library's constants, its estimate batched
            filt = self._filters.Davenport(weights=np.array([p.acc_weight, p.mag_weight]), magnetic_dip=-dip_deg, **kw)
            return _nwu(self._twins.davenport_estimate(filt, acc_m_s2, mag_mt))
        filt = self._filters.Davenport(acc=acc_m_s2, mag=mag_mt, weights=np.array([p.acc_weight, p.mag_weight]),
                                       magnetic_dip=-dip_deg, **kw)
        return _nwu(filt.Q)


# ------------------------------------------------------------------------------ QUEST


@dataclass(frozen=True)
class QUESTParams:
    """`ahrs.filters.QUEST` parameters (its defaults), documented at the fields."""

    acc_weight: float = param(0.5, unit="1", valid="> 0", reference="Shuster & Oh 1981 (QUEST)",
                              meaning="The weight of the normalised accelerometer vector (the library's weights).")
    mag_weight: float = param(0.5, unit="1", valid=">= 0", reference="Shuster & Oh 1981 (QUEST)",
                              search=_mag_weight_search(0.5),
                              meaning="The weight of the normalised magnetometer vector (the library's weights).")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _weights("quest", self.acc_weight, self.mag_weight)


class QUESTPeer(SingleSampleEstimator):
    """QUEST (Shuster & Oh 1981), from the `ahrs` package.

    Davenport's eigenvalue by Newton's method on the characteristic polynomial, per sample,
    `ahrs.filters.QUEST` (its singularity at rotations of 180 deg is not avoided)."""

    Params = QUESTParams
    _name = "quest"

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        p = self.params
        if self._twins is not None:
            filt = self._filters.QUEST(weights=np.array([p.acc_weight, p.mag_weight]), magnetic_dip=-dip_deg)
            return _nwu(self._twins.quest_estimate(filt, acc_m_s2, mag_mt))
        filt = self._filters.QUEST(acc=acc_m_s2, mag=mag_mt, weights=np.array([p.acc_weight, p.mag_weight]),
                                   magnetic_dip=-dip_deg)
        return _nwu(filt.Q)


# ------------------------------------------------------------------------------ OLEQ


@dataclass(frozen=True)
class OLEQParams:
    """`ahrs.filters.OLEQ` parameters (its defaults), documented at the fields."""

    acc_weight: float = param(1.0, unit="1", valid="> 0", reference=_ZHOU,
                              meaning="The weight of the normalised accelerometer vector (the library's weights).")
    mag_weight: float = param(1.0, unit="1", valid=">= 0", reference=_ZHOU, search=_mag_weight_search(1.0),
                              meaning="The weight of the normalised magnetometer vector (the library's weights).")
    seed: int = param(0, unit="", valid="a whole number >= 0",
                      meaning="NumPy's global random seed for the call, since the library starts its iteration at "
                              "random.")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _weights("oleq", self.acc_weight, self.mag_weight)


class OLEQPeer(SingleSampleEstimator):
    """OLEQ, the optimal linear estimator of the quaternion (Zhou et al. 2018), from the `ahrs` package.

    A power iteration per sample, `ahrs.filters.OLEQ` (at most 21 steps from a random start)."""

    Params = OLEQParams
    _name = "oleq"

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        p = self.params
        state = np.random.get_state()
        try:
            np.random.seed(p.seed)
            if self._twins is None:
                filt = self._filters.OLEQ(acc=acc_m_s2, mag=mag_mt, weights=np.array([p.acc_weight, p.mag_weight]),
                                          magnetic_ref=float(dip_deg), frame="ENU")
                return np.asarray(filt.Q, dtype=float)
            # the library draws np.random.random(4) per sample, in order: the same stream drawn at once
            starts = np.random.random((len(acc_m_s2), 4))
        finally:
            np.random.set_state(state)
        if len(acc_m_s2) < 2:  # the library's batch call passes a single sample on as (1, 3), which its estimate
            return np.full((len(acc_m_s2), 4), np.nan)  # cannot unpack (a ValueError: `solve`'s NaN row)
        filt = self._filters.OLEQ(weights=np.array([p.acc_weight, p.mag_weight]), magnetic_ref=float(dip_deg),
                                  frame="ENU")
        out = np.empty((len(acc_m_s2), 4))
        self._twins.oleq_kernel(np.ascontiguousarray(acc_m_s2, dtype=float), np.ascontiguousarray(mag_mt, dtype=float),
                                float(filt.a[0]), float(filt.a[1]), np.array(filt.a_ref, dtype=float),
                                np.array(filt.m_ref, dtype=float), starts, out)
        return out


# ------------------------------------------------------------------------------ FLAE


@dataclass(frozen=True)
class FLAEParams:
    """`ahrs.filters.FLAE` parameters (its defaults), documented at the fields."""

    acc_weight: float = param(
        0.5, unit="1", valid="> 0", reference="Wu et al. 2018 (FLAE)",
        meaning="The weight of the normalised accelerometer vector (the library's weights, which it normalises to "
                "sum 1).")
    mag_weight: float = param(
        0.5, unit="1", valid=">= 0", reference="Wu et al. 2018 (FLAE)", search=_mag_weight_search(0.5),
        meaning="The weight of the normalised magnetometer vector (the library's weights, which it normalises to "
                "sum 1).")
    method: Literal["symbolic", "eig", "newton"] = param(
        "symbolic", unit="", valid="symbolic | eig | newton", reference="Wu et al. 2018 (FLAE)",
        meaning="How the largest eigenvalue is found: symbolic (the library's default, in closed form), eig or "
                "newton.")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _weights("flae", self.acc_weight, self.mag_weight)
        if self.method not in ("symbolic", "eig", "newton"):
            raise ValueError(f"flae: method must be symbolic, eig or newton, got {self.method!r}")


class FLAEPeer(SingleSampleEstimator):
    """FLAE, the fast linear attitude estimator (Wu et al. 2018), from the `ahrs` package.

    Per sample, `ahrs.filters.FLAE`."""

    Params = FLAEParams
    _name = "flae"

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        p = self.params
        if self._twins is not None:
            filt = self._filters.FLAE(method=p.method, weights=np.array([p.acc_weight, p.mag_weight]),
                                      magnetic_dip=float(dip_deg))
            return _nwu(self._twins.flae_estimate(filt, acc_m_s2, mag_mt, p.method))
        filt = self._filters.FLAE(acc=acc_m_s2, mag=mag_mt, method=p.method,
                                  weights=np.array([p.acc_weight, p.mag_weight]), magnetic_dip=float(dip_deg))
        return _nwu(filt.Q)


# ------------------------------------------------------------------------------ parameterless methods


@dataclass(frozen=True)
class NoTunedParams:
    """No parameters: the method has none (its reference field is the recording's, module docstring)."""


@dataclass(frozen=True)
class TwinParams:
    """No parameters of the method's own (its reference field is the recording's, module docstring):
    only the implementation, documented at the field."""

    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _check_impl("ahrs", self.impl)


class FQAPeer(SingleSampleEstimator):
    """FQA, the factored quaternion algorithm (Yun et al. 2008), from the `ahrs` package.

    Elevation, roll and azimuth quaternions, per sample, `ahrs.filters.FQA` (its accelerometer-only
    mode in 6-D)."""

    Params = TwinParams
    _name = "fqa"
    _native_6d = True

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        mag = np.zeros_like(acc_m_s2) if mag_mt is None else mag_mt  # a zero sample: the library's "no field"
        d = np.radians(dip_deg)
        if self._twins is not None:
            filt = self._filters.FQA(mag_ref=np.array([np.cos(d), 0.0, np.sin(d)]))
            nx, ny, _ = filt.m_ref
            north = np.array([nx, ny]) / np.linalg.norm([nx, ny])  # the library's N
            out = np.empty((len(acc_m_s2), 4))
            self._twins.fqa_kernel(np.ascontiguousarray(acc_m_s2, dtype=float), np.ascontiguousarray(mag, dtype=float),
                                   float(north[0]), float(north[1]), out)
            return quat.multiply(_NED_TO_ENU, out)
        filt = self._filters.FQA(acc=acc_m_s2, mag=mag, mag_ref=np.array([np.cos(d), 0.0, np.sin(d)]))
        return quat.multiply(_NED_TO_ENU, np.asarray(filt.Q, dtype=float))


class SAAMPeer(SingleSampleEstimator):
    """SAAM, the super-fast attitude from accelerometer and magnetometer (Wu et al. 2018), from `ahrs`.

    Closed form, per sample, `ahrs.filters.SAAM`."""

    Params = NoTunedParams
    _name = "saam"

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        return _nwu(quat.conjugate(np.asarray(self._filters.SAAM(acc=acc_m_s2, mag=mag_mt).Q, dtype=float)))


class FAMCPeer(SingleSampleEstimator):
    """FAMC, the fast accelerometer-magnetometer combination (Liu et al. 2018), from `ahrs`.

    Closed form, per sample, `ahrs.filters.FAMC`."""

    Params = TwinParams
    _name = "famc"

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        if self._twins is not None:
            out = np.empty((len(acc_m_s2), 4))
            self._twins.famc_kernel(np.ascontiguousarray(acc_m_s2, dtype=float),
                                    np.ascontiguousarray(mag_mt, dtype=float), out)
            return _nwu(out)
        return _nwu(self._filters.FAMC(acc=acc_m_s2, mag=mag_mt).Q)


class TRIADPeer(SingleSampleEstimator):
    """TRIAD (Black 1964), from the `ahrs` package.

    Two orthonormal triads, the accelerometer's direction exact, per sample, `ahrs.filters.TRIAD`."""

    Params = TwinParams
    _name = "triad"

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        d = np.radians(dip_deg)
        refs = dict(v1=np.array([0.0, 0.0, 1.0]), v2=np.array([0.0, np.cos(d), -np.sin(d)]),
                    representation="quaternion")
        if self._twins is not None:
            filt = self._filters.TRIAD(**refs)
            v1xv2 = np.cross(filt.v1, filt.v2)  # the library's reference triad, as its estimate builds it
            r2 = v1xv2 / np.linalg.norm(v1xv2)
            r3 = np.cross(filt.v1, v1xv2) / np.linalg.norm(v1xv2)
            out = np.empty((len(acc_m_s2), 4))
            acc, mag = np.ascontiguousarray(acc_m_s2, dtype=float), np.ascontiguousarray(mag_mt, dtype=float)
            self._twins.triad_kernel(acc, mag, np.ascontiguousarray(np.c_[filt.v1, r2, r3]), out)
            return quat.conjugate(out)
        filt = self._filters.TRIAD(w1=acc_m_s2, w2=mag_mt, **refs)
        return quat.conjugate(np.asarray(filt.A, dtype=float))


class TiltPeer(SingleSampleEstimator):
    """The accelerometer's tilt with a tilt-compensated compass heading, from the `ahrs` package.

    Roll and pitch per sample, `ahrs.filters.Tilt` (without the compass in 6-D)."""

    Params = NoTunedParams
    _name = "tilt"
    _native_6d = True

    def _solve(self, acc_m_s2, mag_mt, dip_deg):
        filt = self._filters.Tilt(acc=acc_m_s2) if mag_mt is None else self._filters.Tilt(acc=acc_m_s2, mag=mag_mt)
        return _nwu(filt.Q)
