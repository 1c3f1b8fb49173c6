# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 3. The quaternion UKF, one step at a time
#
# E. Kraft, "A quaternion-based unscented Kalman filter for orientation tracking", Proc. 6th
# Int. Conf. Information Fusion, 2003: the filter most orientation courses teach. The toolkit's
# `ukf` estimator implements it on top of FilterPy's `UnscentedKalmanFilter`
# (`fusion.estimators.filters.quaternion_ukf.QuaternionUKF`). In this notebook we take one real sample of a
# recording and run Kraft's steps by hand, printing every number, with the library's own
# pieces (`QuaternionSigmaPoints`, `quaternion_mean`, `fusion.quaternion`), and check that the
# result is exactly what the filter computes. Then the whole recording, with the filter's
# $\pm 3\sigma$ bounds against VICON.
#
# **Why a quaternion UKF is not a textbook UKF.** The state is a unit quaternion: four numbers,
# three degrees of freedom. Its mean cannot be an arithmetic average, its error cannot be a
# difference, and its covariance cannot be 4x4 (it would be singular). Kraft's answer, which
# the library follows:
#
# * the covariance $P$ of the orientation (3x3) is the covariance of a **rotation-vector error** $e$,
#   in the library a body-frame one: $q_\text{true} = q \otimes \operatorname{Exp}(e)$, with $\operatorname{Exp}$ the
#   exponential map of notebook 2;
# * sigma points are built in that 3-D error space, then mapped onto quaternions with $\operatorname{Exp}$;
# * the mean of the propagated quaternions is found iteratively (a gradient descent on the sphere);
# * the error of each point about the mean, $\operatorname{Log}(\bar q^{-1} q_i)$, is what goes into the covariances.
#
# The models: the gyro is the control input (process model), the accelerometer measures gravity
# in the body frame (measurement model, in g; linear accelerations count as noise):
#
# $$ q_{k+1} = q_k \otimes \operatorname{Exp}(\omega_k \Delta t_k) \otimes \operatorname{Exp}(w_k), \quad w_k \sim N(0, Q_k);
#    \qquad a_{k+1} = h(q_{k+1}) + v_{k+1} = R(q_{k+1})^\top e_z + v_{k+1}, \quad v \sim N(0, R_{k+1}). $$
#
# The noise is specified as continuous-time densities, so that one setting means the same at
# any sampling rate: $Q_k = Q\,\Delta t_k\,I$ (rad$^2$/s $\cdot$ s) and $R_k = R / \Delta t_k\, I$ (g$^2$ s / s).

# %%
# %matplotlib inline
import matplotlib.pyplot as plt
import numpy as np

from fusion import estimators
from fusion import quaternion as quat
from fusion.datasets import initial_orientation
from fusion.estimators.filters.quaternion_ukf import QuaternionSigmaPoints, QuaternionUKF, quaternion_mean, unscented_transform_state
from fusion.evaluation.scoring import consistency
from tutorial_data import load_recording

np.set_printoptions(precision=5, suppress=False, linewidth=110)
plt.rcParams.update({"figure.figsize": (10, 3.4), "axes.grid": True, "figure.dpi": 90})
rec = load_recording("ece276a/1")
imu = rec.imu
q0 = initial_orientation(rec)

# %% [markdown]
# ## 3.1 Kraft's steps, the library's steps
#
# The module docstring of `estimators/filters/ukf.py` numbers the steps of one filter cycle 1-9; the code
# (`estimators/filters/quaternion_ukf.py`) refers to those numbers. The table says what each step is in
# Kraft's filter, and where the library differs from it.
#
# | `ukf.py` step | operation | Kraft 2003 |
# |---|---|---|
# | 1 | control input $q_\Delta = \operatorname{Exp}(\omega \Delta t)$ | **differs**: Kraft's state also holds the angular velocity, and the gyro is one of his measurements; here, as in the reduced variant that course implementations use, the gyro drives the process model and the state is $q$ alone. The turn over one step, $q \otimes \operatorname{Exp}(\omega \Delta t)$, is the same |
# | 2 | sigma points $W_i$ = $\pm$ columns of $\sqrt{c\,(P + Q)}$ | as in Kraft's filter, $Q$ is added to $P$ *before* the points are drawn. The scheme `kraft`: $2n$ points with equal weights, as the course implementations of the paper use (`sfwa/ukf` uses scaled points with a centre point instead), and $c = n$ where those implementations scale by $2n$: with weights $1/(2n)$, $c = n$ is the one factor with which the points reproduce $P + Q$ (checked below), and the paper's own factor was not checked |
# | 3 | $X_i = q \otimes \operatorname{Exp}(W_i)$ | the error vectors become quaternions through the exponential map, composed with the mean; here on the right (a body-frame error, as $P$ is defined), where implementations differ |
# | 4 | $Y_i = X_i \otimes q_\Delta$ | the process model, applied to every point |
# | 5 | iterative quaternion mean $\bar q$; errors $W'_i = \operatorname{Log}(\bar q^{-1} Y_i)$; $P^- = \sum_i w_i W'_i W'^\top_i$ | the mean is Kraft's gradient descent, his **Sec. 3.4**; $P^-$ from the errors about the mean, with no second $Q$ (it entered in step 2) |
# | 6 | $Z_i = h(Y_i) = R(Y_i)^\top e_z$ | the accelerometer part of Kraft's measurement model (which also measures the angular velocity of his state, step 1), evaluated on the propagated points $Y_i$, not on points re-drawn from $P^-$ |
# | 7 | $z^- = \sum_i w_i Z_i$ | the predicted measurement |
# | 8 | $P_{zz} = \sum_i w_i (Z_i - z^-)(Z_i - z^-)^\top$; $P_{\nu\nu} = P_{zz} + R$; $P_{xz} = \sum_i w_i W'_i (Z_i - z^-)^\top$ | the unscented transform's covariances, with the errors $W'_i$ of step 5 in place of state differences |
# | 9 | $K = P_{xz} P_{\nu\nu}^{-1}$; $q \leftarrow \bar q \otimes \operatorname{Exp}(K \nu)$, $\nu = z - z^-$; $P = P^- - K P_{\nu\nu} K^\top$ | the Kalman gain and covariance update; the correction $K\nu$ is a rotation vector, applied through the exponential map (on the right here, as in step 3) |
#
# **Where these statements come from.** A copy of the paper could not be consulted while this
# notebook was written, so the table gives no equation numbers. Sec. 3.4 is cited for the mean
# because two independent implementations cite it so: `sfwa/ukf` (Thiemar Pty Ltd, 2016,
# `include/UKF/StateVector.h`) and Google's Cartographer
# (`cartographer/kalman_filter/unscented_kalman_filter.h`). `sfwa/ukf` also gives equation numbers
# for steps 5, 8 and 9; they come from one source, which gives one number to two different
# quantities, so they are not repeated here. "As in Kraft's filter" marks what every public
# implementation of the paper read for this notebook does alike: `sfwa/ukf` (`include/UKF/Core.h`)
# and course projects that follow the paper (for example
# `github.com/yrlu/orientation_tracking-unscented_kalman_filter`, whose report implements both
# Kraft's 7-element state and the 4-element variant with the gyro as control input).
#
# ## 3.2 One real sample
#
# We run the filter over the recording up to a sample in the middle of a fast turn, and take
# the state there: the quaternion $q_k$ and the covariance $P_k$ it recorded
# (`trajectory.diagnostics["cov"]`). For this step-by-step part we use Kraft's plain filter:
# `ukf:tauc=0,Qs=0` switches off the two additions the default `ukf` makes (an accelerometer
# variance that grows with the measured external acceleration, and process noise that grows with
# the rate to cover the gyro scale errors of notebook 1), so that $Q_k$ and $R_k$ are the
# constants above.

# %%
SPEC = "ukf:tauc=0,Qs=0"
filt = estimators.build(SPEC)
p = filt.params
print(SPEC, "->", f"Q = {p.process_noise_rad2_s} rad^2/s, R = {p.acc_noise_g2_s} g^2 s, P0 = {p.init_var_rad2} rad^2,",
      f"sigma points: {p.sigma}")

gyr, valid = imu.interval_rates()  # the gyro reading of each interval [t_k, t_k+1]
t_rel = imu.t - imu.t[0]
fast = (t_rel[:-1] > 11.0) & (np.linalg.norm(gyr, axis=1) > 1.0) & valid
k = int(np.argmax(fast)) if fast.any() else len(imu) // 2
m = k + 2  # samples 0 .. k+1: the filter's state at k, and its own result at k+1 to compare with
head = imu.window(0, m)
run = filt.estimate(head, q0)
q_k, P_k = run.quat_wxyz[k], run.diagnostics["cov"][k]
dt, w, a = imu.dt[k], gyr[k], imu.acc_g[k + 1]
print(f"sample k = {k} (t = {t_rel[k]:.2f} s), dt = {dt * 1e3:.2f} ms")
print("q_k =", q_k)
print("P_k (rad^2) =\n", P_k)
print("1-sigma per axis (deg):", np.degrees(np.sqrt(np.diag(P_k))))
print("gyro w (rad/s) =", w, f" |w| = {np.degrees(np.linalg.norm(w)):.1f} deg/s")
print("accelerometer a (g) =", a, f" |a| = {np.linalg.norm(a):.3f} g")

# %% [markdown]
# The heading (about body z, here nearly vertical) is far less certain than the tilt: the
# accelerometer sees the tilt and never the heading, so the heading variance only grows. Keep an
# eye on the third row and column.
#
# ### Step 1: the control input

# %%
Q = p.process_noise_rad2_s * dt * np.eye(3)  # Q_k = Q dt, rad^2
R = p.acc_noise_g2_s / dt * np.eye(3)  # R_k = R / dt, g^2
q_delta = quat.from_rotvec(w * dt)
print("q_delta = Exp(w dt) =", q_delta, f" (a turn of {np.degrees(np.linalg.norm(w) * dt):.3f} deg)")
print("Q_k diagonal (rad^2):", np.diag(Q), " R_k diagonal (g^2):", np.diag(R))

# %% [markdown]
# ### Step 2: sigma points from $P + Q$
#
# $n = 3$ error dimensions give $2n = 6$ points $W_i = \pm$ the columns of $\sqrt{c\,(P_k + Q_k)}$
# (a Cholesky factor) with $c = n$ and equal weights $1/(2n)$; the library also carries a centre
# point of weight 0, which only starts the mean of step 5. The check that matters: the points
# reproduce the covariance they were drawn from, $\sum_i w_i W_i W_i^\top = P_k + Q_k$. (With weights
# $1/(2n)$ that holds for $c = n$ only, which is why the library uses it: a scale of $2n$, as some
# implementations of the paper use, would give $2(P_k + Q_k)$.)

# %%
points = QuaternionSigmaPoints(3, p.sigma)
W = points.offsets(P_k + Q)  # (2n + 1, 3) rotation vectors, rad; row 0 is the centre
print("weights Wm =", points.Wm)
print("W (rad), one point per row =\n", W)
L = np.linalg.cholesky(P_k + Q)
print("by hand, +columns of sqrt(n (P+Q)) equal rows 1-3:", np.allclose(np.sqrt(3) * L.T, W[1:4]))
print("sum_i w_i W_i W_i^T == P + Q:", np.allclose(W.T @ (points.Wc[:, None] * W), P_k + Q))

# %% [markdown]
# ### Step 3: onto the quaternions, $X_i = q_k \otimes \operatorname{Exp}(W_i)$

# %%
X = points.sigma_points(q_k, P_k + Q)  # (2n + 1, 4)
print("X =\n", X)
print("by hand equals the library:", np.allclose(X, quat.multiply(q_k, quat.from_rotvec(W))))

# %% [markdown]
# ### Step 4: propagate, $Y_i = X_i \otimes q_\Delta$

# %%
Y = quat.multiply(X, q_delta)
print("Y =\n", Y)

# %% [markdown]
# ### Step 5: the mean of quaternions, iteratively
#
# The mean $\bar q$ is the rotation about which the errors $e_i = \operatorname{Log}(\bar q^{-1} Y_i)$ average to
# zero. Start from a guess $\bar q_0$ and repeat
#
# $$ e_i = \operatorname{Log}(\bar q_t^{-1} Y_i), \qquad \bar e = \sum_i w_i e_i, \qquad \bar q_{t+1} = \bar q_t \otimes \operatorname{Exp}(\bar e) $$
#
# until $|\bar e|$ is below a tolerance. `quaternion_mean(quats, weights, start, tol, max_iter)` is
# that loop; calling it with `max_iter = 1, 2, 3, ...` (and `tol = 0`) shows every iterate. The
# filter starts from the centre point $Y_0$:

# %%
def mean_error(q_mean):
    """|sum_i w_i Log(q_mean^-1 Y_i)| in rad: zero at the mean."""
    return np.linalg.norm(points.Wm @ quat.relative_rotvec(q_mean, Y))


print(f"start Y_0: |e| = {mean_error(Y[0]):.3e} rad")
for j in range(1, 4):
    q_j, _, _ = quaternion_mean(Y, points.Wm, Y[0], tol=0.0, max_iter=j)
    print(f"iteration {j}: |e| = {mean_error(q_j):.3e} rad")

# %% [markdown]
# Converged at the first iteration, to rounding: the points are symmetric about the centre,
# which is already almost their mean. To watch the iteration work, start it 34 degrees away:

# %%
bad_start = quat.multiply(Y[0], quat.from_rotvec(np.array([0.5, -0.3, 0.2])))
errors = [mean_error(bad_start)]
for j in range(1, 9):
    q_j, _, _ = quaternion_mean(Y, points.Wm, bad_start, tol=0.0, max_iter=j)
    errors.append(mean_error(q_j))
for j, err in enumerate(errors):
    print(f"iteration {j}: |e| = {err:.3e} rad = {np.degrees(err):.2e} deg")
fig, ax = plt.subplots(figsize=(6, 3))
ax.semilogy(range(len(errors)), np.maximum(errors, 1e-18), "o-")
ax.set(xlabel="iteration", ylabel="|mean error| (rad)", title="iterative quaternion mean from a 34 deg start")
plt.show()

# %% [markdown]
# Each iteration shrinks the error by a factor of a few hundred (linear convergence, fast because
# the points are close together) until it stops at rounding, about $10^{-17}$ rad. Now the
# predicted state and covariance, from the errors about the mean:

# %%
q_pred, e_i, iterations = quaternion_mean(Y, points.Wm, Y[0], p.mean_tol_rad, p.mean_max_iter)
P_pred = e_i.T @ (points.Wc[:, None] * e_i)
print("q^- =", q_pred, f"({iterations} iteration(s))")
print("P^- (rad^2) =\n", P_pred)
print("P^- - (P_k + Q_k), the change by the propagation (a rotation of the error frame):\n", P_pred - (P_k + Q))

# %% [markdown]
# ### Steps 6 and 7: predicted gravity
#
# Each propagated point predicts what the accelerometer should read, gravity in its body frame
# $Z_i = R(Y_i)^\top e_z$; their weighted mean is the prediction $z^-$.

# %%
Z = quat.gravity_in_body(Y)  # (2n + 1, 3), g
z_pred = points.Wm @ Z
nu = a - z_pred
print("Z (g) =\n", Z)
print("z^- =", z_pred, f" |z^-| = {np.linalg.norm(z_pred):.6f} g (slightly below 1: the mean of points on a sphere)")
print("measured a =", a, "\ninnovation nu = a - z^- =", nu)

# %%
fig, ax = plt.subplots(figsize=(5.5, 4.5))
ax.plot(Z[1:, 0], Z[1:, 1], "o", label="sigma points Z_i")
ax.plot(*z_pred[:2], "kx", ms=10, mew=2, label="prediction z-")
ax.plot(*a[:2], "r*", ms=12, label="measurement a")
for i in range(1, len(Z)):
    ax.annotate(f"{i}", Z[i, :2], textcoords="offset points", xytext=(4, 4), fontsize=8)
ax.set(xlabel="x component of gravity in the body frame (g)", ylabel="y component (g)",
       title=f"sample {k}: predicted and measured gravity")
ax.axis("equal")
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# Points 2/5 and 3/6 are tilts of the board: they move the predicted gravity by about 0.02 g.
# Points 1 and 4 are mostly a turn about body z (0.27 rad of their 0.29), nearly the vertical
# here: they hardly move it. The accelerometer cannot see the heading, and the sigma points show
# why. The measurement lies a few hundredths of g off the prediction, partly the hand's linear
# acceleration.
#
# ### Steps 8 and 9: covariances, gain, update

# %%
dZ = Z - z_pred
P_zz = dZ.T @ (points.Wc[:, None] * dZ)
P_vv = P_zz + R
P_xz = e_i.T @ (points.Wc[:, None] * dZ)
K = P_xz @ np.linalg.inv(P_vv)
correction = K @ nu
q_new = quat.normalize(quat.multiply(q_pred, quat.from_rotvec(correction)))
P_new = P_pred - K @ P_vv @ K.T
print("P_zz (g^2) =\n", P_zz, "\nP_vv = P_zz + R_k (g^2) =\n", P_vv)
print("P_xz (rad g) =\n", P_xz)
print("K (rad/g) =\n", K)
print("correction K nu (deg) =", np.degrees(correction))
print("q_k+1 =", q_new)
print("P_k+1 (rad^2) =\n", P_new)

# %% [markdown]
# The gain is small: $R_k$ (the printed diagonal, about 0.003 g$^2$, i.e. 0.06 g standard
# deviation per sample at 100 Hz) is twenty times the spread of the predicted gravity in $P_{zz}$,
# so one sample moves the estimate by a few hundredths of a degree. Over many samples the
# accelerometer pulls the tilt back with the time constant $\sqrt{R/Q}$ (about 0.2 s with these
# densities; `FilterParams` explains it). The heading row of $K$ (the third) is not zero: through
# the correlations in $P$ the accelerometer also turns the estimate about the vertical, which it
# cannot observe (`ukf-bias` and `ekf` remove that part of the gain: `heading_free`).
#
# ### Is that what the library computes?
#
# `QuaternionUKF.predict_kraft` (steps 1-5) and `update_kraft` (steps 6-9) run the same cycle
# vectorised; the estimator's own result at sample $k+1$ is the third opinion.

# %%
kf = QuaternionUKF(points, p.mean_tol_rad, p.mean_max_iter)
kf.x, kf.P = q_k.copy(), P_k.copy()
kf.predict_kraft(dt, w, Q)
print("predict_kraft: q^- and P^- equal ours:", np.allclose(kf.x, q_pred, atol=1e-14), np.allclose(kf.P, P_pred, atol=1e-16))
kf.update_kraft(a, R)
print("update_kraft : max |q difference| = %.1e, max |P difference| = %.1e" % (
    np.abs(kf.x - q_new).max(), np.abs(kf.P - P_new).max()))
print("estimator    : max |q difference| = %.1e, max |P difference| = %.1e" % (
    np.abs(run.quat_wxyz[k + 1] - q_new).max(), np.abs(run.diagnostics["cov"][k + 1] - P_new).max()))

# %% [markdown]
# Same numbers. `QuaternionUKF` is a FilterPy `UnscentedKalmanFilter` (it keeps FilterPy's
# attributes and hooks: `x`, `P`, `K`, `points_fn`, `x_mean_fn`, `residual_x`...), and FilterPy's
# own `predict`/`update` still work on it. They are not Kraft's: FilterPy adds $Q$ *after* the
# transform and re-draws the sigma points from the predicted $(x, P)$ before the update, where Kraft
# keeps the propagated points. How much does that change here?

# %%
fp = QuaternionUKF(points, p.mean_tol_rad, p.mean_max_iter)
fp.x, fp.P, fp.Q = q_k.copy(), P_k.copy(), Q
fp.predict(dt=dt, UT=unscented_transform_state, gyr_rad_s=w)
print("FilterPy predict vs Kraft: max |P^- difference| = %.1e" % np.abs(fp.P - P_pred).max())
fp.update(a, R=R)
angle = np.linalg.norm(quat.relative_rotvec(fp.x, q_new))
print("FilterPy update vs Kraft: %.1e deg apart, max |P difference| %.1e" % (np.degrees(angle), np.abs(fp.P - P_new).max()))

# %% [markdown]
# A few millionths of a degree: over one 10 ms step the propagation is almost a pure rotation of
# the error cloud, so both orders give the same distribution. The differences grow with the
# nonlinearity per step: large $P$, fast turns, slow sampling.
#
# ## 3.3 The whole recording, with its $\pm 3\sigma$ bounds
#
# The filter reports its own uncertainty: `diagnostics["cov"]` holds $P$ after every sample. If the
# filter is *consistent*, the true error $e = \operatorname{Log}(q_\text{est}^{-1} q_\text{true})$ (body frame, the
# filter's own error definition) lies inside $\pm 3\sigma$ nearly always, and the normalised
# estimation error squared $\text{NEES} = e^\top P^{-1} e$ averages 3 (a $\chi^2$ with 3 degrees of
# freedom). Kraft's plain filter of section 3.2 and the default `ukf`, against VICON:

# %%
rot_true, has_truth = rec.truth.interpolate(imu.t)
q_true = rot_true.as_quat(scalar_first=True)


def error_and_sigma(spec):
    trajectory = estimators.build(spec).estimate(imu, q0)
    e = quat.relative_rotvec(trajectory.quat_wxyz[has_truth], q_true)  # (M, 3) rad, body frame
    P = trajectory.diagnostics["cov"][has_truth][:, :3, :3]  # the attitude block
    sigma = np.sqrt(np.diagonal(P, axis1=1, axis2=2))
    nees = np.einsum("ti,tij,tj->t", e, np.linalg.inv(P), e)
    # The same three lines are what the comparison reports use (fusion.evaluation.scoring.consistency):
    belief = consistency.from_trajectory(trajectory, consistency.truth_on(rec.truth, imu.t))
    assert np.allclose(nees, belief.nees[has_truth], rtol=1e-6)
    return e, sigma, nees


rows = {f"{SPEC} (Kraft's plain filter)": SPEC, "ukf (the default)": "ukf"}
results = {name: error_and_sigma(spec) for name, spec in rows.items()}
t_truth = t_rel[has_truth]
fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharex=True)
for row, (name, (e, sigma, nees)) in zip(axes, results.items()):
    for i, ax in enumerate(row):
        bound = 3 * np.degrees(sigma[:, i])
        ax.fill_between(t_truth, -bound, bound, color="tab:blue", alpha=0.2, label="+-3 sigma (filter)")
        ax.plot(t_truth, np.degrees(e[:, i]), "k", lw=0.8, label="error vs VICON")
        inside = np.mean(np.abs(e[:, i]) <= 3 * sigma[:, i])
        limit = 3 * np.degrees(np.abs(e[:, i]).max()) + 1
        ax.set(ylim=(-limit, limit), ylabel="error (deg)", title=f"{name}\nbody {'xyz'[i]}: {100 * inside:.1f} % inside")
    print(f"{name}: NEES mean {nees.mean():.2f}, median {np.median(nees):.2f} (consistent: mean 3)")
for ax in axes[1]:
    ax.set_xlabel("time (s)")
axes[0, 0].legend(fontsize=8, loc="lower left")
fig.suptitle(f"{rec.id}: attitude error (body-frame rotation vector) and the filter's 3-sigma bound")
plt.tight_layout()
plt.show()

# %% [markdown]
# Read the top row (Kraft's plain filter) first. While the board lies flat, body z is the
# vertical: its bound opens up steadily (nothing measures the heading) and x and y stay tight.
# Between 15 and 25 s and again around 35-40 s the board stands on its side, body x or y becomes
# the vertical, and the unobservable heading is now *their* error: the x and y bounds balloon, and
# the 10 degree x error around 20 s is a heading error, inside its bound. The error does leave the
# bound now and then (3-4 % of the samples on x and y, where 0.3 % would be expected), and the
# NEES averages above 3: the plain filter is *optimistic*, its $P$ is too small, because the
# hand's accelerations and the gyro's scale errors of notebook 1 are not in its model. The
# default `ukf` (bottom) models both: it inflates $R$ while the hand accelerates and $Q$ while
# the board turns fast. Its errors are smaller and never leave the bound, but the bound is wide
# and its NEES far below 3: it is *pessimistic*, tuned for the lowest error (notebook 6) rather
# than for a calibrated $P$.
# The distribution of the NEES, with the filters that estimate the gyro bias and scale factors:

# %%
fig, ax = plt.subplots(figsize=(8, 3.4))
bins = np.logspace(-3, 2, 60)
for spec in (SPEC, "ukf", "ukf-bias"):
    _, _, nees_spec = error_and_sigma(spec)
    ax.hist(nees_spec, bins=bins, histtype="step", lw=1.5, weights=np.full(len(nees_spec), 1 / len(nees_spec)),
            label=f"{spec}: mean {nees_spec.mean():.2f}")
ax.axvline(3, color="k", ls="--", lw=0.8, label="chi-square(3) mean")
ax.set(xscale="log", xlabel="NEES  e^T P^-1 e", ylabel="fraction of samples", title=f"{rec.id}: filter consistency")
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# `ukf-bias`, which estimates the gyro bias and the x/y scale factors (and adapts $R$ like the
# default), is the closest to consistent here, still on the pessimistic side. Tuning $Q$ and $R$
# moves this balance: notebook 6 sweeps them.
#
# ## Summary
#
# * Kraft's UKF keeps the quaternion as the state and a 3x3 covariance on the body-frame
#   rotation-vector error; sigma points are built in the error space and mapped with $\operatorname{Exp}$.
# * The mean of quaternions is a short iteration; from the filter's centre point it converges at
#   once, from far away it converges linearly.
# * One step by hand equals `predict_kraft` + `update_kraft` and the estimator to rounding.
# * The recorded covariance gives the $\pm 3\sigma$ bound; NEES tells whether it is honest.
#
# **Try it:** run the step-by-step part with `ukf:tauc=0,Qs=0,sigma=julier` (a centre point with
# weight $\kappa/(n+\kappa)$): which numbers change, and which do not?
