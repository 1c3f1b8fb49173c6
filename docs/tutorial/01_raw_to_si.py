# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 1. From raw counts to SI units
#
# An IMU does not give you angular rates and accelerations. It gives you numbers from an
# analogue-to-digital converter (ADC). Everything an orientation filter does later rests on how
# those numbers are turned into rad/s and g, and a filter cannot repair a wrong conversion: a
# gyro that reads 9 % too much turns every 90 degree turn into 98 degrees, for ever.
#
# In this notebook, on a real recording of the course board (VICON motion capture as the truth):
#
# 1. what the file holds (10-bit counts, unix time stamps);
# 2. the conversion `value = sign * (raw - bias) * scale` and where each number comes from;
# 3. the biases, from the stationary start of the recording;
# 4. checking the scales against physics: $|a| = 1\,g$ at rest, and the gyro against VICON;
# 5. what `fusion inspect` finds in a recording (gyro freezes, clock offsets, time-stamp jitter).
#
# Conventions used throughout: quaternions are scalar-first
# `[w, x, y, z]` and describe `R_world_body` (body vectors into the world frame, world z up);
# arrays are batch-first, `(N, 3)`; SI units inside (the accelerometer in g); degrees only in
# plots and tables.
#
# ## 1.0 Starting from a fetched trial
#
# Public orientation benchmarks can be fetched by name. In a terminal:
#
#     fusion data list                                 # the datasets: size, licence, citation, what is local
#     fusion data fetch 'broad/01*'                    # one BROAD trial (about 4 MB) into the user cache
#     fusion data fetch 'broad/01*' --to /tmp/fusion-data   # or into a folder of your choice
#
# or from Python, `fusion.fetch.fetch("broad/01*", to="/tmp/fusion-data")`. Every file is pinned to
# one commit of the repository that publishes it and checked against its git object id before it is
# kept, so everyone who fetches it scores the same bytes. A fetched trial then has a name that every
# command and the API take, without a data folder: `fusion compare --dataset 'broad/01*'`, or
# `datasets.select("broad/01*")` below (with `--to DIR`, add `--data-dir DIR`, or set
# `FUSION_DATA=DIR`). BROAD (Laidig et al. 2021, "BROAD - A Benchmark for Robust Inertial Orientation
# Estimation", Data 6(7):72) is a different IMU from the course board, with optical motion capture as
# its truth.
#
# The cell below finds the trial by name where `fusion compare` would: in `$FUSION_DATA` (the shared
# data folder holds it), else in the cache `fusion data fetch` fills. Set `FETCH = True` to download
# it first; the notebook never downloads unasked.

# %%
import numpy as np

from tutorial_data import fetched_trial

FETCH = False  # True: fetch 'broad/01*' into the user cache first (network, about 4 MB)
trial = fetched_trial("broad/01*", fetch_now=FETCH)  # datasets.select("broad/01*"), then datasets.load_source
steps = np.diff(trial.imu.t)
print(f"{1 / np.median(steps):.2f} Hz, {trial.imu.t[-1] - trial.imu.t[0]:.0f} s; "
      f"magnetometer: {'yes' if trial.imu.mag_ut is not None else 'no'}; "
      f"truth: {'yes' if trial.truth is not None else 'no'}; raw counts: {'none' if trial.raw is None else 'yes'}")
print("gyro rad/s, first sample:", np.round(trial.imu.gyr_rad_s[0], 4),
      "; |acc| g, median:", round(float(np.median(np.linalg.norm(trial.imu.acc_g, axis=1))), 3))

# %% [markdown]
# BROAD publishes its trials in SI units (rad/s, m/s^2, uT; the loader gives the accelerometer in
# g), so the trial has no raw counts (`raw` is None): it is ready for any estimator, e.g.
# `fusion compare --estimators ekf,vqf --dataset 'broad/01*'`. The course board's files hold ADC
# counts instead; turning them into the same units is what the rest of this chapter is about.

# %%
# %matplotlib inline
import matplotlib.pyplot as plt
import numpy as np

from fusion import gyro_fit
from fusion.calibration import BoardModel, rest_gravity_norms
from fusion.checks import vicon_body_rate
from fusion.evaluation.runs import run_calibrate, run_inspect
from tutorial_data import course_recordings, load_recording

plt.rcParams.update({"figure.figsize": (10, 3.2), "axes.grid": True, "figure.dpi": 90})
rec = load_recording("ece276a/1")
raw, calib, imu = rec.raw, rec.calibration, rec.imu
t = imu.t - imu.t[0]  # seconds since the first sample

# %% [markdown]
# ## 1.1 What the file holds
#
# The loader (`fusion.format_checks`) turns every file layout the courses published into one
# canonical form, `RawImu`: time stamps `t` (N,) in seconds (unix time) and `counts` (N, 6) in
# the order ax, ay, az, wx, wy, wz, exactly as the ADC produced them (the different channel
# orders and sign flips of the two releases are undone here, nowhere else).

# %%
print("t[:3]      =", raw.t[:3])
print("counts[:3] =\n", raw.counts[:3])
print("shape", raw.counts.shape, "; ADC range 0 ..", int(BoardModel().adc_full_scale_counts))

# %%
rest = slice(*calib.rest_start)
fig, axes = plt.subplots(1, 2, sharex=True)
names = ["ax", "ay", "az", "wx", "wy", "wz"]
for k in range(6):
    ax = axes[k // 3]
    ax.plot(t, raw.counts[:, k], lw=0.8, label=names[k])
for ax, what in zip(axes, ["accelerometer", "gyro"]):
    ax.axvspan(t[rest.start], t[rest.stop - 1], color="tab:green", alpha=0.15, label="detected rest")
    ax.set(xlim=(0, 20), xlabel="time since first sample (s)", ylabel="raw ADC counts", title=f"{what}, raw")
    ax.legend(loc="lower left", fontsize=8, ncol=2)
plt.tight_layout()
plt.show()

# %% [markdown]
# At rest every channel sits near the middle of the ADC range (about 500 counts for the
# accelerometer, 370 for the gyros): the sensors output a voltage around a zero level, and motion
# moves it up or down. The green band is the stationary start that `fusion.calibration.detect_rest`
# found: every channel's standard deviation over a 0.3 s window stays below a threshold.
#
# ## 1.2 The conversion
#
# For each channel,
#
# $$ \text{value} = \text{sign} \cdot (\text{raw} - \text{bias}) \cdot \text{scale},
#    \qquad \text{scale} = \frac{V_\text{ref}}{1023 \cdot \text{sensitivity}} . $$
#
# The datasheets give the sensitivities: the ADXL335 accelerometer about 300 mV/g at 3.0 V
# supply and ratiometric, i.e. about 330 mV/g at the board's 3.3 V; the rate gyros
# (LPR530AL, LY530ALH, 4x-amplified outputs) 3.33 mV/(deg/s). The x and y accelerometer axes
# point the other way from the body axes, hence sign -1. `BoardModel` holds these numbers,
# each in the unit its name says; we compute its scale vector by hand and compare.

# %%
board = calib.board
acc_g_per_count = board.vref_mv / board.adc_full_scale_counts / board.acc_sensitivity_mv_per_g
gyro_deg_s_per_count = board.vref_mv / board.adc_full_scale_counts / board.gyro_sensitivity_mv_per_deg_s
by_hand = np.r_[np.array(board.acc_sign) * acc_g_per_count,
                np.array(board.gyro_sign) * np.deg2rad(gyro_deg_s_per_count) * np.array(board.gyro_scale_factor)]
print(f"accelerometer: {acc_g_per_count:.6f} g per count = {1 / acc_g_per_count:.1f} counts per g")
print(f"gyro:          {gyro_deg_s_per_count:.4f} deg/s per count")
print("BoardModel.scale  =", board.scale)
print("by hand           =", by_hand, " equal:", np.allclose(by_hand, board.scale))

# %% [markdown]
# ## 1.3 Biases from the stationary start
#
# Still, the gyro reads zero rate, so the gyro bias is the mean of the rest window. The
# accelerometer is not reading zero at rest: it reads the reaction to gravity, +1 g along the
# body z axis when the board lies flat. So the x and y biases are their rest means, while the z
# bias is the rest mean *minus* 1 g worth of counts:
#
# $$ b_{x,y} = \overline{\text{raw}}_{x,y}, \qquad b_z = \overline{\text{raw}}_z - \frac{1\,g}{\text{scale}_z}, \qquad
#    b_{\omega} = \overline{\text{raw}}_{\omega} . $$

# %%
mean_rest = raw.counts[rest].mean(axis=0)
bias = mean_rest.copy()
bias[2] -= 1.0 / board.scale[2]
print("rest window:", calib.rest_start, f"= {t[rest.stop - 1]:.2f} s")
print("bias by hand       :", np.round(bias, 2))
print("calibration.bias   :", np.round(calib.bias_counts, 2), " equal:", np.allclose(bias, calib.bias_counts))
manual = (raw.counts - bias) * board.scale
print("calibrated by hand equals imu.acc_g / imu.gyr_rad_s:",
      np.allclose(manual[:, :3], imu.acc_g) and np.allclose(manual[:, 3:], imu.gyr_rad_s))

# %%
fig, axes = plt.subplots(1, 2, sharex=True)
for k, name in enumerate("xyz"):
    axes[0].plot(t, imu.acc_g[:, k], lw=0.8, label=f"a_{name}")
    axes[1].plot(t, np.rad2deg(imu.gyr_rad_s[:, k]), lw=0.8, label=f"w_{name}")
axes[0].set(xlim=(0, 20), xlabel="time (s)", ylabel="specific force (g)", title="accelerometer, calibrated")
axes[1].set(xlim=(0, 20), xlabel="time (s)", ylabel="angular rate (deg/s)", title="gyro, calibrated")
for ax in axes:
    ax.legend(fontsize=8, loc="lower left")
plt.tight_layout()
plt.show()

# %% [markdown]
# ## 1.4 Is the accelerometer scale right? $|a| = 1\,g$ at rest
#
# The classic check: at rest the accelerometer measures gravity only, so $|a|$ must be 1 g.
# `rest_gravity_norms` does it on the rest windows at the start and the end of the recording:

# %%
print({k: round(v, 4) for k, v in rest_gravity_norms(imu, calib).items()})

# %% [markdown]
# Both are 1.000 g, and yet this proves little: the z bias was *defined* so that the start reads
# exactly 1 g, and on these recordings the board ends lying flat again, so x and y carry almost no
# gravity in either window. A scale error of x or y only shows when gravity falls on x or y. VICON
# tells us the true up direction in the body frame, $R^\top e_z$; let us look at $|a|$ in every
# quasi-static sample (gyro below 0.1 rad/s) against the true tilt:

# %%
if rec.truth is not None:
    rot, has_truth = rec.truth.interpolate(imu.t)
    up_body = rot.inv().apply([0.0, 0.0, 1.0])  # (M, 3) true up direction, body frame (g)
    still = np.linalg.norm(imu.gyr_rad_s[has_truth], axis=1) < 0.1
    tilt_deg = np.degrees(np.arccos(np.clip(up_body[:, 2], -1.0, 1.0)))
    norm_g = np.linalg.norm(imu.acc_g[has_truth], axis=1)
    bins = np.arange(0, 181, 10)
    which = np.digitize(tilt_deg[still], bins) - 1
    medians = [(bins[b] + 5, np.median(norm_g[still][which == b])) for b in range(len(bins) - 1) if np.count_nonzero(which == b) >= 20]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(tilt_deg[still], norm_g[still], ".", ms=2, alpha=0.3, label="quasi-static samples")
    ax.plot(*np.array(medians).T, "rs", label="median per 10 deg (bins with 20+ samples)")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set(xlabel="true tilt of body z from vertical (deg)", ylabel="|a| (g)", ylim=(0.9, 1.1),
           title=f"{rec.id}: |a| in quasi-static samples (nominal 330 mV/g scale)")
    ax.legend(fontsize=8)
    plt.show()
    for lo, hi in ((0, 20), (70, 110)):
        sel = still & (tilt_deg >= lo) & (tilt_deg < hi)
        if sel.any():
            print(f"tilt {lo:3d}-{hi:3d} deg: |a| = {norm_g[sel].mean():.3f} g over {sel.sum()} samples")

# %% [markdown]
# Lying on its side (tilt near 90 degrees), the board reads about 1.03 g on ece276a/1: the x and y
# channels give more counts per g than the nominal 102.3. We can measure the sensitivity directly
# with a straight-line fit per axis, using VICON's gravity direction as the input:
#
# $$ \text{raw}_i = b_i + k_i \cdot \text{sign}_i \, (R^\top e_z)_i , $$
#
# with $k_i$ in counts per g (least squares over the quasi-static samples).

# %%
if rec.truth is not None:
    raw_still = raw.counts[has_truth][still]
    for i, name in enumerate("xyz"):
        design = np.column_stack([np.ones(still.sum()), board.acc_sign[i] * up_body[still, i]])
        (b_i, k_i), *_ = np.linalg.lstsq(design, raw_still[:, i], rcond=None)
        spread = np.ptp(up_body[still, i])
        print(f"a_{name}: {k_i:6.1f} counts/g (nominal {1 / acc_g_per_count:.1f}), zero level {b_i:6.1f} counts"
              f"  [gravity component spans {spread:.2f} g{'; too little to fit' if spread < 1 else ''}]")

# %% [markdown]
# On ece276a/1 (the one recording here that visits every orientation) the three axes give
# 103-105 counts per g, up to 3 % more than the datasheet value; the data README quotes "about 104
# counts per g". The toolkit keeps the nominal value: the filters use the accelerometer for the
# *direction* of gravity, which a common scale error does not change, and they distrust samples
# whose norm is off 1 g (external accelerations) anyway. The gyro is a different story.
#
# ## 1.5 Is the gyro scale right? Against VICON
#
# Differentiating consecutive VICON orientations gives the true body rate,
# $\omega_k = \log(q_k^{-1} q_{k+1}) / \Delta t_k$ (`fusion.checks.vicon_body_rate`). Plot it against
# the gyro (nominal scale), axis by axis: the slope is the sensitivity error.
# `fusion.gyro_fit.fit_data` pairs the two on the IMU clock (after measuring VICON's clock offset).

# %%
if rec.truth is not None:
    pairs = gyro_fit.fit_data(rec)
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4))
    for i, ax in enumerate(axes):
        g_i, v_i = np.rad2deg(pairs.gyro_rad_s[:, i]), np.rad2deg(pairs.vicon_rad_s[:, i])
        slope, icpt = np.polyfit(g_i, v_i, 1)
        ax.plot(g_i, v_i, ".", ms=1.5, alpha=0.3)
        lim = np.array([g_i.min(), g_i.max()])
        ax.plot(lim, lim, "k--", lw=0.8, label="slope 1 (datasheet)")
        ax.plot(lim, slope * lim + icpt, "r", lw=1, label=f"fit: slope {slope:.3f}")
        ax.set(xlabel=f"gyro w_{'xyz'[i]} (deg/s)", ylabel="VICON rate (deg/s)")
        ax.legend(fontsize=8)
    fig.suptitle(f"{rec.id}: gyro (nominal 3.33 mV/(deg/s)) against VICON; clock offset {pairs.clock_offset_s * 1e3:.1f} ms")
    plt.tight_layout()
    plt.show()

# %% [markdown]
# Pooled over all the course recordings, this is what `fusion calibrate` computes
# (`fusion.evaluation.runs.run_calibrate` is the command as a function). Its first line:

# %%
ids = course_recordings()
calibration_run = run_calibrate(",".join(ids))
print(calibration_run.text.splitlines()[0])
print("true / nominal sensitivity:", np.round(calibration_run.fit.sensitivity_ratio, 3))

# %% [markdown]
# The x gyro is about 9 % more sensitive than its datasheet value, y about 4-6 % more and z about
# 3-4 % less: a consistent property of the board (the data README quotes +9, +4, -4 %), not noise.
# More sensitive means more counts per deg/s, so the nominal conversion *overestimates* the rate
# (the x and y slopes above are below 1): a true 90 degree turn about x, integrated with the nominal scale,
# comes out as $90 \times 1.09 \approx 98$ degrees. The filters of notebooks 3-5 either estimate these
# scale factors (`ekf`, `ukf-bias`, `gn`) or absorb them as process noise (`ukf`); `fusion
# calibrate --out calib.json` writes them to a file that `--calibration` applies to every command.
#
# ## 1.6 What else is wrong with real data: `fusion inspect`
#
# `fusion inspect` (here `run_inspect`) runs the sensor checks of `fusion.checks` on a recording:

# %%
inspection = run_inspect(rec.id)
print(inspection.text)

# %% [markdown]
# Read it line by line:
#
# * **IMU rate / jitter**: about 100 Hz, but the steps are not constant; every estimator uses the
#   real `dt = np.diff(t)`.
# * **rests**: the stationary periods, with $|a|$ in each (the calibration used the first).
# * **gyro bias drift**: the bias at the last rest minus the first: how much it wandered.
# * **gyro freezes**: all three gyro channels stuck at one level while the accelerometer shows
#   motion: a sensor fault. The loader marks those samples invalid (`imu.gyr_valid`), and no
#   estimator integrates them.
# * **VICON**: its rate and the clock offset between IMU and VICON, measured by
#   cross-correlating the angular speeds of both.
#
# The freeze is easy to see once you know where to look. Note the level the channels stick at,
# about 382 counts: *not* the zero-rate level of the rest (the biases above, about 370-375
# counts). Integrated as if it were a measurement, the frozen reading would be a steady turn
# of several deg/s per axis while the board actually moves quite differently (VICON, right).

# %%
freezes = inspection.checks[0].freezes
if freezes and rec.truth is not None:
    f = freezes[0].interval
    t_mid, omega_vicon = vicon_body_rate(rec.truth)
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.2))
    window = (f.start_s - 2, f.stop_s + 2)
    for k in range(3, 6):
        axes[0].plot(t, raw.counts[:, k], lw=0.8, label=names[k])
    axes[0].set(xlim=window, xlabel="time (s)", ylabel="raw gyro counts", title="gyro channels")
    axes[1].plot(t, np.rad2deg(np.linalg.norm(imu.gyr_rad_s, axis=1)), lw=0.8, label="|gyro|")
    axes[1].plot(t_mid - imu.t[0], np.rad2deg(np.linalg.norm(omega_vicon, axis=1)), lw=0.8, label="|VICON rate|")
    axes[1].set(xlim=window, ylim=(0, None), xlabel="time (s)", ylabel="angular speed (deg/s)", title="angular speed")
    for ax in axes:
        ax.axvspan(f.start_s, f.stop_s, color="tab:red", alpha=0.2, label="freeze (gyr_valid False)")
        ax.legend(fontsize=8)
    plt.tight_layout()
    plt.show()
    print(f"samples marked invalid: {np.count_nonzero(~imu.gyr_valid)}")
else:
    print("no gyro freeze in this recording")

# %% [markdown]
# And the time stamps: a histogram of the real steps.

# %%
fig, ax = plt.subplots(figsize=(7, 3))
ax.hist(imu.dt * 1e3, bins=80)
ax.set(xlabel="time step dt (ms)", ylabel="count", yscale="log",
       title=f"{rec.id}: IMU time steps (median {np.median(imu.dt) * 1e3:.2f} ms)")
plt.show()

# %% [markdown]
# ## Summary
#
# * `value = sign * (raw - bias) * scale`; the scales come from datasheets, the biases from the
#   stationary start (the accelerometer's z bias keeps 1 g).
# * $|a| = 1\,g$ at the start rest holds by construction; a tilted quasi-static pose, checked with
#   VICON, shows the accelerometer reads 1-3 % high on this board: harmless for a direction.
# * The gyro scales are off by +9 / +4-6 / -3-4 %: harmful, since the error integrates.
# * Real recordings have gyro freezes, clock offsets between sensors and jittery time stamps;
#   `fusion inspect` finds them, and the loaders mark the bad samples instead of hiding them.
#
# **Try it:** run `fusion inspect --dataset ece276a/5` (or `run_inspect("ece276a/5")`): which
# samples exceed the gyro range? Fit the accelerometer scale on another recording: why does the
# fit fail there?
