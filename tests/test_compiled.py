"""The compiled filters (`impl=compiled`, numba) against their numpy reference steps.

`ekf`, `ukf` and `ukf-bias` against `impl=numpy` (itself checked against
FilterPy's update in test_ukf.py): same quaternions and the same per-sample diagnostics and
counts, to 1e-10, NaN at the same places, on a course recording, a BROAD trial and the
simulator (each trimmed to a few thousand samples), for every option and with broken samples.
Real-data cases use the `data_dir` fixture: skipped without FUSION_DATA, failing when it is
set but the files are missing.
"""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from fusion import datasets
from fusion import quaternion as quat
from fusion.estimators import build
from fusion.types import ImuSamples

from optional_helpers import require_module

TOL = 1e-10

SPECS = (
    # ekf: bias and scale on/off, scale axes, gating, heading_free, accelerometer off, no
    # disturbance model, rest detection early / off, accelerometer low-pass off / shorter
    "ekf", "ekf:bias=false,scale=false", "ekf:scale=false", "ekf:saxes=xyz", "ekf:gate=skip,gate_g=0.05",
    "ekf:gate=inflate,gate_g=0.1", "ekf:hf=false", "ekf:acc=false", "ekf:tauc=0", "ekf:rest_time_s=0.3",
    "ekf:rest_time_s=inf", "ekf:taulp=0", "ekf:taulp=0.3,taulpw=1",
    # the rest detector's tilt test off, and so tight that it ends still stretches on the recordings
    "ekf:rtilt=inf", "ekf:rtilt=0.0003,rest_time_s=0.3",
    # ekf's velocity model off, tighter, with a looser acceleration density, without calibration states
    "ekf:Rv=inf", "ekf:Rv=0.09,Qv=2.5e-3", "ekf:bias=false,scale=false,Rv=0.25", "ekf:lpcal=true",
    # ekf without the slow external acceleration, and with a longer one
    "ekf:tauslow=0", "ekf:tauslow=5",
    # ekf's scale test off, and deciding within the windows (wide error probabilities), on three axes without
    # heading_free
    "ekf:sprt=0", "ekf:sprt=0.3", "ekf:sprt=0.45,saxes=xyz,hf=false",
    # ukf: sigma schemes, heading_free, gating, no scale noise, accelerometer off, iteration cap,
    # accelerometer low-pass on (with and without the scale noise in its drift density)
    "ukf", "ukf:hf=true", "ukf:sigma=julier,kappa=2", "ukf:sigma=merwe,alpha=0.9,beta=2,kappa=2",
    "ukf:gate=skip,gate_g=0.05", "ukf:gate=inflate,gate_g=0.1", "ukf:Qs=0", "ukf:acc=false", "ukf:iters=1",
    "ukf:taulp=1", "ukf:taulp=0.5,taulpw=1,Qs=0",
    # ukf-bias: scale on/off and axes, sigma schemes, heading_free off, gating, rest, cap, no
    # disturbance model, accelerometer low-pass off
    "ukf-bias", "ukf-bias:scale=false", "ukf-bias:saxes=xyz", "ukf-bias:sigma=julier,kappa=1",
    "ukf-bias:sigma=merwe,alpha=1,kappa=0.5", "ukf-bias:hf=false", "ukf-bias:gate=skip,gate_g=0.05",
    "ukf-bias:acc=false", "ukf-bias:rest_time_s=0.3", "ukf-bias:iters=2", "ukf-bias:tauc=0", "ukf-bias:taulp=0",
    # ukf-bias's scale test off, and deciding within the windows
    "ukf-bias:sprt=0", "ukf-bias:sprt=0.3", "ukf-bias:sprt=0.45,saxes=xyz,hf=false",
    "ukf-bias:rtilt=inf", "ukf-bias:rtilt=0.0003,rest_time_s=0.3",
)


# ekf and ukf-bias in 9-D (a recording with a magnetometer): the gates, the rate term, the hard-iron fit (loosened
# so that the simulator's motion reaches it), and with fewer states
MAG_SPECS = (
    "ekf", "ekf:mhi=false", "ekf:mrate=inf,mtime=0", "ekf:mnorm=0.08,mdip=0.12,mref=2,mtime=1",
    "ekf:mhiw=3,mhires=5,mhicov=0.05", "ekf:bias=false,scale=false,mhiw=3,mhires=5,mhicov=0.05", "ekf:Rv=inf,Rm=0.01",
    "ekf:sprt=0.3",
    "ukf-bias", "ukf-bias:mhiw=3,mhires=5,mhicov=0.05", "ukf-bias:scale=false,mrate=inf,mtime=0", "ukf-bias:sprt=0.3",
)
FIELD_ENU_UT = np.array([0.0, 16.0, -41.0])


def reference(spec: str) -> str:
    """The spec with the numpy reference implementation."""
    impl = "impl=numpy"
    return spec + ("," if ":" in spec else ":") + impl


def assert_same(a, b) -> None:
    """Trajectories a (compiled) and b (reference): quaternions, every diagnostic, to TOL."""
    np.testing.assert_allclose(a.quat_wxyz, b.quat_wxyz, rtol=0, atol=TOL)
    assert list(a.diagnostics) == list(b.diagnostics)
    for key, ref in b.diagnostics.items():
        got, ref = np.asarray(a.diagnostics[key]), np.asarray(ref)
        assert got.shape == ref.shape and got.dtype == ref.dtype, key
        if ref.dtype.kind == "f":
            np.testing.assert_array_equal(np.isnan(got), np.isnan(ref), err_msg=key)
            np.testing.assert_allclose(got, ref, rtol=TOL, atol=TOL, equal_nan=True, err_msg=key)
        else:
            np.testing.assert_array_equal(got, ref, err_msg=key)


def window(rec, start: int, stop: int) -> tuple[ImuSamples, np.ndarray]:
    """Samples start..stop of a recording and the true orientation at the first one."""
    imu = rec.imu
    part = imu.window(start, stop)
    rot, mask = rec.truth.interpolate(part.t[:1])
    return part, (rot.as_quat(scalar_first=True)[0] if mask[0] else quat.IDENTITY)


def broken(imu: ImuSamples) -> ImuSamples:
    """Invalid gyro stretch, NaN and inf gyro rows, NaN and inf accelerometer rows, a saturated
    (8 g) stretch. The stretch is 5 samples: with the disturbance model off (tauc=0) and no
    gate, each saturated sample turns the estimate by tens of degrees and rounding differences
    between any two implementations grow by a factor of several per sample (one ulp changed in
    one saturated sample moves the reference's nis by 4e-12; compiled and reference differ by
    6e-12 after 5 samples, 5e-10 after 10). Every other case agrees to 1e-13 or better."""
    gyr, acc, valid = imu.gyr_rad_s.copy(), imu.acc_g.copy(), imu.gyr_valid.copy()
    n = len(imu)
    valid[n // 5: n // 5 + 60] = False
    gyr[n // 3: n // 3 + 5] = np.nan
    gyr[n // 3 + 40, 1] = np.inf
    acc[n // 2: n // 2 + 7] = np.nan
    acc[n // 2 + 30, 2] = np.inf
    acc[n // 2 + 50: n // 2 + 55] = 8.0
    return imu.replace(gyr_rad_s=gyr, acc_g=acc, gyr_valid=valid)


@pytest.fixture(scope="module")
def sim():
    """2,500 samples of the built-in simulated recording (3 s rest, then hand-held motion)."""
    return window(datasets.load("sim"), 0, 2500)


@pytest.fixture(scope="module")
def sim_mag():
    """The first 4,000 samples of the simulated recording with a magnetometer along its truth
    (1 uT noise), a magnet carried with the sensor from sample 1,500, NaN and invalid samples."""
    rec = datasets.load("sim")
    imu, q0 = window(rec, 0, 4000)
    rot, _ = rec.truth.interpolate(imu.t)
    mag = rot.inv().apply(FIELD_ENU_UT) + np.random.default_rng(3).normal(0.0, 1.0, (len(imu), 3))
    mag[1500:] += [30.0, -25.0, 12.0]
    mag[700:720] = np.nan
    valid = np.ones(len(imu), bool)
    valid[900:950] = False
    return imu.replace(mag_ut=mag, mag_valid=valid), q0


@pytest.mark.slow
@pytest.mark.parametrize("spec", MAG_SPECS)
def test_compiled_equals_reference_in_9d(sim_mag, spec):
    imu, q0 = sim_mag
    a, b = build(spec).estimate(imu, q0), build(reference(spec)).estimate(imu, q0)
    assert_same(a, b)
    assert a.diagnostics["mag_used"].any()


@pytest.mark.slow
@pytest.mark.parametrize("spec", MAG_SPECS[:3])
def test_compiled_equals_reference_in_9d_with_broken_samples_from_a_wrong_start(sim_mag, spec):
    imu, q0 = sim_mag
    assert_same(build(spec).estimate(broken(imu), wrong_start(q0)),
                build(reference(spec)).estimate(broken(imu), wrong_start(q0)))


def test_the_9d_cases_reach_the_hard_iron_fit(sim_mag, broad):
    imu, q0 = sim_mag
    for name in ("ekf", "ukf-bias"):
        loose = build(f"{name}:mhiw=3,mhires=5,mhicov=0.05").estimate(imu, q0).diagnostics
        assert loose["mag_hard_iron"].any() and loose["mag_used"].any() and not loose["mag_used"].all()
        assert build(name).estimate(*broad).diagnostics["mag_used"].any()  # the BROAD trial is 9-D


@pytest.fixture(scope="module")
def course(data_dir):
    """ece276a/1, samples 0-3,000: the initial rest and the gyro freeze at 8.6 s (marked invalid)."""
    imu, q0 = window(datasets.load("ece276a/1", data_dir), 0, 3000)
    assert not imu.gyr_valid.all()
    return imu, q0


@pytest.fixture(scope="module")
def broad(data_dir):
    """BROAD trial 25 (tapping), 3,000 samples around the end of its initial rest (285.7 Hz)."""
    path = data_dir / "broad" / "25_disturbed_tapping_B.hdf5"
    if not path.is_file():
        pytest.fail(f"FUSION_DATA={data_dir} is set but {path} is missing")
    require_module("h5py")
    return window(datasets.load(str(path)), 11500, 14500)


@pytest.mark.slow
@pytest.mark.parametrize("spec", SPECS)
def test_compiled_equals_reference_on_the_simulator(sim, spec):
    imu, q0 = sim
    assert_same(build(spec).estimate(imu, q0), build(reference(spec)).estimate(imu, q0))


def wrong_start(q0: np.ndarray) -> np.ndarray:
    """An initial orientation 36 deg off in tilt: large innovations (the ekf's chi-square guard)."""
    return quat.multiply(q0, quat.from_rotvec(np.radians([30.0, -20.0, 0.0])))


@pytest.mark.slow
@pytest.mark.parametrize("spec", SPECS)
def test_compiled_equals_reference_with_broken_samples_from_a_wrong_start(sim, spec):
    imu, q0 = sim
    imu, q0 = broken(imu), wrong_start(q0)
    a, b = build(spec).estimate(imu, q0), build(reference(spec)).estimate(imu, q0)
    assert_same(a, b)
    if "acc=false" not in spec:
        assert a.diagnostics["updates_skipped"] > 0
        assert np.isnan(a.diagnostics["acc_var_g2"]).sum() > 1


@pytest.mark.slow
@pytest.mark.parametrize("spec", SPECS)
def test_compiled_equals_reference_on_a_course_recording(course, spec):
    imu, q0 = course
    assert_same(build(spec).estimate(imu, q0), build(reference(spec)).estimate(imu, q0))


@pytest.mark.slow
@pytest.mark.parametrize("spec", SPECS)
def test_compiled_equals_reference_on_a_broad_trial(broad, spec):
    imu, q0 = broad
    assert_same(build(spec).estimate(imu, q0), build(reference(spec)).estimate(imu, q0))


def test_the_cases_reach_the_rarer_branches(sim, course, broad):
    """The comparisons above are only as good as the branches they run through."""
    runs = {(spec, name): build(spec).estimate(imu, q0)
            for spec in ("ekf", "ukf-bias", "ukf-bias:iters=2", "ekf:gate=skip,gate_g=0.05")
            for name, (imu, q0) in (("sim", sim), ("course", course), ("broad", broad))}
    assert all(runs[spec, name].diagnostics["at_rest"].any() for spec in ("ekf", "ukf-bias") for name in ("sim", "broad"))
    for spec in ("ekf", "ukf-bias"):  # both the raw and the low-passed accelerometer are used
        lowpassed = np.concatenate([runs[spec, name].diagnostics["acc_lowpassed"] for name in ("sim", "course", "broad")])
        assert lowpassed.any() and not lowpassed.all()
    assert build("ekf").estimate(broken(sim[0]), wrong_start(sim[1])).diagnostics["bias_guarded"].any()
    assert runs["ukf-bias:iters=2", "sim"].diagnostics["mean_iteration_cap_hits"] > 0
    assert all(runs["ekf:gate=skip,gate_g=0.05", name].diagnostics["updates_skipped"] > 0 for name in ("sim", "course", "broad"))
    # the slow external acceleration acts on the BROAD trial (on the other two, it stays within what the
    # calibration explains)
    assert not np.array_equal(runs["ekf", "broad"].quat_wxyz, build("ekf:tauslow=0").estimate(*broad).quat_wxyz)


@pytest.mark.parametrize("spec", ["ekf", "ukf", "ukf-bias"])
def test_covariance_repair_and_square_root_recovery_agree(spec):
    """P = Q = 0 makes every Cholesky fail: the eigenvalue repair and the square-root fallback
    run on every step, in both paths."""
    from test_ukf import synthetic

    imu, truth = synthetic(200, noise=0.01)
    imu = broken(imu)
    zero = "Q=0,P0=0,Qinvalid=0" + (",Pb0=0,Qb=0,Ps0=0,Qsw=0" if spec != "ukf" else ",Qs=0")
    spec = f"{spec}:{zero}"
    a, b = build(spec).estimate(imu, truth[0]), build(reference(spec)).estimate(imu, truth[0])
    assert_same(a, b)
    assert a.diagnostics["cov_repairs"] > 0
    if not spec.startswith("ekf:"):  # the UKFs' matrix square root falls back to the eigen-decomposition
        assert a.diagnostics["sqrt_recoveries"] > 0


def test_covariance_repair_kernel_agrees_where_an_entry_is_huge_or_not_finite():
    """The kernel of `repair_covariance` resets P where the reference does: finite entries whose
    sum overflows, a non-finite entry; a huge entry whose sum is finite, or a large P, is kept."""
    from fusion.estimators.filters import _compiled  # noqa: F401  (the kernels, compiled or loaded)
    from fusion.estimators.kernels import _compiled_linalg, _linalg

    o = _compiled_linalg.cov_settings()
    nan = np.eye(4)
    nan[1, 2] = nan[2, 1] = np.nan
    cases = {"sum overflows": np.full((11, 11), 9e306) + np.eye(11) * 1e307,
             "huge, sum finite": np.diag([5e300, 1.0, 2.0]),
             "large": np.eye(11) * 1e299,
             "not finite": nan}
    outcomes = {}
    for name, P0 in cases.items():
        P = P0.copy()
        repaired = _compiled_linalg.repair_covariance(P, len(P), o, np.empty_like(P))
        with np.errstate(over="ignore"):  # the reference's sum overflows: what the case is about
            ref, ref_repaired = _linalg.repair_covariance(P0.copy())
        assert repaired == ref_repaired, name
        np.testing.assert_array_equal(P, ref, err_msg=name)
        outcomes[name] = repaired
    assert outcomes == {"sum overflows": True, "huge, sum finite": False, "large": False, "not finite": True}


@pytest.mark.parametrize("spec", ["ekf", "ukf", "ukf-bias"])
def test_compiled_estimate_leaves_the_filter_where_the_steps_do(sim, spec):
    """After `estimate`, `current()` and further `step`s continue as after the reference's loop."""
    imu, q0 = sim
    a, b = build(spec), build(reference(spec))
    a.estimate(imu, q0)
    b.estimate(imu, q0)
    for key, value in b.current().items():
        np.testing.assert_allclose(a.current()[key], value, rtol=TOL, atol=TOL, err_msg=key)
    assert a.diagnostics() == b.diagnostics()
    (gyr, valid), acc = imu.interval_rates(), imu.acc_g
    for k in range(300):
        np.testing.assert_allclose(a.step(gyr[k], 0.01, acc[k], valid[k]), b.step(gyr[k], 0.01, acc[k], valid[k]),
                                   rtol=0, atol=TOL)


@pytest.mark.parametrize("spec", ["ekf:mhiw=3,mhires=5,mhicov=0.05", "ukf-bias:mhiw=3,mhires=5,mhicov=0.05"])
def test_compiled_9d_estimate_leaves_the_filter_where_the_steps_do(sim_mag, spec):
    """As above in 9-D: the magnetometer reference and the hard-iron sums carry over."""
    imu, q0 = sim_mag
    a, b = build(spec), build(reference(spec))
    a.estimate(imu, q0)
    b.estimate(imu, q0)
    np.testing.assert_allclose(a._mag.state(), b._mag.state(), rtol=TOL, atol=TOL)
    np.testing.assert_allclose(a._hard_iron.state(), b._hard_iron.state(), rtol=TOL, atol=TOL)
    (gyr, valid), acc, mag = imu.interval_rates(), imu.acc_g, imu.mag_ut
    for k in range(2000, 2300):
        np.testing.assert_allclose(a.step(gyr[k], 0.01, acc[k + 1], valid[k], mag[k + 1]),
                                   b.step(gyr[k], 0.01, acc[k + 1], valid[k], mag[k + 1]), rtol=0, atol=TOL)


@pytest.mark.parametrize("spec", ["ekf", "ukf", "ukf-bias"])
def test_first_row_is_the_initial_quaternion_as_given(spec):
    from test_ukf import synthetic

    imu, truth = synthetic(50)
    q0 = 3.0 * truth[0]  # not normalised: recorded as given, normalised for the filter
    a, b = build(spec).estimate(imu, q0), build(reference(spec)).estimate(imu, q0)
    np.testing.assert_array_equal(a.quat_wxyz[0], q0)
    assert_same(a, b)


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_a_single_sample_recording(spec):
    imu = ImuSamples(np.array([0.0]), np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
    a, b = build(spec).estimate(imu, quat.IDENTITY), build(reference(spec)).estimate(imu, quat.IDENTITY)
    assert_same(a, b)


@pytest.mark.parametrize("spec", ["ekf:impl=lean", "ekf:impl=filterpy", "ukf:impl=reference", "ukf-bias:impl=fast"])
def test_unknown_implementations_raise(spec):
    with pytest.raises(ValueError, match="impl"):
        build(spec)


def test_impl_lean_is_the_former_name_of_impl_numpy():
    with pytest.warns(FutureWarning, match="impl=lean is now called impl=numpy"):
        params = build("ukf-bias:impl=lean").params
    assert params.impl == "numpy" and params == build("ukf-bias:impl=numpy").params


def test_compiled_is_the_default():
    assert build("ekf").params.impl == build("ukf").params.impl == build("ukf-bias").params.impl == "compiled"


def test_without_a_writable_cache_folder_the_kernels_still_run():
    """numba raises at decoration when it finds no writable cache folder; the module warns once
    and compiles without a cache. Simulated by allowing only the NUMBA_CACHE_DIR locator with
    NUMBA_CACHE_DIR unset (what a read-only install and a read-only home give)."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["NUMBA_CACHE_LOCATOR_CLASSES"] = "UserProvidedCacheLocator"
    code = ("import warnings; warnings.simplefilter('always')\n"
            "from fusion.estimators.filters import _compiled as c\n"
            "from fusion.estimators.kernels import _numba\n"
            "assert not _numba._cache\n"
            "print(c.qmul((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)))\n")
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "(0.0, 1.0, 0.0, 0.0)"
    assert run.stderr.count("cannot be cached") == 1, run.stderr


def test_numba_is_imported_only_for_the_compiled_filters():
    code = ("import sys\n"
            "from fusion.estimators import build\n"
            "for spec in ('ekf:impl=numpy', 'ukf:impl=numpy', 'ukf-bias:impl=filterpy,hf=false'):\n"
            "    build(spec)\n"
            "assert 'numba' not in sys.modules\n"
            "from fusion.estimators.filters import _compiled\n"
            "assert not _compiled._loaded\n"
            "build('ukf')\n"
            "assert _compiled._loaded\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["ekf", "ukf-bias", "ukf", "ekf:Rv=inf,taulp=1"])
def test_compiled_equals_reference_through_an_unflagged_freeze(data_dir, spec):
    """ece276a/1 loaded with its freeze left in (`--dropouts off`): the online stuck-gyro check
    marks the same readings in the numpy step and in the compiled batch path."""
    rec = datasets.LoadOptions(dropouts=False).load(datasets.select("ece276a/1", data_dir)[0])
    imu, q0 = window(rec, 0, 3000)
    assert imu.gyr_valid.all()
    a, b = build(spec).estimate(imu, q0), build(reference(spec)).estimate(imu, q0)
    assert_same(a, b)
    off = build(spec + ("," if ":" in spec else ":") + "stuck=false").estimate(imu, q0)
    assert np.abs(off.quat_wxyz - a.quat_wxyz).max() > 0.01  # the check changed the estimate


# The compiled modules of each room (below fusion.estimators), whose kernels declare their references.
KERNEL_MODULES = {
    "filters": ("kernels._numba", "kernels._compiled_quaternion", "kernels._compiled_linalg",
                "filters.steps._compiled_accel", "filters.steps._compiled_rest", "filters.steps._compiled_stuck",
                "filters.steps._compiled_scale_test", "filters.steps._compiled_magnetometer", "filters._compiled_ekf",
                "filters._compiled_ukf"),
    "smoothers": ("smoothers._compiled_terms", "smoothers._compiled_cost", "smoothers._compiled_linearize",
                  "smoothers._compiled_start"),
    "peers": ("peers._compiled_ahrs",),
}
# A peer's twin carries the library method's name after its filter's (`madgwick_updateIMU` is
# `Madgwick.updateIMU`'s), or with a leading underscore (`_product`: `Quaternion.product`).
PEER_PREFIXES = ("madgwick_", "mahony_", "ekf_", "_")


def _resolve(dotted: str):
    """The object a dotted name such as `fusion.estimators.filters.ekf.EKF._correct` names (ImportError or
    AttributeError when there is none)."""
    import pkgutil

    return pkgutil.resolve_name(dotted)


@pytest.mark.parametrize("room", sorted(KERNEL_MODULES))
def test_every_kernel_carries_the_name_of_the_reference_it_declares(room):
    """A reader finds a kernel by its reference's name, by one convention in every room (STYLE 12):
    every compiled function of the filters, the smoothers and the peers' twins declares the function
    or method it implements (`_numba.mirrors`, `_numba.compiled`: the numpy reference, or for the
    peers the library's), which exists and has the kernel's name, or is listed among its module's
    HELPERS (no reference of its own); a kernel is bound to its own name, and no two of the
    smoothers' kernels share one."""
    import importlib

    from numba.core.registry import CPUDispatcher

    from fusion.estimators.kernels import _numba

    if room == "peers":
        require_module("ahrs")
    seen, names, references = 0, {}, {}
    for name in KERNEL_MODULES[room]:
        module = importlib.import_module(f"fusion.estimators.{name}")
        helpers = set(module.HELPERS)
        own = {attr for attr, obj in vars(module).items() if isinstance(obj, CPUDispatcher)
               and ((module.__name__, attr) in _numba.REFERENCES or obj.py_func.__module__ == module.__name__)}
        assert helpers <= own, f"{name}.HELPERS names no kernel: {sorted(helpers - own)}"
        for attr in sorted(own):
            kernel = vars(module)[attr]
            if kernel.py_func.__module__ == module.__name__:
                assert kernel.py_func.__name__ == attr, f"the kernel {kernel.py_func.__name__} is bound to the name {attr}"
            if room == "smoothers":  # their modules import each other's kernels by name: one kernel a name
                assert names.setdefault(attr, kernel) is kernel, f"two kernels named {attr} in {room}"
        for attr in sorted(own - helpers):
            reference = _numba.REFERENCES.get((module.__name__, attr))
            assert reference is not None, f"{name}.{attr} declares no reference and is not a helper"
            last = reference.rsplit(".", 1)[1]
            if room == "peers":
                assert attr == last or any(attr == prefix + last for prefix in PEER_PREFIXES), (attr, reference)
            else:
                assert last == attr, f"{name}.{attr} mirrors {reference}: the names differ"
            target = _resolve(reference)
            assert callable(target) and target.__name__ == last, reference
            references[attr] = reference
            seen += 1
    assert seen >= {"filters": 30, "smoothers": 15, "peers": 8}[room]
    if room == "filters":  # both kernels and the rest detector's names as the style's examples give them
        assert references["_correct"] == "fusion.estimators.filters.ekf.EKF._correct"
        assert _numba.REFERENCES[("fusion.estimators.filters.steps._compiled_rest", "update")] == \
            "fusion.estimators.filters.steps._rest.RestDetector.update"
        assert _numba.REFERENCES[("fusion.estimators.filters._compiled_ekf", "estimate")] == \
            "fusion.estimators.filters.ekf.EKF.estimate"
    if room == "smoothers":  # what the solvers run, each under its reference's name
        assert references["cost"] == "fusion.estimators.smoothers.cost.SmootherProblem.cost"
        assert references["linearize"] == "fusion.estimators.smoothers.cost.SmootherProblem.linearize"
        assert references["retract"] == "fusion.estimators.smoothers.smoother.retract"
        assert references["levelled"] == "fusion.estimators.smoothers.smoother.levelled"
        assert references["robust_terms"] == "fusion.estimators.smoothers.cost.robust_terms"
        assert references["multiply_floats"] == "fusion.quaternion.multiply_floats"  # compiled from the core
    if room == "peers":
        assert references["madgwick_updateIMU"] == "ahrs.filters.madgwick.Madgwick.updateIMU"


def test_the_packed_states_match_their_layout():
    """`state()` of every packed helper has the length its layout declares and puts each field at
    its offset (the kernels read the same offsets)."""
    from fusion.estimators.filters.steps import _accel, _magnetometer, _rest, _scale_test, _stuck

    dist = _accel.AccDisturbance(1.0, 2.0, 3.0, lag=True)
    dist.update((1.0, 0.0, 0.0, 0.0), np.array([0.1, 0.2, 0.9]), 0.01, np.array([0.1, 0.2, 0.3]), np.ones(3))
    dist.update(quat.exp_floats(0.01, 0.02, 0.03), np.array([0.1, 0.2, 0.95]), 0.01, np.array([0.1, 0.2, 0.3]),
                np.ones(3))
    st = dist.state()
    assert st.shape == (_accel.DIST_STATE,)
    assert tuple(st[_accel.DIST_MEAN:_accel.DIST_MEAN + 3]) == dist.m and st[_accel.DIST_VAR] == dist.v
    assert tuple(st[_accel.DIST_FRAME:_accel.DIST_FRAME + 4]) == dist.qi and st[_accel.DIST_AGE] == dist.age
    assert np.array_equal(st[_accel.DIST_BODY:_accel.DIST_BODY + 3], dist.lowpass_body)
    assert st[_accel.DIST_DENSITY] == dist.lowpass_density
    assert np.array_equal(st[_accel.DIST_LAG_S:_accel.DIST_STATE], dist.lag.N[1].ravel())
    again = _accel.AccDisturbance(1.0, 2.0, 3.0, lag=True)
    again.set_state(st)
    assert np.array_equal(again.state(), st)
    rest = _rest.RestDetector(0.1, 0.1, 0.5, tilt_rad=0.01)
    rest.update(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.01)
    rest.update(np.zeros(3), np.array([0.0, 0.01, 1.0]), 0.01)
    assert rest.state().shape == (_rest.REST_STATE,) and rest.state()[_rest.REST_TIME_STILL] == rest.time_still
    assert np.array_equal(rest.state()[_rest.REST_START:_rest.REST_START + 3], rest.lp0) and rest.lp0[2] == 1.0
    again = _rest.RestDetector(0.1, 0.1, 0.5, tilt_rad=0.01)
    again.set_state(rest.state())
    assert np.array_equal(again.state(), rest.state())
    mag = _magnetometer.MagReference(0.1, 0.1, 1.0, 10.0)
    mag.update(50.0, 0.9, 0.01)
    assert mag.state().shape == (_magnetometer.MAG_STATE,) and mag.state()[_magnetometer.MAG_DIP] == 0.9
    assert _magnetometer.HardIron(1.0, 1.0, 0.1).state().shape == (_magnetometer.HARD_IRON_STATE,)
    test = _scale_test.ScaleTest(1e-2, 1e-4, 0.1, np.ones(3, dtype=bool))
    assert test.state()[_scale_test.TEST_ON] == 1.0 and test.state().shape == (_scale_test.TEST_STATE,)
    assert _stuck.stuck_gyro_state().shape == (_stuck.STUCK_STATE,)

