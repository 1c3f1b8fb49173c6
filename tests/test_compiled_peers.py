"""The compiled twins of the `ahrs` estimators (`peers._compiled_ahrs`, `peers._compiled_ahrs_recursive`,
`peers._compiled_ahrs_single`) against the library itself.

Each of `madgwick`, `mahony` and `ahrs-ekf` runs twice on the same samples, with `impl=compiled`
(the numba twin, the default) and `impl=library` (the library's update per sample, the
reference): the quaternions must agree to 1e-9 (largest difference of a component, q and -q the
same), and so must the diagnostics (Mahony's bias estimate, the EKF's covariance). The twins round
as one OpenBLAS build does; on a recording where another build's last-bit differences grow beyond
1e-9, the bound is ten times the library's own rounding sensitivity there (how far its output moves
when its accelerometer input moves by one unit in the last place).

On every recording under `$FUSION_DATA` (the course sets and BROAD's trials as found there: 6-D,
and 9-D where the recording has a magnetometer), a window of `WINDOW` samples: the library takes
60-150 us a sample, so whole recordings would take some 15 minutes (they were compared once in
full when the twins were written: Madgwick and Mahony equal bit for bit, the EKF within 4e-13). The window holds the recording's first
invalid gyro samples where it has some (the course recordings' gyro freezes), else the middle of
the recording (motion); the filters start there from the recording's initial orientation, an
error of up to tens of degrees they must correct alike. Without `$FUSION_DATA` these are skipped
(failed under CI); with it set but the recordings missing they fail (`conftest.data_dir`).

On a short simulated recording (`fusion.sim`, no data needed): a gyro freeze marked invalid (the
1e-150 rad/s stand-in of Madgwick and Mahony, the EKF's zero rate), exactly zero gyro samples
(the library's "skip the update" branch), accelerometer samples that are NaN or exactly zero,
and, in 9-D, a field along the truth with invalid (NaN) magnetometer rows; with the libraries'
defaults and with other parameters.

The twins of the rest of `ahrs` (`MORE`: AQUA, FKF, Fourati, ROLEQ, the UKF, AngularRate and the
single-sample methods with a twin) likewise, on shorter samples, as the library takes 40-1000 us a
sample: a 6 s simulated recording with the same branches and three magnetometer samples along
gravity (a degenerate geometry for the single-sample methods), with the defaults and other
parameters (every FLAE method, AngularRate's series, AQUA's adaptive gain), and `MORE_WINDOW` samples
of one recording of each shared dataset (and BROAD's trial with a magnet 1 cm from the sensor).
"""
from __future__ import annotations

import numpy as np
import pytest

from fusion import datasets
from fusion.calibration import calibrate
from fusion.sim import SimSettings, simulate
from fusion.types import ImuSamples

from optional_helpers import build_estimator, require_module

PEERS = ("madgwick", "mahony", "ahrs-ekf")
TOL = 1e-9
ROUNDING_FACTOR = 10.0  # a few last-place differences per step, against the one of `rounding_sensitivity`
WINDOW = 1500  # samples per recording compared against the library (see the module docstring)
OTHER_PARAMS = {"madgwick": "beta=0.12", "mahony": "kp=0.74,ki=0.0012",
                "ahrs-ekf": "var_gyr=0.001,var_acc=0.01,var_mag=0.1,P0=0.01"}
# the rest of ahrs with a twin, and the other parameters each is compared with (besides its defaults)
MORE = {"aqua": ("alpha=0.03,beta=0.001,adaptive=true",), "fkf": ("sigma_g=0.001,sigma_a=0.1,sigma_m=0.05,Pk=1",),
        "fourati": ("gain=0.3",), "roleq": ("mag_weight=10",), "ahrs-ukf": ("Q=1e-3,R=1e-3",),
        "ahrs-angular": ("method=series,order=3",), "davenport": ("mag_weight=100",), "quest": ("mag_weight=5",),
        "oleq": ("mag_weight=0.1,seed=3",), "flae": ("method=newton,mag_weight=5", "method=eig"), "fqa": (),
        "triad": (), "famc": ()}
MORE_WINDOW = 300
MORE_RECORDINGS = ("ece276a/1", "ese650/1", "broad/06*", "broad/32*", "repoimu/TStick/*", "repoimu/Pendulum/*")


def largest_difference(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| over the components of (N, 4) quaternions, each row of b signed as a's."""
    sign = np.where(np.sum(a * b, axis=1) < 0.0, -1.0, 1.0)
    return float(np.max(np.abs(a - sign[:, None] * b)))


def rounding_sensitivity(peer: str, imu: ImuSamples, seed: np.ndarray, params: str = "") -> dict[str, float]:
    """How far the library's own quaternions and diagnostics move when every accelerometer value
    moves by one unit in the last place: the scale of a rounding difference on these samples."""
    spec = f"{peer}:{params + ',' if params else ''}impl=library"
    lib = build_estimator(spec).estimate(imu, seed)
    nudged = build_estimator(spec).estimate(imu.replace(acc_g=np.nextafter(np.asarray(imu.acc_g), np.inf)), seed)
    out = {"quat": largest_difference(lib.quat_wxyz, nudged.quat_wxyz)}
    for key in lib.diagnostics:
        out[key] = float(np.max(np.abs(np.asarray(lib.diagnostics[key]) - np.asarray(nudged.diagnostics[key]))))
    return out


def twin_and_library(peer: str, params: str, imu: ImuSamples, seed: np.ndarray) -> dict[str, float]:
    """The largest differences between the twin's and the library's quaternions and diagnostics."""
    sep = ":" + params + "," if params else ":"
    twin = build_estimator(f"{peer}{sep}impl=compiled").estimate(imu, seed)
    lib = build_estimator(f"{peer}{sep}impl=library").estimate(imu, seed)
    assert twin.quat_wxyz.shape == lib.quat_wxyz.shape == (len(imu), 4)
    assert np.all(np.isfinite(twin.quat_wxyz))
    np.testing.assert_array_equal(twin.quat_wxyz[0], lib.quat_wxyz[0])  # the seed, as the library path writes it
    assert sorted(twin.diagnostics) == sorted(lib.diagnostics)
    out = {"quat": largest_difference(twin.quat_wxyz, lib.quat_wxyz)}
    for key in twin.diagnostics:
        out[key] = float(np.max(np.abs(np.asarray(twin.diagnostics[key]) - np.asarray(lib.diagnostics[key]))))
    return out


def window(imu: ImuSamples, length: int = WINDOW) -> ImuSamples:
    """`length` samples holding the first invalid gyro samples, else the middle of the recording."""
    bad = np.flatnonzero(~imu.gyr_valid)
    centre = int(bad[0]) if len(bad) else len(imu) // 2
    start = max(0, min(centre - length // 2, len(imu) - length))
    return imu.window(start, start + length)


@pytest.fixture(scope="module")
def shared_recordings(data_dir) -> list[tuple[str, ImuSamples, np.ndarray]]:
    """(id, samples, seed) of every recording under $FUSION_DATA (each copy of a course
    recording: the three sets are compared), windowed."""
    out = []
    for source in datasets.select("all", data_dir, dedupe=False):
        rec = datasets.LoadOptions().load(source)
        out.append((source.id, window(rec.imu), datasets.initial_orientation(rec)))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("peer", PEERS)
def test_twin_equals_the_library_on_every_shared_recording(peer, shared_recordings):
    ids = [rid for rid, _, _ in shared_recordings]
    assert any(rid.startswith("ece276a/") for rid in ids) and any(rid.startswith("broad/") for rid in ids), ids
    worst: dict[str, float] = {}
    for rid, imu, seed in shared_recordings:
        runs = {"6-D": imu.replace(mag_ut=None)}
        if imu.has_mag:
            runs["9-D"] = imu
        for label, samples in runs.items():
            for name, value in twin_and_library(peer, "", samples, seed).items():
                worst[f"{rid} {label} {name}"] = value
    assert any(key.endswith("9-D quat") for key in worst), "no recording with a magnetometer was compared"
    over = {key: value for key, value in worst.items() if not value <= TOL}
    # Where they differ by more than TOL, the bound is the library's own rounding: how far its output
    # moves when its accelerometer input moves by one unit in the last place (`rounding_sensitivity`).
    # The twins round as one OpenBLAS build does (`fusion.estimators.peers._compiled_ahrs`); another build
    # rounds a norm or a product differently in the last bit, and Madgwick's normalised gradient, near
    # zero where the estimate agrees with the accelerometer, turns that bit into up to 1e-8 (measured on
    # ece276a/9 with numpy 2.4's OpenBLAS 0.3.31: twin 8.7e-9, the library against itself 3.5e-8).
    inputs = {f"{rid} {label}": (samples, seed) for rid, imu, seed in shared_recordings
              for label, samples in (("6-D", imu.replace(mag_ut=None)), ("9-D", imu))}
    beyond = {}
    for key, value in over.items():
        run = key.rsplit(" ", 1)[0]
        bound = ROUNDING_FACTOR * rounding_sensitivity(peer, *inputs[run])[key.rsplit(" ", 1)[1]]
        if not value <= max(TOL, bound):
            beyond[key] = (value, bound)
    assert not beyond, f"{peer}: twin and library differ by more than {TOL} and their rounding allows: {beyond}"


def simulated(rate_hz: float = 100.0) -> tuple[ImuSamples, np.ndarray]:
    """20 s of `fusion.sim` with a gyro freeze (invalid), a few exactly zero gyro samples, NaN and
    zero accelerometer samples, and a magnetometer (an ENU field along the truth, uT, with noise)
    with NaN rows. Returns the samples and the initial orientation (the truth's, turned 20 deg
    about the vertical and 5 deg about x, so that the corrections work from the start)."""
    from scipy.spatial.transform import Rotation

    raw, truth = simulate(SimSettings(duration_s=20.0, imu_rate_hz=rate_hz, freezes_s=((8.0, 9.5),), seed=4))
    imu = datasets.calibrated_samples(raw, calibrate(raw), dropouts=True)
    assert 50 < np.count_nonzero(~imu.gyr_valid) < 400  # the freeze, marked invalid
    rot, inside = truth.interpolate(imu.t)
    assert np.all(inside)
    rng = np.random.default_rng(7)
    mag = rot.inv().apply([0.0, 19.0, -45.0]) + rng.normal(0.0, 0.3, (len(imu), 3))
    n = len(imu)
    mag[rng.choice(n, n // 20, replace=False)] = np.nan
    gyr, acc = np.array(imu.gyr_rad_s), np.array(imu.acc_g)
    gyr[[300, 301, 1200]] = 0.0  # exactly zero and valid: the library skips the whole update
    acc[[400, 401, 1500]] = np.nan
    acc[[700, 1600]] = 0.0
    imu = imu.replace(gyr_rad_s=gyr, acc_g=acc, mag_ut=mag)
    assert 0 < np.count_nonzero(~imu.mag_valid) < n
    seed = (Rotation.from_euler("zx", [20.0, 5.0], degrees=True) * rot[0]).as_quat(scalar_first=True)
    return imu, seed


@pytest.fixture(scope="module")
def sim_recording() -> tuple[ImuSamples, np.ndarray]:
    return simulated()


@pytest.mark.parametrize("nine_d", [False, True], ids=["6-D", "9-D"])
@pytest.mark.parametrize("params", ["defaults", "other"])
@pytest.mark.parametrize("peer", PEERS)
def test_twin_equals_the_library_on_a_simulated_recording(peer, params, nine_d, sim_recording):
    imu, seed = sim_recording
    samples = imu if nine_d else imu.replace(mag_ut=None)
    diffs = twin_and_library(peer, OTHER_PARAMS[peer] if params == "other" else "", samples, seed)
    over = {key: value for key, value in diffs.items() if not value <= TOL}
    assert not over, f"{peer}: twin and library differ: {over}"


def test_the_simulated_recording_reaches_the_librarys_branches(sim_recording):
    """The branches the simulated recording is built to reach do change the estimate (else the
    comparison above would not test them): a zero gyro sample holds the orientation (the library
    skips the update), an invalid one does not (the 1e-150 rad/s stand-in lets the
    accelerometer correct)."""
    imu, seed = sim_recording
    est = build_estimator("madgwick").estimate(imu.replace(mag_ut=None), seed).quat_wxyz
    # interval k uses gyro sample k ("start" timing): out[k + 1] is out[k], normalised
    np.testing.assert_allclose(est[301], est[300], atol=1e-15)
    frozen = np.flatnonzero(~imu.interval_rates()[1])
    assert np.max(np.abs(est[frozen[10] + 1] - est[frozen[10]])) > 1e-9


@pytest.mark.parametrize("peer, zero, tiny", [("madgwick", "beta=0", "beta=1e-300"),
                                              ("mahony", "kp=1,ki=0", "kp=1,ki=1e-300")])
def test_a_zero_gain_is_the_limit_of_the_library(peer, zero, tiny, sim_recording):
    """The library refuses a zero gain (Madgwick's beta, Mahony's k_I must be > 0), the twin takes
    it (BROAD's grid includes Ki = 0): it equals the library with a gain of 1e-300."""
    imu, seed = sim_recording
    for samples in (imu.replace(mag_ut=None), imu):
        twin = build_estimator(f"{peer}:{zero}").estimate(samples, seed)
        lib = build_estimator(f"{peer}:{tiny},impl=library").estimate(samples, seed)
        assert largest_difference(twin.quat_wxyz, lib.quat_wxyz) <= TOL
    with pytest.raises(ValueError, match="non-zero"):
        build_estimator(f"{peer}:{zero},impl=library").estimate(imu, seed)


def test_streaming_steps_are_the_library_in_either_impl(sim_recording):
    """`reset`/`step` (streaming) call the library whatever `impl` says, and give the batch
    estimate of the twin to 1e-9."""
    imu, seed = sim_recording
    imu = imu.replace(mag_ut=None)
    twin = build_estimator("mahony").estimate(imu, seed).quat_wxyz
    filt = build_estimator("mahony")
    filt.reset(seed)
    (rates, valid), dt = imu.interval_rates(), imu.dt
    steps = [filt.step(rates[k], dt[k], imu.acc_g[k + 1], valid[k]) for k in range(len(imu) - 1)]
    assert largest_difference(twin[1:], np.array(steps)) <= TOL


def test_an_unknown_impl_is_refused():
    with pytest.raises(ValueError, match="impl"):
        build_estimator("madgwick:impl=numpy")


# --- the rest of ahrs ------------------------------------------------------------------------------

def short_simulated(degenerate: bool = False) -> tuple[ImuSamples, np.ndarray]:
    """6 s of `fusion.sim` at 100 Hz with `simulated`'s branches (a gyro freeze marked invalid, exactly
    zero gyro samples, NaN and zero accelerometer samples, NaN magnetometer rows) and, where
    `degenerate`, three magnetometer samples along the accelerometer's (a degenerate geometry for a
    single-sample method: a recursive filter may not recover from it, in the library as in its twin)."""
    from scipy.spatial.transform import Rotation

    raw, truth = simulate(SimSettings(duration_s=6.0, imu_rate_hz=100.0, seed=4))
    imu = datasets.calibrated_samples(raw, calibrate(raw), dropouts=False)
    rot, inside = truth.interpolate(imu.t)
    assert np.all(inside)
    rng = np.random.default_rng(7)
    mag = rot.inv().apply([0.0, 19.0, -45.0]) + rng.normal(0.0, 0.3, (len(imu), 3))
    gyr, acc, valid = np.array(imu.gyr_rad_s), np.array(imu.acc_g), np.ones(len(imu), dtype=bool)
    gyr[200:260], valid[200:260] = gyr[200], False  # a gyro freeze, marked invalid
    mag[[60, 61, 420]] = np.nan
    if degenerate:
        mag[[90, 91, 300]] = 40.0 * acc[[90, 91, 300]]  # along the accelerometer
    gyr[[100, 101, 350]] = 0.0  # exactly zero and valid
    acc[[150, 151, 400]] = np.nan
    acc[[250, 450]] = 0.0
    imu = imu.replace(gyr_rad_s=gyr, gyr_valid=valid, acc_g=acc, mag_ut=mag)
    seed = (Rotation.from_euler("zx", [20.0, 5.0], degrees=True) * rot[0]).as_quat(scalar_first=True)
    return imu, seed


@pytest.fixture(scope="module")
def short_sim() -> tuple[ImuSamples, np.ndarray]:
    return short_simulated()


@pytest.fixture(scope="module")
def short_sim_degenerate() -> tuple[ImuSamples, np.ndarray]:
    return short_simulated(degenerate=True)


SINGLE_SAMPLE = ("davenport", "quest", "oleq", "flae", "fqa", "triad", "famc")


def assert_within_rounding(peer: str, params: str, diffs: dict[str, dict[str, float]],
                           inputs: dict[str, tuple[ImuSamples, np.ndarray]]) -> None:
    """Every difference (run -> name -> value) within TOL, or within ROUNDING_FACTOR times the
    library's own rounding sensitivity on that run (`rounding_sensitivity`)."""
    beyond = {}
    for run, values in diffs.items():
        over = {k: v for k, v in values.items() if not v <= TOL}
        if over:
            bound = rounding_sensitivity(peer, *inputs[run], params=params)
            beyond.update({f"{run} {k}": (v, ROUNDING_FACTOR * bound[k]) for k, v in over.items()
                           if not v <= ROUNDING_FACTOR * bound[k]})
    assert not beyond, f"{peer}: twin and library differ by more than {TOL} and their rounding allows: {beyond}"


def _more_cases():
    for peer, others in MORE.items():
        for params in ("",) + others:
            yield pytest.param(peer, params, id=f"{peer}-{params or 'defaults'}")


@pytest.mark.parametrize("peer, params", list(_more_cases()))
def test_more_twins_equal_the_library_on_a_simulated_recording(peer, params, short_sim, short_sim_degenerate):
    imu, seed = short_sim_degenerate if peer in SINGLE_SAMPLE else short_sim
    inputs = {"6-D": (imu.replace(mag_ut=None), seed), "9-D": (imu, seed)}
    diffs = {run: twin_and_library(peer, params, *args) for run, args in inputs.items()}
    assert_within_rounding(peer, params, diffs, inputs)


@pytest.fixture(scope="module")
def some_recordings(data_dir) -> dict[str, tuple[ImuSamples, np.ndarray]]:
    """`MORE_WINDOW` samples of the first recording each pattern of `MORE_RECORDINGS` selects."""
    out = {}
    for pattern in MORE_RECORDINGS:
        source = datasets.select(pattern, data_dir, dedupe=False)[0]
        rec = datasets.LoadOptions().load(source)
        imu, seed = window(rec.imu, MORE_WINDOW), datasets.initial_orientation(rec)
        out[f"{source.id} 6-D"] = (imu.replace(mag_ut=None), seed)
        if imu.has_mag:
            out[f"{source.id} 9-D"] = (imu, seed)
    return out


@pytest.mark.parametrize("peer", list(MORE))
def test_more_twins_equal_the_library_on_real_windows(peer, some_recordings):
    assert sum(run.endswith("9-D") for run in some_recordings) >= 3, list(some_recordings)
    diffs = {run: twin_and_library(peer, "", *args) for run, args in some_recordings.items()}
    assert_within_rounding(peer, "", diffs, some_recordings)


def test_the_short_simulated_recording_reaches_the_librarys_branches(short_sim):
    """The branches `short_simulated` is built for change the estimates (else comparing them would
    not test them): a zero gyro sample holds AQUA's orientation (its "skip" branch), an invalid one
    does not; a missing accelerometer or magnetometer sample is held by a single-sample method."""
    imu, seed = short_sim
    est = build_estimator("aqua").estimate(imu, seed).quat_wxyz
    np.testing.assert_array_equal(est[101], est[100])  # step 100 (gyro sample 100, "start" timing): held
    frozen = np.flatnonzero(~imu.interval_rates()[1])
    assert np.max(np.abs(est[frozen[10] + 1] - est[frozen[10]])) > 1e-9
    triad = build_estimator("triad").estimate(imu, seed).quat_wxyz
    np.testing.assert_array_equal(triad[150], triad[149])  # NaN accelerometer
    np.testing.assert_array_equal(triad[60:62], triad[[59, 59]])  # NaN magnetometer samples
    assert not np.array_equal(triad[59], triad[58])


def test_where_the_library_ukf_fails_its_twin_fails(short_sim):
    """With Q = 1e-5 (a grid value) the library's UKF loses its covariance's positive definiteness
    on the simulated recording and raises numpy's LinAlgError; its twin raises it too, naming the sample."""
    imu, seed = short_sim
    for samples in (imu.replace(mag_ut=None), imu):
        with pytest.raises(np.linalg.LinAlgError):
            build_estimator("ahrs-ukf:Q=1e-5,impl=library").estimate(samples, seed)
        with pytest.raises(np.linalg.LinAlgError, match="ahrs-ukf: sim: .* fails at sample"):
            build_estimator("ahrs-ukf:Q=1e-5").estimate(samples, seed)


def test_every_twin_names_the_library_function_it_mirrors():
    """A reader finds a twin by its library function's name (as `filters`' kernels carry their
    numpy reference's, `kernels._numba.mirrors`): every public function of the peers' twin modules
    but their loops (`*_kernel`) and `load` names, first in its docstring, the `ahrs` function or
    method it mirrors, which exists and whose name ends the twin's."""
    import importlib
    import inspect

    require_module("ahrs")
    from numba.core.registry import CPUDispatcher

    seen = 0
    for name in ("_compiled_ahrs", "_compiled_ahrs_recursive", "_compiled_ahrs_single"):
        module = importlib.import_module(f"fusion.estimators.peers.{name}")
        for attr, obj in vars(module).items():
            func = obj.py_func if isinstance(obj, CPUDispatcher) else obj
            if (attr.startswith("_") or attr.endswith("_kernel") or attr == "load" or not inspect.isfunction(func)
                    or func.__module__ != module.__name__):
                continue
            doc = inspect.getdoc(func) or ""
            assert doc.startswith("`ahrs."), f"{name}.{attr}: its docstring does not start with its reference"
            reference = doc.split("`")[1].split(" ")[0]
            parts = reference.split(".")
            for i in range(len(parts), 0, -1):  # the longest prefix that is a module, then its attributes
                try:
                    target = importlib.import_module(".".join(parts[:i]))
                except ImportError:
                    continue
                for part in parts[i:]:
                    target = getattr(target, part)
                break
            assert callable(target), reference
            assert attr.endswith(parts[-1]), f"{name}.{attr} mirrors {reference}: the names differ"
            seen += 1
    assert seen >= 25
