# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 2. Dead reckoning, and why it drifts
#
# Integrate the gyro and you have an orientation: no accelerometer, no filter. This is the
# prediction step of every filter in the following notebooks, so it pays to get it exactly right
# and to know what its errors look like. In this notebook:
#
# 1. quaternion kinematics and the exponential map (Sola 2017);
# 2. dead reckoning written out as a loop, checked against the library's `dr` estimator;
# 3. how large the *integration* error is (tiny) compared with the *sensor* errors (not tiny);
# 4. the error growing against VICON, and what each sensor error contributes.
#
# Reference: J. Sola, "Quaternion kinematics for the error-state Kalman filter", 2017,
# arXiv:1711.02508: Sec. 1.2.2 (the quaternion product), Sec. 1.3.4 (exponential of pure
# quaternions), Sec. 1.3.6 (logarithm of unit quaternions), Secs. 2.3.1 and 2.3.4 (the exponential
# and logarithmic maps of rotations). The numbers are sections of the paper's version dated
# 12 October 2017, not equations.

# %%
# %matplotlib inline
import matplotlib.pyplot as plt
import numpy as np
from scipy.spatial.transform import Rotation

from fusion import datasets, estimators, gyro_fit
from fusion import quaternion as quat
from fusion.datasets import initial_orientation
from fusion.evaluation.scoring.metrics import score
from tutorial_data import course_recordings, load_recording

plt.rcParams.update({"figure.figsize": (10, 3.4), "axes.grid": True, "figure.dpi": 90})
rec = load_recording("ece276a/1")
imu = rec.imu
q0 = initial_orientation(rec)  # the VICON orientation at the first IMU sample
print("q0 =", np.round(q0, 4))

# %% [markdown]
# ## 2.1 Quaternion kinematics
#
# A unit quaternion $q = [w, x, y, z]$ stands for the rotation `R_world_body`. If the body turns
# with angular rate $\omega$ measured *in the body frame* (what a gyro measures), the quaternion
# changes as
#
# $$ \dot q = \tfrac12\, q \otimes \begin{bmatrix} 0 \\ \omega \end{bmatrix} , $$
#
# with $\otimes$ the Hamilton product. Body-frame rates multiply on the *right*; a rate given
# in the world frame would multiply on the left. If $\omega$ is constant over a step $\Delta t$,
# the equation has an exact solution: the rotation by the angle $|\omega| \Delta t$ about
# $\omega / |\omega|$,
#
# $$ q_{k+1} = q_k \otimes \operatorname{Exp}(\omega_k \Delta t_k), \qquad
#    \operatorname{Exp}(\theta) = \begin{bmatrix} \cos(|\theta|/2) \\ \sin(|\theta|/2)\, \theta / |\theta| \end{bmatrix}, $$
#
# the exponential map from a rotation vector $\theta$ (axis times angle, rad) to a unit
# quaternion; its inverse, the logarithm $\operatorname{Log}(q)$, returns the rotation vector.
# In `fusion.quaternion` these are `from_rotvec` and `to_rotvec`, batched over leading axes.
# First the formula, by hand, against the library and against SciPy:

# %%
theta = np.array([0.3, -1.2, 0.5])  # rad
angle = np.linalg.norm(theta)
by_hand = np.r_[np.cos(angle / 2), np.sin(angle / 2) * theta / angle]
print("by hand           :", by_hand)
print("quat.from_rotvec  :", quat.from_rotvec(theta))
print("SciPy             :", Rotation.from_rotvec(theta).as_quat(scalar_first=True))
print("Log(Exp(theta))   :", quat.to_rotvec(quat.from_rotvec(theta)), " (theta =", theta, ")")
print("q and -q, one rotation:", quat.to_rotvec(-quat.from_rotvec(theta)))

# %% [markdown]
# A test that could fail: turning at a constant 90 deg/s about z for one second, in 100 steps of
# 10 ms, must give exactly 90 degrees about z.

# %%
step = quat.from_rotvec(np.array([0.0, 0.0, np.pi / 2 * 0.01]))
q = quat.IDENTITY
for _ in range(100):
    q = quat.multiply(q, step)
print("rotation vector (deg):", np.degrees(quat.to_rotvec(q)))

# %% [markdown]
# ## 2.2 Dead reckoning on the recording
#
# Every step uses the real time step `dt = t[k+1] - t[k]` (the time stamps jitter, notebook 1)
# and the gyro reading *for that interval*. Which sample that is depends on the board: the course
# boards pair gyro sample $k$ with the interval $[t_k, t_{k+1})$, most IMUs with
# $(t_{k-1}, t_k]$. The recording knows (`imu.gyr_timing`) and `imu.interval_rates()` returns the
# right reading for each interval, with the validity flag (False inside a gyro freeze, which is
# then not integrated). Written as a loop:

# %%
rate, valid = imu.interval_rates()  # (N-1, 3) rad/s, (N-1,) bool
print("gyr_timing:", imu.gyr_timing, "| invalid intervals:", np.count_nonzero(~valid))
increments = rate * imu.dt[:, None]  # (N-1, 3) rotation vectors, rad, body frame
increments[~valid] = 0.0
q_loop = np.empty((len(imu), 4))
q_loop[0] = q0
for k in range(len(imu) - 1):
    q_loop[k + 1] = quat.normalize(quat.multiply(q_loop[k], quat.from_rotvec(increments[k])))

dr = estimators.build("dr").estimate(imu, q0)  # the library: vectorised, a parallel scan of products
gap = np.degrees(np.linalg.norm(quat.relative_rotvec(q_loop, dr.quat_wxyz), axis=1))
print(f"loop vs estimators 'dr': largest difference {gap.max():.2e} deg over {len(imu)} samples")

# %% [markdown]
# The library does the same in a few vectorised calls (`estimators/dr.py`: one `from_rotvec` for
# all increments, then `cumulative_product`, a parallel scan, since the product is associative);
# the two agree to rounding.
#
# ## 2.3 Is the integration scheme the problem?
#
# A common alternative is the first-order (Euler) step $q_{k+1} = q_k + \tfrac12 q_k \otimes [0, \omega_k] \Delta t_k$,
# then renormalise. Its error per step is third order in the step angle, so at 100 Hz it is
# negligible against the sensor errors:

# %%
q_euler = np.empty((len(imu), 4))
q_euler[0] = q0
for k in range(len(imu) - 1):
    pure = np.r_[0.0, increments[k]]
    q_euler[k + 1] = quat.normalize(q_euler[k] + 0.5 * quat.multiply(q_euler[k], pure))
diff = np.degrees(np.linalg.norm(quat.relative_rotvec(q_euler, dr.quat_wxyz), axis=1))
step_deg = np.degrees(np.linalg.norm(increments, axis=1))
print(f"largest step angle {step_deg.max():.2f} deg; Euler vs exponential map after "
      f"{imu.t[-1] - imu.t[0]:.0f} s: {diff[-1]:.4f} deg (largest {diff.max():.4f} deg)")

# %% [markdown]
# Thousandths of a degree. Whatever drift we see next comes from the sensor, not the arithmetic.
#
# ## 2.4 Error growth against VICON
#
# `fusion.evaluation.scoring.metrics.score` slerps VICON onto the estimate's time stamps and returns,
# per sample, three angles: the **total** error (geodesic angle of $R_\text{true}^{-1} R_\text{est}$),
# the **inclination** error (angle between the true and the estimated gravity direction in the
# body frame: what an accelerometer could correct) and the **heading** error (the turn about
# world z: what it cannot).

# %%
def plot_errors(ax, s, label, kind="total", **style):
    ax.plot(s.t - imu.t[0], np.degrees(s.errors_rad[kind]), label=label, **style)


s_dr = score(rec.truth, dr)
fig, ax = plt.subplots()
for kind in ("total", "inclination", "heading"):
    plot_errors(ax, s_dr, f"{kind} (RMSE {s_dr.rmse_deg[kind]:.2f} deg)", kind, lw=1)
bad = ~imu.gyr_valid
if bad.any():
    ax.axvspan(imu.t[bad][0] - imu.t[0], imu.t[bad][-1] - imu.t[0], color="tab:red", alpha=0.2,
               label="gyro freeze (not integrated)")
ax.set(xlabel="time (s)", ylabel="error (deg)", title=f"{rec.id}: dead reckoning against VICON")
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# ### What causes it: three sensor errors
#
# **Noise.** At rest the gyro's standard deviation $\sigma$ per sample is about 0.6 deg/s (a
# count of the ADC is 0.97 deg/s). White rate noise integrates into an angle random walk: after
# $t$ seconds the angle's standard deviation is $\sigma \sqrt{\Delta t} \sqrt{t}$.

# %%
rest = slice(*rec.calibration.rest_start)
sigma = imu.gyr_rad_s[rest].std(axis=0)  # rad/s per sample
density = sigma * np.sqrt(np.median(imu.dt))  # rad / sqrt(s)
duration = imu.t[-1] - imu.t[0]
print("rest std (deg/s):", np.round(np.degrees(sigma), 3))
print("noise density (deg/sqrt(s)):", np.round(np.degrees(density), 4))
print(f"angle random walk after {duration:.0f} s: {np.degrees(density * np.sqrt(duration)).round(2)} deg (1 sigma, per axis)")

# %% [markdown]
# Half a degree: noise does not explain the error above. **Scale factors.** Notebook 1 found the
# x and y gyros 9 % and 4-6 % more sensitive than the datasheet; with the nominal scale every turn
# about x is integrated 9 % too large. Re-calibrate the recording with scale factors fitted on the *other*
# recordings (so that this recording's VICON is not used to correct itself) and integrate again.
# **Freezes.** With the freeze *integrated* (the loader's dropout detection switched off), the
# frozen reading acts as a steady false rate.

# %%
others = [rid for rid in course_recordings() if rid != rec.id]
variants = {"as loaded (nominal scales, freeze skipped)": rec}
if rec.calibration is not None and others and rec.truth is not None:
    fit = gyro_fit.fit_recordings(datasets.load(rid) for rid in others)
    print("scale factors fitted on", len(others), "other recordings:", np.round(fit.gyro_scale_factor, 4))
    variants["calibrated scales (fitted on the others)"] = gyro_fit.with_gyro_scale(rec, fit.gyro_scale_factor)
if rec.raw is not None:
    variants["freeze integrated (dropouts off)"] = datasets.load(rec.id, dropouts=False)

fig, axes = plt.subplots(1, 2, sharey=True)
for (label, variant), style in zip(variants.items(), ("-", "--", ":")):
    s = score(rec.truth, estimators.build("dr").estimate(variant.imu, q0))
    for ax, kind in zip(axes, ("inclination", "heading")):
        plot_errors(ax, s, f"{label}: {s.rmse_deg[kind]:.2f}", kind, ls=style, lw=1.2)
t_axis = np.linspace(0, duration, 200)
for ax, kind in zip(axes, ("inclination", "heading")):
    ax.plot(t_axis, 3 * np.degrees(density.max() * np.sqrt(t_axis)), "k", lw=0.8, label="3 sigma angle random walk")
    ax.set(xlabel="time (s)", ylabel=f"{kind} error (deg)", title=f"{kind} error, RMSE in the legend")
    ax.legend(fontsize=7)
plt.tight_layout()
plt.show()

# %% [markdown]
# Read the curves of ece276a/1 from left to right. Until the freeze at 8.6 s every variant stays
# inside the random-walk envelope. Skipping the frozen samples loses the rotation that happened
# during them: a 3-6 degree step at once, which nothing later undoes. Integrating them instead
# (dotted) is far worse, a 12-15 degree step: the frozen level is not the zero-rate level. After
# the freeze, the nominal scales add error whenever the board turns about x or y (the bump at
# 35-40 s); the calibrated scales remove most of it (inclination RMSE 4.4 -> 3.0 deg). What is
# left is mainly the motion lost in the freeze. None of this can be removed by integrating
# better. It needs a second sensor that knows where "down" is: the accelerometer, fused by the
# filters of the next notebooks.
#
# ## Summary
#
# * $q_{k+1} = q_k \otimes \operatorname{Exp}(\omega_k \Delta t_k)$, body rates on the right, the real $\Delta t_k$,
#   and the reading that belongs to each interval (`interval_rates`).
# * The integration scheme is not what drifts: Euler and the exponential map differ by
#   thousandths of a degree over a minute at 100 Hz.
# * Drift comes from the sensor: noise (an angle random walk, small here), scale-factor errors
#   (proportional to how much you turn), bias (grows linearly with time) and faults such as freezes.
#
# **Try it:** add a constant 0.5 deg/s bias to the gyro (`imu.replace(gyr_rad_s=...)`) and check
# that the error grows roughly like $0.5\,t$ degrees.
