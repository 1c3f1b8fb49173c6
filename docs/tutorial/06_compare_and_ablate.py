# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 6. Everything side by side, and what each setting is worth
#
# The previous notebooks took estimators apart on one recording. Now all of them, ours and the
# community's, on every course recording, scored the same way; then ablations: one estimator
# over a grid of parameter values, to see which choices matter.
#
# Everything here is the library behind the command line: `fusion.evaluation.runs.run_compare`
# is `fusion compare`, `run_ablate` is `fusion ablate`. Each call returns the rows (one per
# recording and estimator: its scores, timing and coverage; a sweep of hundreds of jobs keeps
# rows, not trajectories) and the table the command prints.
#
# The estimators (`fusion.estimators.ESTIMATORS`):
#
# | name | what | sees the future |
# |---|---|---|
# | `dr` | gyro integration (notebook 2) | no |
# | `ukf` | Kraft's quaternion UKF, adaptive noise (notebook 3) | no |
# | `ukf-bias`, `ekf` | UKF / error-state EKF with gyro bias and x/y scale states (notebook 4) | no |
# | `gn`, `gd` | batch smoother, Gauss-Newton / gradient descent (notebook 5) | yes |
# | `vqf`, `vqf-basic`, `vqf-offline` | VQF (Laidig & Seel 2023), `vqf` package | offline: yes |
# | `madgwick`, `mahony`, `ahrs-ekf` | the `ahrs` package's filters | no |
# | `fusion-ahrs` | x-io's Fusion (`imufusion` package) | no |
#
# Every estimator gets the same calibrated samples and the same initial orientation (VICON's at
# the first IMU sample); the peers run with their libraries' defaults.

# %%
# %matplotlib inline
import matplotlib.pyplot as plt
import numpy as np

from fusion.estimators import ESTIMATORS, resolve_all
from fusion.evaluation.runs import run_ablate, run_compare
from tutorial_data import course_recordings, load_recording

plt.rcParams.update({"figure.figsize": (10, 3.6), "axes.grid": True, "figure.dpi": 90})
rec = load_recording("ece276a/1")  # prints where the data come from
ids = course_recordings()
DATASETS = ",".join(ids)
JOBS = 2  # worker processes; the results do not depend on it
print(f"{len(ids)} recordings:", DATASETS)
# The ablations run on three of them (one with a gyro freeze, two without) to keep this
# notebook under two minutes; pass DATASETS instead to run them on all.
ABLATION = ",".join([rid for rid in ("ece276a/1", "ece276a/3", "ece276a/6") if rid in ids] or ids[:3])
print("ablations on:", ABLATION)

# %% [markdown]
# ## 6.1 The comparison
#
# `run_compare("all", ...)` runs every registered estimator (a peer whose library is missing is
# left out with a warning) on every recording. To keep this notebook under two minutes we leave
# out two: `gd` (a millisecond per sample; notebook 5 compares it with `gn`) and `ukf-bias`
# (within hundredths of a degree of `ekf` at twice its cost, notebook 4). `fusion compare
# --estimators all` runs them all; `docs/results.md` has the full tables.

# %%
specs = [spec for spec in resolve_all("all") if spec.spec.name not in ("gd", "ukf-bias")]
print("estimators:", ", ".join(spec.label for spec in specs))
run = run_compare(specs, DATASETS, jobs=JOBS)
print(run.table)

# %% [markdown]
# The table first gives the mean over the recordings per estimator, then every recording. Three
# columns of RMSE (notebook 2): the total error, the inclination (what a gyro and an accelerometer
# can observe) and the heading (what they cannot). `us/sample` is the wall time per sample,
# measured on this machine while other work may have been running: treat it as a rough guide.
#
# As pictures: the inclination per estimator and recording, then accuracy against cost.

# %%
labels = list(dict.fromkeys(r.estimator for r in run.results))
datasets = list(dict.fromkeys(r.dataset for r in run.results))
rmse = {kind: np.full((len(labels), len(datasets)), np.nan) for kind in ("total", "inclination", "heading")}
us = np.zeros(len(labels))
for r in run.results:
    i, j = labels.index(r.estimator), datasets.index(r.dataset)
    us[i] += r.us_per_sample / len(datasets)
    if r.rmse_deg:
        for kind in rmse:
            rmse[kind][i, j] = r.rmse_deg[kind]
fig, ax = plt.subplots(figsize=(10, 4.6))
top = np.nanpercentile(rmse["inclination"], 95)
image = ax.imshow(rmse["inclination"], cmap="viridis", vmin=0, vmax=top)
for i in range(len(labels)):
    for j in range(len(datasets)):
        value = rmse["inclination"][i, j]
        ax.text(j, i, f"{value:.1f}", ha="center", va="center", fontsize=7, color="k" if value > 0.6 * top else "w")
ax.set(xticks=range(len(datasets)), xticklabels=[d.split("/")[-1] for d in datasets], yticks=range(len(labels)),
       yticklabels=labels, xlabel="course recording", title="inclination RMSE (deg)")
ax.grid(False)
fig.colorbar(image, ax=ax, label="deg")
plt.show()

# %%
causal = {name: ESTIMATORS[name.split(":")[0]].causal for name in labels}
fig, axes = plt.subplots(1, 2)
for ax, kind in zip(axes, ("inclination", "total")):
    mean = np.nanmean(rmse[kind], axis=1)
    for i, name in enumerate(labels):
        ax.plot(us[i], mean[i], "o" if causal[name] else "s", color="tab:blue" if causal[name] else "tab:red")
        ax.annotate(name, (us[i], mean[i]), textcoords="offset points", xytext=(4, 3 if i % 2 else -9), fontsize=7)
    ax.set(xscale="log", xlabel="wall time per sample (us, log)", ylabel=f"mean {kind} RMSE (deg)",
           title=f"{kind}: blue filters, red smoothers / offline")
plt.tight_layout()
plt.show()

# %% [markdown]
# What to read from it (the numbers are those of the course recordings; the table above has
# yours):
#
# * **Inclination** is where estimators differ by design. The smoother `gn` is best: it sees the
#   whole recording and estimates the gyro scale factors. Among the causal filters `ekf` leads,
#   helped by its scale-factor states; plain `ukf`, then the peers, which do not model the board's
#   4-9 % scale errors, follow. Recordings 6 and 7 (fast motion, gyro samples beyond 300 deg/s)
#   separate the peers most.
# * **Heading** is not observable: its error is integration error, from gyro freezes and gyro
#   scale errors. On recording 4 (a 2.8 s freeze) every estimator loses 14-20 degrees of
#   heading: nothing can recover the rotation that happened while the gyro was frozen. On
#   recording 3 (no freeze, much turning) the estimators without scale-factor states lose 8-19
#   degrees, `ekf` and `gn` 2-4. On average `dr`'s heading error is about that of plain `ukf` and
#   of most peers; the estimators with scale-factor states gain a degree or two.
# * **Cost** spans four orders of magnitude: the compiled peers (VQF in C++, Fusion in C) need
#   between a fraction of a microsecond and a few tens per sample, the Python filters (ours and the
#   `ahrs` package's) one to a few hundred. Filters that must run on a small board need the left
#   of the plot.
#
# The same comparison on the fourteen BROAD trials (another IMU at 286 Hz, with BROAD's own protocol,
# `docs/results.md`) is the command below. It takes several minutes, so it is not run here:
#
#     fusion compare --estimators all --dataset 'broad/*' --jobs 2
#
# ## 6.2 Ablation: the noise parameters Q and R
#
# Which parameter matters? `run_ablate(estimator, params)` runs the Cartesian product of the
# values given (each setting labelled as `compare` would label it) and, below its table, reads the
# result as the BROAD benchmark does: the best *common* setting (lowest mean over the recordings)
# and each recording's own best. We sweep the gyro noise density Q (rad$^2$/s) and the
# accelerometer noise density R (g$^2$ s) of Kraft's plain filter (`ukf:tauc=0,Qs=0`, notebook 3),
# a decade apart each, around the defaults (1e-3, 3e-5):

# %%
PLAIN = "ukf:tauc=0,Qs=0"
Q_VALUES, R_VALUES = ["1e-4", "1e-3", "1e-2"], ["3e-6", "3e-5", "3e-4"]
grid = run_ablate(PLAIN, [("Q", Q_VALUES), ("R", R_VALUES)], dataset=ABLATION, jobs=JOBS)
print(grid.table.split("\n\n")[-1])  # the sweep summary under the table

# %%
fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
for ax, kind in zip(axes, ("inclination", "total")):
    mean = np.zeros((len(Q_VALUES), len(R_VALUES)))
    for a, qv in enumerate(Q_VALUES):
        for b, rv in enumerate(R_VALUES):
            label = f"{PLAIN},Q={qv},R={rv}"
            mean[a, b] = np.mean([r.rmse_deg[kind] for r in grid.results if r.estimator == label and r.in_means])
    image = ax.imshow(mean, cmap="viridis")
    for a in range(len(Q_VALUES)):
        for b in range(len(R_VALUES)):
            tau = np.sqrt(float(R_VALUES[b]) / float(Q_VALUES[a]))
            color = "k" if mean[a, b] > mean.min() + 0.6 * np.ptp(mean) else "w"
            ax.text(b, a, f"{mean[a, b]:.2f}\n(tau {tau:.2g} s)", ha="center", va="center", fontsize=8, color=color)
    ax.set(xticks=range(len(R_VALUES)), xticklabels=R_VALUES, yticks=range(len(Q_VALUES)), yticklabels=Q_VALUES,
           xlabel="R, accelerometer noise density (g^2 s)", ylabel="Q, gyro noise density (rad^2/s)",
           title=f"{PLAIN}: mean {kind} RMSE (deg)")
    ax.grid(False)
    fig.colorbar(image, ax=ax)
plt.tight_layout()
plt.show()
default = [r for r in run.results if r.estimator == "ukf" and r.dataset in ABLATION.split(",") and r.in_means]
print(f"the default ukf on the same recordings: inclination {np.mean([r.rmse_deg['inclination'] for r in default]):.2f}, "
      f"total {np.mean([r.rmse_deg['total'] for r in default]):.2f} deg")

# %% [markdown]
# Along each diagonal of the grid the ratio $R/Q$ is constant, and so is the time constant with
# which the accelerometer pulls the tilt back, $\tau = \sqrt{R/Q}$ (printed in each cell). On the
# course recordings the inclination is the same along each diagonal to about the second decimal:
# it depends on $\tau$, not on $Q$ and $R$ separately. Too small a $\tau$ (trust the accelerometer) and
# every hand acceleration tilts the estimate; too large, and the gyro's errors accumulate before the
# accelerometer corrects them. The total error, mostly heading, prefers a longer $\tau$ than the
# inclination does: the accelerometer's corrections also turn the estimate about the vertical
# (notebook 3), and the heading pays for every one. The default `ukf` (the line under the figure)
# beats every cell of the grid on both: it adapts $R$ to the measured external acceleration and
# inflates $Q$ with the rate, so it can afford a short $\tau$ when the board is quiet and a long one
# when the hand accelerates.
#
# ## 6.3 Ablation: the sigma points
#
# The preset `sigma` compares Kraft's sigma points with Julier's (a centre point with weight
# $\kappa/(n + \kappa)$) and Van der Merwe's scaled points:

# %%
sigma_run = run_ablate(preset="sigma", dataset=ABLATION, jobs=JOBS)
for line in sigma_run.table.splitlines():
    if line.startswith(("mean", "best", "each", "RMSE", "dataset")):
        print(line)

# %% [markdown]
# The inclination does not change at all, the heading by a tenth of a degree. All three schemes
# reproduce the mean and the covariance exactly; they differ only in the higher moments of the
# distribution they represent, and at the filter's working point (a tilt $\sigma$ of a degree,
# notebook 4) the models are so close to linear that higher moments hardly matter. Sigma-point
# schemes are worth comparing for large uncertainties, not here.
#
# ## 6.4 A fair comparison: every estimator tuned by one protocol, judged out of sample
#
# The table of 6.1 puts our filters, whose defaults were chosen on recordings like these, beside
# the peers at their libraries' defaults: a comparison of defaults, not of algorithms. BROAD's
# study (Laidig et al., Data 2021) tunes every filter over a grid and reports its best *common*
# setting; Caruso et al. (Sensors 2021) found that well-tuned filters often do not differ
# significantly. `run_tune` (`fusion tune`) does both things honestly: every estimator searches its
# declared space (`fusion list NAME` shows it) by the same protocol, and the figure that counts is
# *out of sample*: each recording scored with the setting chosen on the other recordings.
#
# Then the question is whether a difference is real. Over recordings, the tuned rows are compared
# as Demsar (JMLR 2006) recommends for many data sets: the Friedman test over all rows, average ranks
# with Nemenyi's critical difference (the diagram: rows joined by a bar do not differ significantly
# at 5 %), and each row paired against the best by the Wilcoxon signed-rank test, Holm-corrected.

# %%
from fusion.evaluation.scoring.stats import paired_statistics
from fusion.evaluation.report.stats_plots import cd_figure
from fusion.evaluation.sweeps.tune import run_tune

TUNED = "ekf,vqf,madgwick,mahony"
if len(ids) >= 5:
    tuning = run_tune(TUNED, DATASETS, jobs=JOBS)
    print(tuning.table)
    out_of_sample = {f"{t.estimator} tuned": t.scores_tuned for t in tuning.tunings}
    statistics = paired_statistics(out_of_sample, metric="total")
    figure = cd_figure(statistics, title="tuned out of sample: average rank of the total RMSE (1 = best)")
    plt.show()
    print(f"{'':<16} {'mean':>6} {'95 % CI':>15} {'rank':>5}  W/T/L vs best  Holm p")
    for row in statistics.rows:
        ci = f"[{row.ci_low:.2f}, {row.ci_high:.2f}]" if row.ci_low is not None else ""
        p_holm = "best" if row.p_holm is None else f"{row.p_holm:.3f}"
        print(f"{row.label:<16} {row.mean:6.2f} {ci:>15} {row.rank:5.2f}  {row.wins}/{row.ties}/{row.losses:<10} {p_holm}")
else:
    print("NOTE: tuning needs five recordings or more; this data folder has", len(ids))

# %% [markdown]
# Read the table from left to right: the library default, the best common setting and each
# recording's own best (both *in sample*: chosen and judged on the same recordings, so they flatter),
# then `tuned`, the honest figure. A peer that looks far behind at its default (Mahony's integral
# gain, for instance, is far too high for these IMUs) often closes most of the gap once tuned; the
# difference between the in-sample and out-of-sample columns is what choosing a setting on the test
# data would have claimed for free. Whether the remaining differences are real is what the diagram
# says: with nine recordings only large differences in rank are significant.
#
# ## 6.5 Watching them: the run in 3-D, on one timeline with its events
#
# A table says how far each estimator is off; to see *when* and *why*, line the orientations up
# with the recording's events. [Rerun](https://rerun.io) (the `rerun-sdk` package, the `viz`
# extra) is a time-synchronised viewer of poses, images and scalar series; `--rerun FILE.rrd`
# writes the run as one of its recordings, which its viewer opens:
#
#     pip install -e '.[viz]'
#     fusion compare --estimators ekf,gn,vqf --dataset ece276a/1 --rerun run.rrd
#     rerun run.rrd                  # the native viewer; `rerun run.rrd --web-viewer` in a browser
#
# Each recording gets a tab: the truth (light grey) and each estimator (in its colour in the report's
# figures) as a board with its body axes (x red, y green, z blue), side by side, turning together as
# you scrub the timeline; the camera's frames (here rendered from a 360-degree photograph with the
# truth, as in notebook 7) on the truth's board; the total, inclination and heading error of each
# estimator; the recording's events as steps (rest, the gyro freeze, the samples marked invalid,
# tracking gaps; on BROAD its movement phases and magnetic disturbances) with a log line as each
# starts; what each filter believed (its $\sqrt{P_{ii}}$, NIS and NEES, and its rest-update, bias-guard
# and accelerometer-update flags as steps); every estimator's own flags as steps under
# `beliefs/<estimator>/flags/` (ours: the magnetometer's use, the low-passed accelerometer, the
# scale test's decision; VQF's rest and magnetic-disturbance detection; Fusion's rejections and
# recoveries); the calibrated gyro, accelerometer and magnetometer.
# The file of the command above, opened in Rerun's web viewer (`rerun run.rrd --web-viewer`; the
# screenshot is stored beside this notebook, it is not made when the notebook runs):

# %%
from IPython.display import Image

Image(filename="images/rerun_ece276a_1.jpg", width=960)

# %% [markdown]
# Below, the same run from Python, and the file read back with Rerun's own reader.

# %%
import tempfile
from collections import Counter
from pathlib import Path

from rerun.chunk import RrdReader

path = Path(tempfile.mkdtemp()) / "run.rrd"
run_compare("ekf,gn,vqf", rec.id, rerun=path, jobs=JOBS)
samples = Counter()
for chunk in RrdReader(path).stream():
    if not chunk.is_static:
        samples[chunk.entity_path] += chunk.num_rows
print(f"{path.name}: {path.stat().st_size / 1e6:.1f} MB, {len(samples)} entities")
for entity, count in sorted(samples.items()):
    print(f"{count:7d}  {entity}")

# %% [markdown]
# The bodies hold one orientation per IMU sample (the truth one per VICON sample, its gaps left
# out); the errors one value per scored sample; events and flags one value per switch. Scrub to the
# gyro freeze of `ece276a/1` (8.6-9.8 s, the `gyro_freeze` step under `events`): the gyro reads its
# zero-rate level while the board turns, so every estimator's board lags the truth's and the total
# errors jump to 3-5 deg inside it. What each carries out of it is heading: about 1.1-1.4 deg
# averaged over the next two seconds, from 0.2-0.4 deg before, for the filters and the smoother
# alike (no IMU-only estimator can observe the rotation about the vertical that the gyro missed),
# and it stays for the rest of the recording. VQF's `rest_detected` step rises in the rests at the
# start and the end, never inside the freeze: its rest detector watches the gyro and the
# accelerometer, and the accelerometer sees the motion the frozen gyro misses. The report of
# `fusion compare --out DIR` shows the same moments as a figure per recording: the total error with
# the recording's events shaded (rests, freezes, samples marked invalid, tracking gaps, magnetic
# disturbances, BROAD's movement phases), the longest incidents zoomed, and each estimator's flag
# switches marked.

# %% [markdown]
# ## Summary
#
# * `run_compare` / `fusion compare` runs any set of estimators on any recordings, scored the same
#   way; `--out DIR` writes the same results as `results.json`, figures and an HTML report.
# * On the course recordings: smoother > filters with scale-factor states > plain filters and
#   peers for inclination; heading is limited by the gyro (freezes, scale errors) for everyone.
# * `--rerun FILE.rrd` (the `viz` extra) writes the run for Rerun's viewer: every estimator beside
#   the truth in 3-D, on one timeline with the errors, the recording's events and the filters' flags.
# * `run_ablate` / `fusion ablate` sweeps parameters. For Kraft's plain UKF the balance of $R$ and
#   $Q$ (a time constant) is what to tune; the sigma-point scheme hardly matters.
#
# **Try it:** `run_ablate("ekf", ["tauc=0,0.1,0.5"], dataset=DATASETS)`: how much does the adaptive
# accelerometer noise (the correlation time of the external acceleration) buy?
