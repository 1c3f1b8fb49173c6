# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 7. Panoramas from orientations
#
# The course platform carries a camera looking along the body x axis. Paste every frame onto a
# sphere at the orientation the estimator gives for its time stamp, unwrap the sphere, and you
# have a panorama: a picture of your orientation errors. A heading error shifts a frame sideways,
# a tilt error bends it up or down, and frames taken from the same view at different times stop
# lining up. In this notebook:
#
# 1. the camera model: from a pixel to a direction in the body frame, and back;
# 2. frames rendered from a real 360-degree photograph with the VICON orientations;
# 3. from a frame and an orientation to panorama pixels;
# 4. panoramas stitched with the estimates of several estimators, scored against the panorama
#    stitched with VICON.
#
# **About the frames.** The course released camera recordings for its sessions, but they are
# 0.1-1 GB each and not available here. So the frames are *rendered*: at 10 frames per second, with
# the VICON orientation at each frame time, from `scenes/room_equirect.jpg`, a real equirectangular
# photograph of a room (the example image of the MIT-licensed py360convert project). Without the
# data folder, a procedural scene is generated instead. The estimators never see these frames:
# they only supply the orientations used to stitch them back.

# %%
# %matplotlib inline
import matplotlib.pyplot as plt
import numpy as np

from fusion import estimators
from fusion.camera import CameraModel
from fusion.datasets import data_dir_from, initial_orientation
from fusion.evaluation.panorama import camsim
from fusion.evaluation.panorama.equirect import PanoramaGrid
from fusion.evaluation.scoring.metrics import score
from fusion.evaluation.panorama.recording import comparison_image, estimate_panorama, reference_panorama
from tutorial_data import load_recording

plt.rcParams.update({"figure.figsize": (10, 3.4), "figure.dpi": 90})
rec = load_recording("ece276a/3")
DATA = data_dir_from(None)
scene = camsim.scene_for(rec.id, DATA)  # (H, W, 3) uint8, OpenCV's BGR channel order
print("scene:", scene.shape)


def rgb(image_bgr):
    """OpenCV images are BGR; matplotlib wants RGB."""
    return image_bgr[..., ::-1]


fig, ax = plt.subplots(figsize=(10, 5))
ax.imshow(rgb(scene), extent=(180, -180, -90, 90))
ax.set(xlabel="longitude (deg; 0 = world +x, increasing to the left)", ylabel="latitude (deg)",
       title="the scene: an equirectangular 360-degree image")
plt.show()

# %% [markdown]
# An equirectangular image maps longitude to columns and latitude to rows. The toolkit's layout
# (`PanoramaGrid`): column $j$ (of $W$) is at longitude $\lambda = \pi - 2\pi (j + 0.5)/W$, so longitude
# *decreases* to the right and the image is not mirrored when seen from inside the sphere; row $i$
# (of $H$) is at latitude $\varphi = \pi/2 - \pi (i + 0.5)/H$, world up at the top.
#
# ## 7.1 The camera model
#
# `CameraModel`: 320 x 240 pixels, 60 x 45 degrees field of view, and the course reports'
# *spherical* projection: pixel columns and rows are equal steps of azimuth $\alpha$ and elevation $\epsilon$
# about the optical axis (body x),
#
# $$ u = c_x - k_x \alpha, \quad v = c_y - k_y \epsilon, \qquad
#    d_\text{body} = (\cos\epsilon \cos\alpha,\ \cos\epsilon \sin\alpha,\ \sin\epsilon), $$
#
# with $k_x = W / \text{hfov}$ pixels per radian. Columns grow to the right (body $-y$), rows
# downwards (body $-z$).

# %%
camera = CameraModel()
print(camera)
print("centre pixel (cx, cy) =", camera.center_px, "; pixels per rad (kx, ky) =", np.round(camera.scale, 2))
corners = np.array([[0, 0], [camera.width_px - 1, 0], [0, camera.height_px - 1], [camera.width_px - 1, camera.height_px - 1]])
d = camera.directions(corners[:, 0], corners[:, 1])
az, el = np.degrees(np.arctan2(d[:, 1], d[:, 0])), np.degrees(np.arcsin(d[:, 2]))
for (u, v), a, e in zip(corners, az, el):
    print(f"pixel ({u:3d}, {v:3d}) -> azimuth {a:+6.2f} deg, elevation {e:+6.2f} deg")
u_back, v_back = camera.project(d[:, 0], d[:, 1], d[:, 2])
print("project(directions(u, v)) == (u, v):", np.allclose(u_back, corners[:, 0]) and np.allclose(v_back, corners[:, 1]))

# %% [markdown]
# ## 7.2 Frames from the scene
#
# A frame is rendered by asking, for every pixel, which world direction it sees,
# $d_\text{world} = R_\text{world,body}\, d_\text{body}$, and reading the scene there
# (`camsim.SceneRenderer`, one `cv2.remap` per frame). `camsim.simulate_camera` does it at 10 Hz
# over the span of the VICON orientations:

# %%
frames = camsim.simulate_camera(rec.truth, scene, rate_hz=10.0, model=camera, source=f"{rec.id} (rendered)")
print(f"{len(frames.t)} frames over {frames.t[-1] - frames.t[0]:.1f} s")
picks = np.linspace(0, len(frames.t) - 1, 4).astype(int)
fig, axes = plt.subplots(1, 4, figsize=(12, 2.6))
for ax, k in zip(axes, picks):
    ax.imshow(rgb(frames.frame(k)))
    ax.set_title(f"t = {frames.t[k] - rec.imu.t[0]:.1f} s", fontsize=9)
    ax.axis("off")
plt.show()

# %% [markdown]
# ## 7.3 From a frame to the panorama
#
# Stitching is the same map run the other way: for every *panorama* pixel, find where it falls
# in the frame ($d_\text{body} = R^\top d_\text{world}$, then `project`) and sample the frame there
# (`fusion.evaluation.panorama.recording.Stitcher`, inverse mapping: no holes). With a wrong $R$, the frame is
# pasted in the wrong place. Where does each frame's centre pixel land, with the true orientations?

# %%
grid = PanoramaGrid(1024, 512)
R = frames.rotations  # (K, 3, 3) R_world_body the frames were rendered with
axis_world = R @ np.array([1.0, 0.0, 0.0])  # the optical axis, body x, in the world frame
col, row = grid.pixel(axis_world)
fig, ax = plt.subplots(figsize=(10, 5))
ax.imshow(rgb(camsim.resample_scene(scene, grid)))
sc = ax.scatter(col, row, c=frames.t - frames.t[0], s=6, cmap="plasma")
fig.colorbar(sc, ax=ax, label="time (s)", shrink=0.7)
ax.set(xlabel="panorama column (px)", ylabel="panorama row (px)", title="where the camera looked (centre pixel of each frame)")
plt.show()

# %% [markdown]
# ## 7.4 Panoramas from estimated orientations
#
# `reference_panorama` renders the frames and stitches them with VICON; `estimate_panorama`
# stitches the *same* frames with an estimate and scores it against the reference, over the pixels
# both cover: PSNR (dB, higher is better) and SSIM (1 = identical structure), both weighted by the
# pixels' solid angle (`cos latitude`). The command line does the same:
# `fusion panorama --dataset ece276a/3 --estimator gn --out pano.png --reference`.

# %%
q0 = initial_orientation(rec)
reference = reference_panorama(rec, data_dir=DATA, grid=grid)
panoramas, rows = {}, []
for spec in ("dr", "ukf", "ekf", "gn"):
    trajectory = estimators.build(spec).estimate(rec.imu, q0)
    panoramas[spec], scores = estimate_panorama(rec, trajectory, data_dir=DATA, grid=grid)
    rmse = score(rec.truth, trajectory).rmse_deg
    rows.append((spec, rmse["inclination"], rmse["heading"], scores["psnr_db"], scores["ssim"]))
print(f"{'estimator':<10}{'inclination':>12}{'heading':>9}{'PSNR dB':>9}{'SSIM':>7}   (RMSE in deg, vs the VICON panorama)")
for r in rows:
    print(f"{r[0]:<10}{r[1]:12.2f}{r[2]:9.2f}{r[3]:9.2f}{r[4]:7.3f}")

# %%
fig, axes = plt.subplots(3, 2, figsize=(12, 9))
axes[0, 0].imshow(rgb(reference.truth.bgr()))
axes[0, 0].set_title("stitched with VICON (the reference)")
axes[0, 1].imshow(rgb(reference.scene))
axes[0, 1].set_title("the scene itself")
for ax, (spec, *_, psnr, ssim) in zip(axes.flat[2:], rows):
    ax.imshow(rgb(panoramas[spec].bgr()))
    ax.set_title(f"stitched with {spec}: PSNR {psnr:.1f} dB, SSIM {ssim:.3f}")
for ax in axes.flat:
    ax.axis("off")
plt.tight_layout()
plt.show()

# %% [markdown]
# Dead reckoning drifts in heading by over ten degrees on this recording: frames taken when the
# board comes back to a view it saw before land beside their earlier copies, and edges double.
# The filters hold the tilt, so horizontal lines stay straight, but their heading still wanders
# (`ekf`, with its scale-factor states, wanders less than `ukf`). The smoother, which bends the
# whole trajectory to fit every sample, has the smallest heading error and the highest PSNR (its
# SSIM is on par with `ekf`'s: the two scores weigh misplaced edges differently). The differences to
# the reference show where:

# %%
worst = min(rows, key=lambda r: r[3])[0]
best = max(rows, key=lambda r: r[3])[0]
fig, axes = plt.subplots(1, 2, figsize=(12, 6.5))
for ax, spec in zip(axes, (worst, best)):
    ax.imshow(rgb(comparison_image(panoramas[spec], reference.truth)))
    ax.set_title(f"{spec}: estimate, reference, |difference| x 2")
    ax.axis("off")
plt.tight_layout()
plt.show()

# %% [markdown]
# ## Summary
#
# * A panorama is the orientation estimate made visible: each frame's place on the sphere is
#   $R_\text{world,body}$ applied to its pixels' directions.
# * Heading errors shift frames sideways, tilt errors bend them; both blur and double the
#   panorama, and PSNR/SSIM against the VICON panorama follow the orientation errors.
# * The frames here are rendered from a real photograph with the VICON orientations, because the
#   course's camera files are not available; with a recording's own camera file
#   (`<data>/<course>/cam/camN.p`), the same functions stitch the real frames.
#
# **Try it:** stitch with `ukf:hf=true` (no accelerometer correction about the vertical) and with
# `gn:saxes=none`: which panorama gets sharper, and does the heading RMSE say the same?
