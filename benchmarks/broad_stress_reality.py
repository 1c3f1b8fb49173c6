"""Do the simulated faults rank the estimators as BROAD's real disturbed trials do?

    FUSION_DATA=../shared/data python benchmarks/broad_stress_reality.py [--estimators all] [--jobs 2]

1. Measured from the data (BROAD, Laidig et al. 2021, Data 6(7): 72):
   - vibration: trial 26 (phone vibration): the RMS of the accelerometer's part above 20 Hz (a 4th-order
     Butterworth high-pass, forward and backward) while the phone vibrates (its movement phases), less
     (in quadrature) the same RMS of the undisturbed trials' movement phases; and its frequency (the
     peak of Welch's spectrum above 20 Hz);
   - magnet: the Earth's field in BROAD's world frame, the median over the undisturbed trials of
     `R_world_body m` (their truth rotating each magnetometer sample into the world); in each
     magnet trial the disturbance `|m - R_world_body^T B_earth|` per sample; for the stationary
     magnet (trials 28, 30: the sensor passes a magnet) its passes (stretches above twice the
     largest 99th percentile of the same disturbance in the undisturbed trials, which is their noise
     floor: the field model's residual; merged when closer than 0.5 s) and their peak, the dipole's
     severity being the median peak; for the attached magnet (32, 34, 36: a hard iron while attached)
     the median disturbance over the samples above that floor's median, each trial's own hard-iron
     severity.
2. Simulated: `fusion stress` on the seven undisturbed trials with `vibration` at the measured RMS,
   `mag-dipole` at the measured peak and `mag-hard-iron` at each attached trial's offset (their
   models: `fusion.faults`); and three variants closer to how the trials were disturbed, built here
   from the same transforms and run on the same runner: the vibration only during the movement
   phases (trial 26 vibrates only then), the magnet passing at the speed that gives the long passes'
   measured duration above half their peak (a dipole's is 1.53 d / v), the hard iron only during a
   window in the middle of the trial as long as the magnet was attached. Real: `fusion compare` on
   the disturbed trials. Both 9-D where an estimator fuses the magnetometer (the default), BROAD's
   protocol, total RMSE.
3. Per disturbance, the estimators ranked by their error (mean over trials) under the simulated
   fault and on the real trials, and Spearman's rank correlation of the two (`scipy.stats.spearmanr`),
   with its p-value; also of the *increase* over each estimator's clean error (simulated: faulted
   minus clean on the same trials; real: the disturbed trials minus its mean over the undisturbed
   ones), and, as the yardstick, the correlation the clean undisturbed errors alone already have with
   the real disturbed ones (what any fault would inherit from the estimators' baseline accuracy).
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from scipy import signal, stats

from fusion import datasets, faults
from fusion.checks import runs as mask_runs
from fusion.faults import DIPOLE_DISTANCE_M, DIPOLE_SPEED_M_S, VIBRATION_HZ, Fault
from fusion.evaluation.run.runner import run
from fusion.evaluation.runs import run_compare, run_stress

VIBRATION = "broad/26_*"
STATIONARY = ("broad/28_*", "broad/30_*")
ATTACHED = ("broad/32_*", "broad/34_*", "broad/36_*")
HIGH_PASS_HZ = 20.0


def _load(selection: str):
    return [datasets.LoadOptions().load(s) for s in datasets.select(selection)]


def _high_passed(rec) -> np.ndarray:
    fs = 1.0 / np.median(np.diff(rec.imu.t))
    b, a = signal.butter(4, HIGH_PASS_HZ / (fs / 2), "high")
    return signal.filtfilt(b, a, np.asarray(rec.imu.acc_g) * 9.80665, axis=0)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(x**2, axis=1))))


def measure_vibration(undisturbed) -> tuple[float, float, float, float]:
    """(added RMS m/s^2, frequency Hz, trial 26's RMS, the undisturbed trials' RMS) above 20 Hz in movement."""
    (rec,) = _load(VIBRATION)
    hp = _high_passed(rec)
    during = _rms(hp[rec.movement])
    base = float(np.sqrt(np.mean([_rms(_high_passed(u)[u.movement]) ** 2 for u in undisturbed])))
    fs = 1.0 / np.median(np.diff(rec.imu.t))
    f, p = signal.welch(hp[rec.movement], fs=fs, axis=0, nperseg=4096)
    total = p.sum(axis=1)
    peak = float(f[np.argmax(np.where(f > HIGH_PASS_HZ, total, 0.0))])
    return float(np.sqrt(max(during**2 - base**2, 0.0))), peak, during, base


def earth_field(undisturbed) -> np.ndarray:
    """(3,) the Earth's field in BROAD's world frame, uT: the median over the undisturbed trials of
    each trial's median of R_world_body m."""
    per = []
    for rec in undisturbed:
        rot, mask = rec.truth.interpolate(rec.imu.t)
        ok = rec.imu.mag_valid[mask]
        per.append(np.median(rot.apply(np.asarray(rec.imu.mag_ut)[mask])[ok], axis=0))
    return np.median(per, axis=0)


def disturbance(rec, b_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t s from the first sample, |m - R^T B_earth| uT) over the samples with truth and a magnetometer."""
    rot, mask = rec.truth.interpolate(rec.imu.t)
    d = np.linalg.norm(np.asarray(rec.imu.mag_ut)[mask] - rot.inv().apply(b_world), axis=1)
    ok = rec.imu.mag_valid[mask]
    return (rec.imu.t[mask] - rec.imu.t[0])[ok], d[ok]


def passes(t: np.ndarray, d: np.ndarray, threshold: float, merge_s: float = 0.5) -> list[tuple[float, float, int]]:
    """(time s, peak uT, index of the peak) of each stretch above `threshold`, stretches closer than
    `merge_s` merged."""
    merged: list[list[int]] = []
    for a, b in mask_runs(d > threshold):
        if merged and t[a] - t[merged[-1][1] - 1] < merge_s:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    return [(float(t[a]), float(d[a:b].max()), a + int(np.argmax(d[a:b]))) for a, b in merged]


def half_peak_s(t: np.ndarray, d: np.ndarray, i: int) -> float:
    """How long the disturbance stays above half its peak around its peak at sample `i`."""
    above = d > d[i] / 2
    lo = hi = i
    while lo > 0 and above[lo - 1]:
        lo -= 1
    while hi < len(d) - 1 and above[hi + 1]:
        hi += 1
    return float(t[hi] - t[lo])


def _during(clean, faulted, mask: np.ndarray):
    """The recording with the faulted sensor samples where `mask`, the clean ones elsewhere (same stamps)."""
    imu = clean.imu.replace(acc_g=np.where(mask[:, None], faulted.imu.acc_g, clean.imu.acc_g),
                            mag_ut=np.where(mask[:, None], faulted.imu.mag_ut, clean.imu.mag_ut),
                            mag_valid=clean.imu.mag_valid)
    return faults.loader_checks(clean, replace(clean, imu=imu))


def _means(rows, kind=None, severity=None, trials=None) -> dict[str, float]:
    """Estimator -> mean total RMSE over its rows (of a fault kind and severity, over some trials)."""
    out: dict[str, list[float]] = {}
    for r in rows:
        f = r.fault or {"kind": "none", "severity": 0.0}
        if kind is not None and (f["kind"] != kind or (severity is not None and f["severity"] != severity)):
            continue
        if trials is not None and r.dataset not in trials:
            continue
        if r.rmse_deg:
            out.setdefault(r.estimator, []).append(r.rmse_deg["total"])
    return {k: float(np.mean(v)) for k, v in out.items()}


def _compare(name: str, sim: dict[str, float], real: dict[str, float], sim_clean: dict[str, float],
             real_clean: dict[str, float]) -> None:
    labels = [k for k in sim if k in real and k in sim_clean and k in real_clean]
    s = np.array([sim[k] for k in labels])
    r = np.array([real[k] for k in labels])
    ds = s - np.array([sim_clean[k] for k in labels])
    dr = r - np.array([real_clean[k] for k in labels])
    base = np.array([sim_clean[k] for k in labels])
    print(f"\n{name}: {len(labels)} estimators, total RMSE deg (sim: the undisturbed trials under the fault; "
          "real: the disturbed trials; clean: the undisturbed trials)")
    print(f"  {'estimator':<12} {'sim':>7} {'rank':>4} {'real':>7} {'rank':>4} {'sim-clean':>9} {'rank':>4} "
          f"{'real-clean':>10} {'rank':>4} {'clean':>6}")
    rs, rr, rds, rdr = (stats.rankdata(x) for x in (s, r, ds, dr))
    for i, k in enumerate(labels):
        print(f"  {k:<12} {s[i]:7.2f} {rs[i]:4.0f} {r[i]:7.2f} {rr[i]:4.0f} {ds[i]:+9.2f} {rds[i]:4.0f} "
              f"{dr[i]:+10.2f} {rdr[i]:4.0f} {base[i]:6.2f}")
    for what, a, b in (("errors under the fault vs the real disturbed trials", s, r),
                       ("increase over clean, simulated vs real", ds, dr),
                       ("yardstick: clean undisturbed errors vs the real disturbed trials", base, r)):
        rho, p = stats.spearmanr(a, b)
        print(f"  Spearman rho = {rho:+.3f} (p = {p:.2g}, n = {len(labels)}): {what}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--estimators", default="all")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    start = time.perf_counter()

    undisturbed = _load("broad/*_undisturbed_*")
    undisturbed_ids = [r.id for r in undisturbed]
    vib_rms, vib_hz, vib_during, vib_base = measure_vibration(undisturbed)
    print(f"vibration (trial 26): {vib_during:.2f} m/s^2 RMS above {HIGH_PASS_HZ:g} Hz while it vibrates, "
          f"{vib_base:.2f} in the undisturbed trials' movement: {vib_rms:.2f} m/s^2 RMS added, its peak at "
          f"{vib_hz:.1f} Hz (the model's: {VIBRATION_HZ:g} Hz)")
    b_world = earth_field(undisturbed)
    print(f"Earth's field, BROAD's world frame: {np.round(b_world, 2)} uT, |B| {np.linalg.norm(b_world):.2f} uT")
    floor = [disturbance(u, b_world)[1] for u in undisturbed]
    threshold = 2 * max(np.percentile(d, 99) for d in floor)
    attached_floor = float(np.median([np.percentile(d, 99) for d in floor]))
    print(f"the undisturbed trials' disturbance (the field model's residual): median "
          f"{np.median(np.concatenate(floor)):.1f} "
          f"uT, 99th percentiles {', '.join(f'{np.percentile(d, 99):.1f}' for d in floor)} uT: a pass is above "
          f"{threshold:.1f} uT, an attached magnet above {attached_floor:.1f} uT")
    peaks, offsets, durations, attached_share = [], {}, [], []
    for sel in STATIONARY + ATTACHED:
        (rec,) = _load(sel)
        t, d = disturbance(rec, b_world)
        if sel in STATIONARY:
            found = passes(t, d, threshold)
            peaks += [p for _, p, _ in found]
            durations += [half_peak_s(t, d, i) for _, _, i in found]
            print(f"  {rec.id}: {len(found)} passes over {threshold:.1f} uT, peaks "
                  f"{', '.join(f'{p:.0f}' for _, p, _ in found)} uT "
                  f"(at {', '.join(f'{a:.0f}' for a, _, _ in found)} s), above half their peak for "
                  f"{', '.join(f'{x:.2f}' for x in durations[-len(found):])} s")
        else:
            on = d > attached_floor
            offsets[rec.id] = float(np.median(d[on])) if on.any() else 0.0
            attached_share.append(float(on.mean()))
            print(f"  {rec.id}: attached magnet: median disturbance {offsets[rec.id]:.1f} uT over the "
                  f"{100 * on.mean():.0f}% of the samples above {attached_floor:.1f} uT")
    dipole = float(np.median(peaks))
    print(f"mag-dipole severity: the median pass peak, {dipole:.1f} uT; mag-hard-iron severities: "
          + ", ".join(f"{v:.1f}" for v in offsets.values()) + " uT")
    long = [x for x in durations if x > 0.5]
    slow = 1.53 * DIPOLE_DISTANCE_M / float(np.median(long)) if long else DIPOLE_SPEED_M_S
    share = float(np.mean(attached_share))
    print(f"the model's pass at {DIPOLE_SPEED_M_S:g} m/s stays above half its peak for "
          f"{1.53 * DIPOLE_DISTANCE_M / DIPOLE_SPEED_M_S:.2f} s; BROAD's passes longer than 0.5 s (median "
          f"{np.median(long) if long else float('nan'):.2f} s) need {slow:.3f} m/s; the magnets were attached for "
          f"{100 * share:.0f} % of their trials")

    hard = sorted({round(v, 1) for v in offsets.values()})
    texts = [f"vibration={vib_rms:.2f}", f"mag-dipole={dipole:.1f}",
             "mag-hard-iron=" + ",".join(f"{v:g}" for v in hard)]
    sim = run_stress(args.estimators, ",".join(undisturbed_ids), faults=texts, jobs=args.jobs).results
    # the variants, as the trials were disturbed: each recording built here, the runner given them loaded
    variants: dict[str, list] = {"vibration in movement": [], "dipole, slow": []}
    variants.update({f"hard iron {v:.1f} uT, attached": [] for v in offsets.values()})
    for rec in undisturbed:
        vib = faults.apply(rec, Fault("vibration", round(vib_rms, 2)))
        variants["vibration in movement"].append(_during(rec, vib, rec.movement))
        dip = faults.mag_dipole(rec, round(dipole, 1), faults.rng_for(rec.id, "mag-dipole"), speed_m_s=slow)
        variants["dipole, slow"].append(faults.loader_checks(rec, dip))
        s = rec.imu.t - rec.imu.t[0]
        window = np.abs(s - s[-1] / 2) <= share * s[-1] / 2
        for v in offsets.values():
            hard = faults.apply(rec, Fault("mag-hard-iron", round(v, 1)))
            variants[f"hard iron {v:.1f} uT, attached"].append(_during(rec, hard, window))
    items = [r for recs in variants.values() for r in recs]
    rows = run(args.estimators, items, jobs=args.jobs)
    per = len(rows) // len(items)
    variant_rows = {name: rows[per * k * len(undisturbed):per * (k + 1) * len(undisturbed)]
                    for k, name in enumerate(variants)}
    real = run_compare(args.estimators, ",".join(s.id for sel in (VIBRATION, *STATIONARY, *ATTACHED)
                                                 for s in datasets.select(sel)), jobs=args.jobs).results
    clean = _means(sim, "none")
    ids = {sel: datasets.select(sel)[0].id for sel in (VIBRATION, *STATIONARY, *ATTACHED)}
    _compare(f"vibration {vib_rms:.2f} m/s^2 RMS vs trial 26", _means(sim, "vibration"),
             _means(real, trials={ids[VIBRATION]}), clean, clean)
    _compare(f"mag-dipole {dipole:.1f} uT vs trials 28, 30 (stationary magnet)", _means(sim, "mag-dipole"),
             _means(real, trials={ids[s] for s in STATIONARY}), clean, clean)
    _compare(f"variant: vibration {vib_rms:.2f} m/s^2 RMS during the movement phases only vs trial 26",
             _means(variant_rows["vibration in movement"]), _means(real, trials={ids[VIBRATION]}), clean, clean)
    _compare(f"variant: mag-dipole {dipole:.1f} uT passing at {slow:.3f} m/s vs trials 28, 30",
             _means(variant_rows["dipole, slow"]), _means(real, trials={ids[s] for s in STATIONARY}), clean, clean)
    attached = {ids[s] for s in ATTACHED}
    for label, name in (("mag-hard-iron at each attached trial's offset", None),
                        ("variant: the same hard iron attached for the middle", "attached")):
        hard_sim: dict[str, list[float]] = {}
        for offset in offsets.values():  # each attached trial against the hard iron at its own offset
            means = (_means(sim, "mag-hard-iron", round(offset, 1)) if name is None
                     else _means(variant_rows[f"hard iron {offset:.1f} uT, attached"]))
            for k, v in means.items():
                hard_sim.setdefault(k, []).append(v)
        _compare(f"{label}{f' {100 * share:.0f} %' if name else ''} vs trials 32, 34, 36 (attached magnet)",
                 {k: float(np.mean(v)) for k, v in hard_sim.items()}, _means(real, trials=attached), clean, clean)
    print(f"\n{time.perf_counter() - start:.0f} s (jobs {args.jobs})")


if __name__ == "__main__":
    main()
