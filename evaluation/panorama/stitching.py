"""Stitching: camera frames and their orientations into an equirectangular panorama, and its scores.

The course reports' pipeline (project each pixel onto the unit sphere, rotate it into the world
frame with the frame's orientation, unwrap longitude/latitude into an image), done the
other way round: for every panorama pixel we ask where it falls in the frame and sample
it there with `cv2.remap` (inverse mapping: no holes, no per-pixel Python).

Panorama layout (`fusion.evaluation.panorama.equirect.PanoramaGrid`, the same for the scenes in `fusion.evaluation.panorama.camsim`):
longitude across, decreasing to the right so that the image is not mirrored when seen
from inside (column centre j at lon = pi - 2 pi (j + 0.5) / W; lon 0 = world +x in the
middle), latitude down (row centre i at lat = pi/2 - pi (i + 0.5) / H; +z at the top).

Speed: the panorama's pixel directions are separable (cos lat * cos lon, ...), so they are
"precomputed" as four 1-D tables; per frame only the panorama's bounding box of the frame
footprint is touched, and the remap coordinates are computed exactly on a coarse grid
(every `map_step_px` pixels) and bilinearly upsampled with `cv2.resize` (the map is smooth:
at 8 px the interpolation error is well under 0.05 px).

Memory: the accumulators (`(H, W, 4)` float32 for `average`/`feather`, `(H, W, 3)` uint8
plus a coverage mask for `last`), one frame and one warped region, whatever the number of
frames. OpenCV is imported here and in `fusion.evaluation.panorama.camsim` only.

Arrays in, arrays out: reading a recording's camera file or scene is `fusion.evaluation.panorama.recording`'s.
"""
from __future__ import annotations

import math
import sys
import warnings
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from fusion.camera import CameraModel, CameraSource
from fusion.types import Trajectory

from .equirect import PanoramaGrid  # noqa: F401  (PanoramaGrid: part of this module's API)

Blend = Literal["last", "average", "feather"]
BLENDS = ("last", "average", "feather")


# --------------------------------------------------------------------------- geometry
@dataclass
class Panorama:
    """A stitched panorama.

    image: (H, W, 3) uint8, black where nothing landed; channel order as the frames'.
    covered: (H, W) bool, pixels at least one frame covered.
    frames_used, frames_skipped: counts (skipped: no orientation at the frame's time).
    """

    image: np.ndarray
    covered: np.ndarray
    frames_used: int = 0
    frames_skipped: int = 0
    channel_order: str = "rgb"
    grid: PanoramaGrid = field(default_factory=PanoramaGrid)

    @property
    def covered_fraction(self) -> float:
        """Covered share of the sphere's solid angle (cos-latitude weighted)."""
        w = self.grid.area_weights()
        return float((self.covered * w[:, None]).sum() / (w.sum() * self.grid.width_px))

    def bgr(self) -> np.ndarray:
        """The image in OpenCV's channel order (for `cv2.imwrite`)."""
        return self.image[..., ::-1].copy() if self.channel_order == "rgb" else self.image


class Stitcher:
    """Accumulates frames into a panorama, one `add(frame, rotation)` at a time.

    camera: the camera model (frame size and field of view).
    grid: panorama size.
    blend: "last" (each pixel shows the last frame that covered it: the course reports'), "average"
        (mean of all frames covering it) or "feather" (weighted mean, weight = 1 + distance
        in px to the nearest frame border, so seams fade).
    map_step_px: spacing of the exactly computed remap coordinates (1 = every pixel).
    """

    def __init__(self, camera: CameraModel | None = None, grid: PanoramaGrid | None = None,
                 blend: Blend = "feather", map_step_px: int = 8) -> None:
        if blend not in BLENDS:
            raise ValueError(f"panorama: blend must be one of {BLENDS}, got {blend!r}")
        if map_step_px < 1:
            raise ValueError(f"panorama: map_step_px must be >= 1, got {map_step_px}")
        self.camera = camera or CameraModel()
        self.grid = grid or PanoramaGrid()
        self.blend = blend
        self.step = int(map_step_px)
        H, W = self.grid.height_px, self.grid.width_px
        h, w = self.camera.height_px, self.camera.width_px
        # The precomputed panorama direction grid, in separable form (cos lat cos lon, ...).
        self._border = self.camera.border_directions(32)  # (M, 3) body frame
        if blend == "last":
            self._image = np.zeros((H, W, 3), np.uint8)
            self._count = np.zeros((H, W), np.uint8)  # 0/1 coverage
            self._ones = np.ones((h, w), np.uint8)
        else:
            self._acc = np.zeros((H, W, 4), np.float32)  # premultiplied colour, weight
            if blend == "average":
                weight = np.ones((h, w), np.float32)
            else:
                v, u = np.mgrid[0:h, 0:w]
                weight = (np.minimum(np.minimum(u, w - 1 - u), np.minimum(v, h - 1 - v)) + 1.0).astype(np.float32)
            self._weight = weight
            # frame (BGRA, alpha 255) * [w, w, w, w / 255] = [premultiplied colour, w]
            self._w4 = np.dstack([weight, weight, weight, weight / 255.0]).astype(np.float32)
            self._bgra = np.empty((h, w, 4), np.uint8)
            self._src = np.empty((h, w, 4), np.float32)
        # Work buffers, grown on demand and reused: allocating fresh megabyte arrays per
        # frame costs more (page faults) than the arithmetic.
        self._buffers: dict[str, np.ndarray] = {}
        self.frames_used = 0

    def _buffer(self, name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
        """A view of shape `shape` into a reusable buffer (contents undefined)."""
        buf = self._buffers.get(name)
        if buf is None or any(n > m for n, m in zip(shape, buf.shape)):
            grown = shape if buf is None else tuple(max(n, m) for n, m in zip(shape, buf.shape))
            buf = self._buffers[name] = np.empty(grown, dtype)
        return buf[tuple(slice(0, n) for n in shape)]

    # -- per frame ------------------------------------------------------------------
    def footprint(self, rot_world_body: np.ndarray) -> tuple[int, int, int, int]:
        """Panorama bounding box `(row0, row1, col0, col1)` (half-open) of a frame's footprint.
        Columns are unwrapped: they may start below 0 or end beyond W (the seam)."""
        R = np.asarray(rot_world_body, dtype=float)
        g = self.grid
        H, W = g.height_px, g.width_px
        d = self._border @ R.T  # world directions of the frame border
        lon = np.arctan2(d[:, 1], d[:, 0])
        lat = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        loop = np.unwrap(np.append(lon, lon[0]))
        margin = 2 + self.step // 4
        rows = g.row(lat)
        r0 = max(0, int(math.floor(rows.min())) - margin)
        r1 = min(H, int(math.ceil(rows.max())) + margin + 1)
        if abs(loop[-1] - loop[0]) > math.pi:  # the border winds around a pole: it is inside
            if R[2, 0] > 0:
                r0 = 0
            else:
                r1 = H
            return r0, r1, 0, W
        cols = g.col(loop)
        c0 = int(math.floor(cols.min())) - margin
        c1 = int(math.ceil(cols.max())) + margin + 1
        if c1 - c0 >= W:
            return r0, r1, 0, W
        shift = (c0 // W) * W  # bring c0 into [0, W)
        return r0, r1, c0 - shift, c1 - shift

    def _map(self, R: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """(r1 - r0, c1 - c0, 2) float32 frame coordinates (u, v) of the region's pixels."""
        s = self.step
        h, w = r1 - r0, c1 - c0
        nr, nc = -(-h // s), -(-w // s)
        # Coarse samples at fine positions k s + (s - 1) / 2, k = -1 .. n: exactly where
        # cv2.resize by a factor s puts its source pixel centres; the extra ring avoids
        # clamped extrapolation at the region edges.
        off = (s - 1) / 2.0
        lat = self.grid.lat(r0 + off + s * np.arange(-1, nr + 1))
        lon = self.grid.lon(c0 + off + s * np.arange(-1, nc + 1))
        cl, sl = np.cos(lat)[:, None], np.sin(lat)[:, None]
        co, so = np.cos(lon)[None, :], np.sin(lon)[None, :]
        # body = R^T world, world = (cl co, cl so, sl): separable products
        x = cl * (R[0, 0] * co + R[1, 0] * so) + R[2, 0] * sl
        y = cl * (R[0, 1] * co + R[1, 1] * so) + R[2, 1] * sl
        z = cl * (R[0, 2] * co + R[1, 2] * so) + R[2, 2] * sl
        u, v = self.camera.project(x, y, z)
        front = x > 0.1  # within 84 deg of the optical axis
        all_front = bool(front.all())
        if not all_front:
            u = np.where(front, u, -1e4)
            v = np.where(front, v, -1e4)
        coarse = np.stack([u, v], axis=-1).astype(np.float32)
        size = ((nc + 2) * s, (nr + 2) * s)  # cv2 order: width, height
        if s == 1:
            fine = coarse
        else:
            fine = cv2.resize(coarse, size, dst=self._buffer("map", (size[1], size[0], 2), np.float32),
                              interpolation=cv2.INTER_LINEAR)
        fine = fine[s : s + h, s : s + w]
        if not all_front:
            # A pixel is usable only if every coarse sample around it was in front: the
            # azimuth wraps behind the camera, and interpolating across that is garbage.
            f = front.astype(np.float32)
            if s > 1:
                f = cv2.resize(f, size, interpolation=cv2.INTER_LINEAR)
            fine[f[s : s + h, s : s + w] < 0.999] = -1e4
        return fine

    def add(self, frame: np.ndarray, rot_world_body: np.ndarray) -> None:
        """Blend one frame into the panorama.

        frame: (h, w, 3) uint8 image (the camera model's size).
        rot_world_body: (3, 3) orientation `R_world_body` at the frame's time.
        """
        if frame.shape != (self.camera.height_px, self.camera.width_px, 3):
            raise ValueError(f"panorama: frame shape {frame.shape} does not match the camera model "
                             f"({self.camera.height_px}, {self.camera.width_px}, 3)")
        R = np.asarray(rot_world_body, dtype=float)
        r0, r1, c0, c1 = self.footprint(R)
        if r1 <= r0:
            return
        fmap = self._map(R, r0, r1, c0, c1)
        W = self.grid.width_px
        # Split the unwrapped column range at the seam: (panorama cols, region cols).
        pieces = [(c0, min(c1, W), 0)]
        if c1 > W:
            pieces.append((0, c1 - W, W - c0))
        if self.blend == "last":
            shape = fmap.shape[:2]
            warped = cv2.remap(frame, fmap, None, cv2.INTER_LINEAR, dst=self._buffer("warp8", shape + (3,), np.uint8),
                               borderMode=cv2.BORDER_REPLICATE)
            hit = cv2.remap(self._ones, fmap, None, cv2.INTER_NEAREST, dst=self._buffer("hit", shape, np.uint8),
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            for p0, p1, q0 in pieces:
                q1 = q0 + p1 - p0
                cv2.copyTo(warped[:, q0:q1], hit[:, q0:q1], self._image[r0:r1, p0:p1])
                dst = self._count[r0:r1, p0:p1]
                cv2.bitwise_or(dst, hit[:, q0:q1], dst=dst)
        else:
            cv2.cvtColor(frame, cv2.COLOR_RGB2RGBA, dst=self._bgra)  # alpha = 255
            cv2.multiply(self._bgra, self._w4, dst=self._src, dtype=cv2.CV_32F)  # premultiplied colour, weight
            warped = cv2.remap(self._src, fmap, None, cv2.INTER_LINEAR,
                               dst=self._buffer("warp", fmap.shape[:2] + (4,), np.float32),
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            for p0, p1, q0 in pieces:
                q1 = q0 + p1 - p0
                dst = self._acc[r0:r1, p0:p1]
                cv2.add(dst, warped[:, q0:q1], dst=dst)
        self.frames_used += 1

    # -- result -----------------------------------------------------------------------
    def result(self, frames_skipped: int = 0, channel_order: str = "rgb") -> Panorama:
        """The panorama so far (new arrays)."""
        if self.blend == "last":
            image, covered = self._image.copy(), self._count > 0
        else:
            wsum = self._acc[..., 3]
            covered = wsum >= 0.5  # at least half a pixel's worth of weight
            image = np.zeros(wsum.shape + (3,), np.uint8)
            acc = self._acc[covered]  # (n, 4): premultiplied colour, weight
            image[covered] = np.clip(np.rint(acc[:, :3] / acc[:, 3:]), 0, 255).astype(np.uint8)
        return Panorama(image, covered, self.frames_used, frames_skipped, channel_order, self.grid)


def frame_rotations(camera: CameraSource, trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Orientation at each frame time, slerped from the trajectory.

    Returns `(rot (K_used, 3, 3) R_world_body, used (K,) bool)`; frames outside the
    trajectory's span or inside a gap of it are not used.
    """
    rotation, mask = trajectory.interpolate(camera.t)
    if rotation is None:
        return np.zeros((0, 3, 3)), mask
    return rotation.as_matrix(), mask


def stitch(camera: CameraSource, trajectory: Trajectory, *, model: CameraModel | None = None,
           grid: PanoramaGrid | None = None, blend: Blend = "feather", map_step_px: int = 8,
           progress: bool = False, desc: str = "frames") -> Panorama:
    """Stitch every frame of `camera` with its orientation slerped from `trajectory`.

    model: camera model (default: the course reports' 60 x 45 deg for the frames' size).
    Frames whose time falls outside the trajectory (or in a gap of it) are skipped with a
    warning. `progress` shows a tqdm bar on stderr.
    """
    h, w = camera.shape[:2]
    if model is None:
        model = CameraModel() if (w, h) == (320, 240) else CameraModel(
            width_px=w, height_px=h, hfov_rad=math.radians(60.0), vfov_rad=math.radians(60.0) * h / w)
    if (model.width_px, model.height_px) != (w, h):
        raise ValueError(f"panorama: camera model is {model.width_px} x {model.height_px} px but "
                         f"{camera.source or 'the camera'} has {w} x {h} px frames")
    stitcher = Stitcher(model, grid, blend, map_step_px)
    rots, used = frame_rotations(camera, trajectory)
    skipped = int((~used).sum())
    if skipped:
        warnings.warn(
            f"{camera.source or 'camera'}: {skipped} of {len(used)} frames fall outside the trajectory "
            f"({trajectory.t[0]:.3f}-{trajectory.t[-1]:.3f} s) or in a gap of it and are skipped",
            stacklevel=2,
        )
    indices = np.flatnonzero(used)
    frames = camera.frames(indices)
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, total=len(indices), desc=desc, unit="frame", leave=False, file=sys.stderr)
    for i, (_, _, frame) in enumerate(frames):
        stitcher.add(frame, rots[i])
    return stitcher.result(skipped, camera.channel_order)


# --------------------------------------------------------------------------- scores
def _masked_weights(grid: PanoramaGrid, mask: np.ndarray) -> np.ndarray:
    return mask * grid.area_weights()[:, None]


def psnr_db(a: np.ndarray, b: np.ndarray, mask: np.ndarray, grid: PanoramaGrid | None = None) -> float:
    """PSNR (dB, peak 255) of two (H, W, 3) uint8 images over `mask` (H, W) bool.

    With `grid`, pixels are weighted by their solid angle (cos latitude): the WS-PSNR of
    360-degree video coding (Sun, Lu, Yu 2017). NaN if the mask is empty.
    """
    w = mask.astype(float) if grid is None else _masked_weights(grid, mask)
    if w.sum() <= 0:
        return float("nan")
    err = (a.astype(np.float32) - b.astype(np.float32)) ** 2
    mse = float((err.sum(axis=-1) * w).sum() / (3.0 * w.sum()))
    return float("inf") if mse == 0 else 10.0 * math.log10(255.0**2 / mse)


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray, grid: PanoramaGrid | None = None, sigma_px: float = 1.5) -> float:
    """Mean SSIM (Wang, Bovik, Sheikh, Simoncelli 2004, eq. 13; Gaussian window sigma 1.5 px,
    K1 = 0.01, K2 = 0.03, L = 255) of the grey levels (channel mean) of two (H, W, 3) uint8
    images, averaged over `mask` eroded by the window radius (so no window sees an uncovered
    pixel), cos-latitude weighted with `grid`. NaN if nothing is left."""
    radius = int(3.5 * sigma_px + 0.5)
    k = 2 * radius + 1
    inner = cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    w = inner.astype(float) if grid is None else _masked_weights(grid, inner)
    if w.sum() <= 0:
        return float("nan")
    x = a.astype(np.float32).mean(axis=-1)
    y = b.astype(np.float32).mean(axis=-1)
    blur = lambda img: cv2.GaussianBlur(img, (k, k), sigma_px, borderType=cv2.BORDER_REFLECT)  # noqa: E731
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    smap = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float((smap * w).sum() / w.sum())


def score_panorama(estimate: Panorama, reference: Panorama | np.ndarray, reference_covered: np.ndarray | None = None) -> dict[str, float]:
    """PSNR, SSIM and covered fraction of `estimate` against a reference panorama (or a
    scene image of the same size) over the pixels both cover. Weighted by solid angle."""
    grid = estimate.grid
    if isinstance(reference, Panorama):
        ref_image, ref_cov = reference.image, reference.covered
    else:
        ref_image = reference
        ref_cov = np.ones(ref_image.shape[:2], bool) if reference_covered is None else reference_covered
    if ref_image.shape != estimate.image.shape:
        raise ValueError(f"panorama: reference shape {ref_image.shape} differs from the estimate's {estimate.image.shape}")
    both = estimate.covered & ref_cov
    w = grid.area_weights()
    return {
        "psnr_db": psnr_db(estimate.image, ref_image, both, grid),
        "ssim": ssim(estimate.image, ref_image, both, grid),
        "covered_fraction": float((both * w[:, None]).sum() / (w.sum() * grid.width_px)),
    }


def comparison_image(estimate: Panorama, reference: Panorama) -> np.ndarray:
    """BGR image for `--reference`: the estimate's panorama on top, the ground truth's below,
    then their absolute difference (x 2) over the pixels both cover, each labelled."""
    both = estimate.covered & reference.covered
    diff = cv2.absdiff(estimate.bgr(), reference.bgr())
    diff = cv2.convertScaleAbs(diff, alpha=2.0)
    diff[~both] = 0
    panels = []
    for image, label in ((estimate.bgr(), "estimate"), (reference.bgr(), "ground truth"), (diff, "|difference| x 2")):
        image = np.ascontiguousarray(image)
        scale = image.shape[0] / 480.0
        cv2.putText(image, label, (int(10 * scale), int(30 * scale)), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255),
                    max(1, int(2 * scale)), cv2.LINE_AA)
        panels.append(image)
    return np.vstack(panels)

