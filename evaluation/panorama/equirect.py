"""The equirectangular pixel grid panoramas and scenes share (`PanoramaGrid`).

Longitude across, decreasing to the right so that the image is not mirrored when seen from
inside (column centre j at lon = pi - 2 pi (j + 0.5) / W; lon 0 = world +x in the middle),
latitude down (row centre i at lat = pi/2 - pi (i + 0.5) / H; +z at the top). Used by the
stitcher (`fusion.evaluation.panorama.recording`) and the camera simulator (`fusion.evaluation.panorama.camsim`);
numpy only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Largest panorama: 8K equirectangular, 33.5 Mpx; the stitcher's float32 accumulators take
# ~16 bytes per pixel (0.5 GB here); 100000 x 100000 would take 160 GB.
MAX_WIDTH_PX, MAX_HEIGHT_PX = 8192, 4096


@dataclass(frozen=True)
class PanoramaGrid:
    """Equirectangular pixel grid: width_px columns of longitude, height_px rows of latitude."""

    width_px: int = 1920
    height_px: int = 960

    def __post_init__(self) -> None:
        if self.width_px < 4 or self.height_px < 2:
            raise ValueError(f"panorama: size must be at least 4 x 2 px, got {self.width_px} x {self.height_px}")
        if self.width_px > MAX_WIDTH_PX or self.height_px > MAX_HEIGHT_PX:
            raise ValueError(f"panorama: size {self.width_px} x {self.height_px} px exceeds {MAX_WIDTH_PX} x {MAX_HEIGHT_PX} "
                             "(8K equirectangular; the stitcher keeps several float buffers of this size)")

    def lon(self, col: np.ndarray | float) -> np.ndarray:
        """Longitude (rad) of column coordinate(s) (pixel centres at integers)."""
        return math.pi - 2.0 * math.pi * (np.asarray(col, dtype=float) + 0.5) / self.width_px

    def lat(self, row: np.ndarray | float) -> np.ndarray:
        """Latitude (rad) of row coordinate(s)."""
        return 0.5 * math.pi - math.pi * (np.asarray(row, dtype=float) + 0.5) / self.height_px

    def col(self, lon: np.ndarray | float) -> np.ndarray:
        """Column coordinate of longitude(s), rad (not wrapped: lon outside (-pi, pi] gives
        columns outside [−0.5, W − 0.5))."""
        return (math.pi - np.asarray(lon, dtype=float)) * self.width_px / (2.0 * math.pi) - 0.5

    def row(self, lat: np.ndarray | float) -> np.ndarray:
        """Row coordinate of latitude(s), rad."""
        return (0.5 * math.pi - np.asarray(lat, dtype=float)) * self.height_px / math.pi - 0.5

    def pixel(self, direction_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(col, row) coordinates of world directions `(..., 3)` (any length)."""
        d = np.asarray(direction_world, dtype=float)
        lon = np.arctan2(d[..., 1], d[..., 0])
        lat = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
        return self.col(lon), self.row(lat)

    def area_weights(self) -> np.ndarray:
        """(H,) relative solid angle of a pixel in each row (cos latitude)."""
        return np.cos(self.lat(np.arange(self.height_px)))
