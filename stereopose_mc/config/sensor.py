"""Sensor realism of a scenario in SI: pixel camera, tracker faults (docs/realism.md).

The filters and the measurement model work in normalized image coordinates (focal
length 1, ``u = x / y``, ``v = z / y``). A pixel camera (``camera.resolution_px``) maps
them to pixels by

    col = c_x + f_px u,    row = c_y + f_px v,    f_px = (W / 2) / tan(fov / 2)

(``fov_deg`` horizontal, or ``focal_length_px`` directly; ``principal_point_px``
defaults to the image centre). So a noise of ``s`` pixels is ``s / f_px`` in normalized
units, and ``s`` px/s of image velocity is ``s / f_px`` 1/s. A feature is in an image
when ``0 <= col <= W`` and ``0 <= row <= H``.

A target shape (``target.shape``) gives feature points sampled on its surface
(``feature_points: {sample_on_surface: N}``, drawn from the generator of
``SeedSequence(seed, spawn_key=FEATURE_KEY)``, a stream no trial uses), their outward
normals, and the body for the occlusion and illumination tests (core/shapes.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core import shapes
from .schema import Scenario

DEG = math.pi / 180.0
# half-width (normalized units) of the square image assumed by the ``uniform_image``
# outlier model when the camera has no resolution: tan(26.6 deg), a 53 deg field of view
DEFAULT_HALF_WIDTH = 0.5
FEATURE_KEY = (0xFEA7, 0, 0)  # spawn key of the feature-sampling stream (trials use (j,) and (j, 0xFA))


@dataclass(frozen=True)
class PixelCamera:
    """A pinhole camera in pixels (the same for both cameras of the rig)."""

    width: int
    height: int
    f_px: float
    cx: float
    cy: float

    def normalized(self, col, row):
        """Normalized image coordinates ``(u, v)`` of image positions ``(col, row)`` (px):
        ``u = (col - c_x) / f_px``, ``v = (row - c_y) / f_px``."""
        return (np.asarray(col, dtype=float) - self.cx) / self.f_px, (np.asarray(row, dtype=float) - self.cy) / self.f_px

    def pixels(self, u, v):
        """Image positions ``(col, row)`` (px) of normalized coordinates ``(u, v)``: ``col = c_x + f_px u``."""
        return self.cx + self.f_px * np.asarray(u, dtype=float), self.cy + self.f_px * np.asarray(v, dtype=float)

    def bounds(self) -> tuple[float, float, float, float]:
        """The image in normalized coordinates: ``(u_min, u_max, v_min, v_max)``."""
        return (-self.cx / self.f_px, (self.width - self.cx) / self.f_px,
                -self.cy / self.f_px, (self.height - self.cy) / self.f_px)  # fmt: skip


@dataclass(frozen=True)
class SensorSetup:
    """Everything beyond the thesis's ideal sensor; the defaults are the thesis's."""

    pixels: PixelCamera | None = None
    dropout: float = 0.0  # per feature and step
    outlier_probability: float = 0.0
    outlier_model: str = "uniform_image"
    shape: shapes.Shape | None = None  # the target's body (target frame)
    normals: np.ndarray | None = None  # (N, 3) outward normals at the feature points
    occlusion: bool = False
    sun: np.ndarray | None = None  # (3,) unit vector toward the Sun in L

    @property
    def faults(self) -> bool:
        return self.dropout > 0.0 or self.outlier_probability > 0.0

    def image_bounds(self) -> tuple[float, float, float, float]:
        """Normalized image extent used by the ``uniform_image`` outliers."""
        if self.pixels is not None:
            return self.pixels.bounds()
        h = DEFAULT_HALF_WIDTH
        return (-h, h, -h, h)


def pixel_camera_of(s: Scenario) -> PixelCamera | None:
    c = s.camera
    if c.resolution_px is None:
        return None
    W, H = c.resolution_px
    f = c.focal_length_px if c.focal_length_px is not None else (W / 2.0) / math.tan(0.5 * c.fov_deg * DEG)
    cx, cy = c.principal_point_px if c.principal_point_px is not None else (W / 2.0, H / 2.0)
    return PixelCamera(int(W), int(H), float(f), float(cx), float(cy))


def sensor_of(s: Scenario) -> SensorSetup:
    m = s.measurements
    o = m.outliers
    shape = shape_of(s)
    normals = None if shape is None else feature_points_of(s, shape)[1]
    return SensorSetup(
        pixels=pixel_camera_of(s),
        dropout=m.dropout_probability,
        outlier_probability=0.0 if o is None else o.probability,
        outlier_model="uniform_image" if o is None else o.model,
        shape=shape,
        normals=normals,
        occlusion=m.occlusion,
        sun=None if m.illumination is None else np.asarray(m.illumination.sun_direction_lvlh, dtype=float),
    )


def shape_of(s: Scenario) -> shapes.Shape | None:
    """The target's body in SI (a mesh is read from its file)."""
    c = s.target.shape
    if c is None:
        return None
    if c.type == "box":
        return shapes.box(np.asarray(c.size_m, dtype=float))
    if c.type == "ellipsoid":
        return shapes.ellipsoid(np.asarray(c.semi_axes_m, dtype=float))
    from .meshfiles import read_mesh

    m = read_mesh(Path(c.file))
    return shapes.mesh(m.vertices, m.faces)


def feature_points_of(s: Scenario, shape: shapes.Shape | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Feature points ``(N, 3)`` in the target frame and (with a shape) their outward normals.

    With ``feature_slots`` (tracks fill the slots as they come and go) there are no fixed points: ``N`` zero
    points and no normals (the slots' true points vary per step, sim/slots.py).
    """
    t = s.target
    if t.feature_slots is not None:
        return np.zeros((t.feature_slots, 3)), None
    shape = shape if shape is not None else shape_of(s)
    if t.feature_points is None:
        pts = np.asarray(t.feature_points_m, dtype=float)
        return pts, None if shape is None else shapes.normals(shape, pts)
    rng = np.random.default_rng(np.random.SeedSequence(s.seed, spawn_key=FEATURE_KEY))
    return shapes.sample_surface(shape, t.feature_points.sample_on_surface, rng)


def feature_count(s: Scenario) -> int:
    """Number of feature points of a scenario (without reading a mesh)."""
    t = s.target
    if t.feature_slots is not None:
        return t.feature_slots
    return len(t.feature_points_m) if t.feature_points is None else t.feature_points.sample_on_surface


def truth_sigmas(s: Scenario) -> tuple[float, float]:
    """The truth's ``(image_sigma, flow_sigma)`` in normalized units (pixels converted)."""
    m = s.measurements
    cam = pixel_camera_of(s)
    si = m.image_sigma if m.image_sigma_px is None else m.image_sigma_px / cam.f_px
    sf = m.flow_sigma if m.flow_sigma_pxps is None else m.flow_sigma_pxps / cam.f_px
    return si, sf
