"""The scenario schema (the public contract of a scenario YAML file).

Units follow the key names: ``_km``, ``_m``, ``_deg``, ``_degps`` (deg/s), ``_m2``
(variances), ``_deg2ps2`` (deg^2/s^2). Everything is converted to SI (m, s, rad) by
``stereopose_mc.config.resolve``; the numerical core never sees degrees.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from . import filters as _filters
from .base import NonNeg, Pos, Vec3, _Model
from .filters import (EKFConfig, FilterConfig, FilterMeasurementNoise, GatingConfig, IEKFConfig, MEKFConfig,
                      ProcessNoiseConfig, UKFConfig)  # noqa: F401 (the scenario's filter entries: config/filters.py)

SCHEMA_VERSION = 1

# Physical ranges: a value outside them is no scenario of this tool, and would make a run crash
# or integrate for hours (issue 34, item 8). Each is far outside every use (the thesis: a = 7078 km,
# |rho| = 40 m, |omega| < 10 deg/s).
MAX_A_KM = 1.0e6  # beyond the Earth's sphere of influence (~0.93e6 km)
MAX_RANGE_M = 1.0e5  # relative position: a stereo camera does not see features 100 km away
MAX_SPEED_MPS = 1.0e3  # relative velocity
MAX_RATE_DEGPS = 360.0  # one revolution per second
MAX_SEED = 2**63 - 1  # the seed is an int64 column of the tables
MAX_DENSITY_KGPM3 = 1.225  # the sea-level density
MIN_SCALE_HEIGHT_KM = 1.0  # the Earth's atmosphere: 6-70 km



def _normalized(v: list[float], what: str) -> list[float]:
    """``v / |v|``; a zero or non-finite ``v`` is an error naming ``what``."""
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"{what} must be non-zero")
    return [float(c) / n for c in v]


class TimeConfig(_Model):
    dt_s: Pos = 1.0
    duration_s: Pos = 100.0
    error_window_start_s: NonNeg = 10.0
    truth_rtol: Annotated[float, Field(gt=0, lt=1e-3)] = 1e-12

    @model_validator(mode="after")
    def _whole_steps(self):
        steps = self.duration_s / self.dt_s
        if abs(steps - round(steps)) > 1e-9 * max(1.0, steps):
            raise ValueError(f"duration_s ({self.duration_s}) must be a whole number of dt_s ({self.dt_s})")
        if self.error_window_start_s >= self.duration_s:
            raise ValueError("error_window_start_s must be before duration_s")
        return self


class OrbitConfig(_Model):
    a_km: Annotated[float, Field(gt=0, le=MAX_A_KM)]
    e: Annotated[float, Field(ge=0, lt=1)]
    i_deg: float = 0.0
    raan_deg: float = 0.0
    argp_deg: float = 0.0
    true_anomaly_deg: float = 0.0

    @model_validator(mode="after")
    def _above_ground(self):
        if self.a_km * (1.0 - self.e) < 6378.137:
            raise ValueError(f"perigee radius a(1-e) = {self.a_km * (1 - self.e):.1f} km is below the Earth's surface")
        return self


class LeaderConfig(_Model):
    orbit: OrbitConfig


class BoxShape(_Model):
    type: Literal["box"]
    size_m: Annotated[list[Pos], Field(min_length=3, max_length=3)] = Field(
        description="edge lengths along the target's x, y, z (centred at its centre of mass)"
    )


class EllipsoidShape(_Model):
    type: Literal["ellipsoid"]
    semi_axes_m: Annotated[list[Pos], Field(min_length=3, max_length=3)]


class MeshShape(_Model):
    type: Literal["mesh"]
    file: Annotated[str, Field(min_length=1)] = Field(
        description="closed triangle mesh (OBJ, STL, PLY) in the target frame, metres; a relative path is taken "
        "from the scenario file's folder"
    )


ShapeConfig = Annotated[Union[BoxShape, EllipsoidShape, MeshShape], Field(discriminator="type")]


class SampledFeaturesConfig(_Model):
    sample_on_surface: Annotated[int, Field(ge=1, le=500)] = Field(
        description="number of feature points drawn uniformly over the shape's surface (deterministic from the seed)"
    )


class TargetConfig(_Model):
    inertia_kgm2: Annotated[list[Pos], Field(min_length=3, max_length=3)] = Field(
        description="principal moments Ix, Iy, Iz (kg m^2); only their ratios matter torque-free"
    )
    feature_points_m: Annotated[list[Vec3], Field(min_length=1)] | None = Field(
        default=None, description="feature points P_i in the target frame; or feature_points with a shape"
    )
    shape: ShapeConfig | None = Field(
        default=None,
        description="the target's body, `{type: box, size_m}`, `{type: ellipsoid, semi_axes_m}` or `{type: mesh, "
        "file}`: occlusion, illumination, feature sampling (docs/realism.md)",
    )
    feature_points: SampledFeaturesConfig | None = Field(
        default=None, description="`{sample_on_surface: N}` instead of feature_points_m (needs shape)"
    )
    feature_slots: Annotated[int, Field(ge=1, le=500)] | None = Field(
        default=None,
        description="number N of feature slots in the state, refilled as tracks come and go; instead of "
        "feature_points_m / feature_points, for measurements.source images or tracks (docs/images.md)",
    )

    @model_validator(mode="after")
    def _points(self):
        given = [k for k in ("feature_points_m", "feature_points", "feature_slots") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of feature_points_m, feature_points or feature_slots"
                             + (f" (got {', '.join(given)})" if given else ""))
        if self.feature_points is not None and self.shape is None:
            raise ValueError("feature_points: {sample_on_surface: N} needs target.shape")
        return self

    @field_validator("inertia_kgm2")
    @classmethod
    def _triangle(cls, v):
        a, b, c = v
        if a + b < c or a + c < b or b + c < a:
            raise ValueError(f"principal moments {v} violate the triangle inequality (no rigid body has them)")
        return v


class InitialStateConfig(_Model):
    rho_m: Vec3
    rho_dot_mps: Vec3
    omega_degps: Vec3
    q: Annotated[list[float], Field(min_length=4, max_length=4)] = Field(
        description="scalar first, target -> leader (LVLH); normalized on load"
    )

    @field_validator("rho_m", "rho_dot_mps", "omega_degps")
    @classmethod
    def _in_range(cls, v, info):
        limit, unit = {"rho_m": (MAX_RANGE_M, "m"), "rho_dot_mps": (MAX_SPEED_MPS, "m/s"),
                       "omega_degps": (MAX_RATE_DEGPS, "deg/s")}[info.field_name]  # fmt: skip
        size = math.hypot(*v)  # no overflow warning for 1e308
        if size > limit:
            raise ValueError(f"magnitude {size:.3g} {unit} is beyond {limit:g} {unit}")
        return v

    @field_validator("q")
    @classmethod
    def _nonzero(cls, v):
        return _normalized(v, "quaternion")


class CameraConfig(_Model):
    baseline_m: Pos = 1.0
    focal_length: Pos = 1.0
    resolution_px: Annotated[list[Annotated[int, Field(gt=0)]], Field(min_length=2, max_length=2)] | None = Field(
        default=None,
        description="[W, H] of each camera's image in pixels; sets the pixel camera (docs/realism.md): features "
        "outside either image are not measured, and noise may be given in pixels",
    )
    fov_deg: Annotated[float, Field(gt=0, lt=180)] | None = Field(
        default=None, description="horizontal field of view (with resolution_px; or focal_length_px)"
    )
    focal_length_px: Pos | None = Field(default=None, description="focal length in pixels (with resolution_px)")
    principal_point_px: Annotated[list[float], Field(min_length=2, max_length=2)] | None = Field(
        default=None, description="[c_x, c_y] in pixels; default the image centre [W/2, H/2]"
    )

    @model_validator(mode="after")
    def _pixel_camera(self):
        px = (self.fov_deg, self.focal_length_px, self.principal_point_px)
        if self.resolution_px is None:
            if any(v is not None for v in px):
                raise ValueError("fov_deg, focal_length_px and principal_point_px need resolution_px")
            return self
        if (self.fov_deg is None) == (self.focal_length_px is None):
            raise ValueError("with resolution_px give exactly one of fov_deg or focal_length_px")
        if self.focal_length != 1.0:
            raise ValueError("focal_length (normalized-image scale) must stay 1 with a pixel camera (resolution_px)")
        return self


class PseudoMeasurementConfig(_Model):
    """Inertia pseudo-measurement; the angular-acceleration sources are in docs/angular-acceleration.md."""

    enabled: bool = True
    angular_acceleration_sigma_radps2: Pos = 1e-6
    angular_acceleration: Literal["truth_plus_noise", "savitzky_golay", "tikhonov", "tracking_differentiator"] = (
        "truth_plus_noise"
    )
    window: Annotated[int, Field(ge=3, le=1001)] = Field(
        default=9,
        description="Samples of the filter's own omega estimates the differentiators use (the newest ending at the "
        "sample where alpha is needed); the pseudo rows are skipped until that many exist. For the tracking "
        "differentiator (which uses every sample): its warm-up.",
    )
    polyorder: Annotated[int, Field(ge=1)] = Field(
        default=2, description="savitzky_golay: degree p of the local least-squares polynomial (1 <= p < window)."
    )
    tikhonov_lambda: Pos = Field(
        default=100.0,
        description="tikhonov: dimensionless regularization weight lam in ‖A s − (w − w_0)‖² + lam ‖D s‖² "
        "(s = alpha dt).",
    )
    tikhonov_order: Literal[1, 2] = Field(
        default=2, description="tikhonov: order of the difference operator D (exact for polynomials of this degree)."
    )
    td_r_radps3: Pos = Field(
        default=0.05,
        description="tracking_differentiator: Han's speed factor r, the bound on the rate of change of the "
        "differentiator's alpha; keep r h0² above the largest expected jump of the omega estimate (linear zone).",
    )
    td_h0_steps: Annotated[float, Field(ge=1.0, le=1000.0)] = Field(
        default=1.5,
        description="tracking_differentiator: Han's filtering factor h0 in time steps (h0 = td_h0_steps dt_s).",
    )
    sigma_floor_radps2: Pos = Field(
        default=1e-9,
        description="Differentiated sources: lower bound on the pseudo-measurement standard deviation the filter uses.",
    )

    @model_validator(mode="after")
    def _differentiator_options(self):
        if self.polyorder >= self.window:
            raise ValueError(f"polyorder ({self.polyorder}) must be less than window ({self.window})")
        if self.angular_acceleration == "tikhonov" and self.window < self.tikhonov_order + 2:
            raise ValueError(f"tikhonov needs window >= tikhonov_order + 2 = {self.tikhonov_order + 2}")
        return self


class OutlierConfig(_Model):
    """Wrong correspondences of the feature tracker (docs/realism.md)."""

    probability: Annotated[float, Field(ge=0, le=1)] = Field(description="per feature and step")
    model: Literal["uniform_image", "swapped_feature"] = Field(
        default="uniform_image",
        description="uniform_image: a spurious static point anywhere in the image (both cameras, same row); "
        "swapped_feature: the measurement of another feature of the target",
    )


class IlluminationConfig(_Model):
    sun_direction_lvlh: Vec3 = Field(description="direction toward the Sun in the leader's LVLH frame (normalized)")

    @field_validator("sun_direction_lvlh")
    @classmethod
    def _unit(cls, v):
        return _normalized(v, "sun_direction_lvlh")


DETECTORS = ("gftt", "fast", "orb", "sift")  # sim/tracker/klt.py DETECTORS


class ImageSensorConfig(_Model):
    """The image sensor (sim/render/sensor.py ``SensorModel``)."""

    exposure: Annotated[float, Field(gt=0, le=10)] = Field(
        default=0.8, description="fraction of the full well a white surface facing the Sun fills")
    full_well_e: Pos = Field(default=20000.0, description="full-well capacity (electrons)")
    read_noise_e: NonNeg = Field(default=10.0, description="read noise (electrons, standard deviation)")
    bits: Annotated[int, Field(ge=1, le=16)] = Field(default=8, description="digitization depth")
    defocus_sigma_px: NonNeg = Field(default=0.0, description="Gaussian defocus blur (px, standard deviation)")


class PanelsConfig(_Model):
    """Two solar-panel wings beside the body (sim/render/scene.py ``Panels``)."""

    span_m: Pos = 3.0
    width_m: Pos = 1.0
    thickness_m: Pos = 0.03
    gap_m: NonNeg = 0.15
    axis: Annotated[int, Field(ge=0, le=2)] = 0
    normal_axis: Annotated[int, Field(ge=0, le=2)] = 2

    @model_validator(mode="after")
    def _axes(self):
        if self.axis == self.normal_axis:
            raise ValueError(f"normal_axis ({self.normal_axis}) must differ from axis ({self.axis})")
        return self


class TrackerConfig(_Model):
    """The feature tracker's settings (sim/tracker/klt.py ``TrackerSettings``)."""

    max_tracks: Annotated[int, Field(ge=1, le=10000)] = Field(default=150, description="live tracks at most")
    min_tracks: Annotated[int, Field(ge=0)] = Field(default=80, description="re-detect below this many live tracks")
    min_distance_px: Pos = Field(default=8.0, description="spacing of new features (px)")
    window_px: Annotated[int, Field(ge=5, le=101)] = Field(default=21, description="KLT window (px, odd)")
    levels: Annotated[int, Field(ge=0, le=8)] = Field(default=3, description="pyramid levels above the image")
    fb_max_px: Pos = Field(default=0.5, description="temporal forward-backward round trip at most (px)")
    lr_max_px: Pos = Field(default=0.5, description="stereo left-right round trip at most (px)")
    row_max_px: Pos = Field(default=0.5, description="right-left row difference at most (px)")
    min_ncc: Annotated[float, Field(gt=0, le=1)] = Field(
        default=0.85, description="a track ends when its window correlates less with its detection window")
    detect_ncc: Annotated[float, Field(gt=0, le=1)] = Field(
        default=0.9, description="stereo-match correlation a new track needs")
    border_px: Annotated[int, Field(ge=0)] = Field(default=16, description="no features closer to the image border")

    @model_validator(mode="after")
    def _consistent(self):
        if self.window_px % 2 == 0:
            raise ValueError(f"window_px ({self.window_px}) must be odd")
        if self.min_tracks > self.max_tracks:
            raise ValueError(f"min_tracks ({self.min_tracks}) must not exceed max_tracks ({self.max_tracks})")
        return self


class TextureFileConfig(_Model):
    """A texture read from an image file (sim/render/texture.py ``file_atlas``, docs/images.md)."""

    file: Annotated[str, Field(min_length=1)] = Field(
        description="grayscale albedo image (PNG, JPEG, ...; colour is converted to luma, 0..255 -> 0..1); a "
        "relative path is taken from the scenario file's folder")
    size_m: tuple[Pos, Pos] = Field(description="[w, h]: the tile's width (image columns) and height (rows) in m")


BACKGROUNDS = ("black", "earth")


class ImagesConfig(_Model):
    """Rendered stereo images and the feature tracker (``measurements.source: images``, docs/images.md)."""

    detector: Literal[DETECTORS] = Field(default="gftt", description="feature detector of the tracker")
    sensor: ImageSensorConfig = ImageSensorConfig()
    panels: PanelsConfig | None = Field(
        default=None,
        description="solar-panel wings beside the body: false or null (none), true (the default wings) or `{span_m, "
        "width_m, thickness_m, gap_m, axis, normal_axis}` (docs/images.md)",
    )
    texture: TextureFileConfig | None = Field(
        default=None, description="null: the seeded procedural texture; `{file, size_m: [w, h]}`: an image file's "
        "albedo, a w x h m tile repeated over every surface (docs/images.md)")
    background: Literal[BACKGROUNDS] = Field(
        default="black", description="black, or earth: the sunlit Earth sphere behind the target where it is in view")
    supersample: Annotated[int, Field(ge=1, le=8)] = Field(default=1, description="rays per pixel along each axis")
    ambient: Annotated[float, Field(ge=0, le=1)] = Field(
        default=0.0, description="diffuse light from everywhere, a fraction of the Sun's")
    cache: bool = Field(
        default=True,
        description="keep the rendered radiance of a shared truth on disk (keyed by the poses, camera, target, "
        "panels, texture, Sun, background and render settings) and reuse it",
    )
    tracker: TrackerConfig = TrackerConfig()

    @field_validator("panels", mode="before")
    @classmethod
    def _panels_switch(cls, v):
        """``true``: the default wings; ``false``: none (so a wrong mapping is reported by its keys)."""
        if isinstance(v, bool):
            return {} if v else None
        return v


class TracksConfig(_Model):
    """The user's own tracks (``measurements.source: tracks``, docs/images.md "Your own tracks")."""

    file: Annotated[str, Field(min_length=1)] = Field(
        description="track table (Parquet or CSV); a relative path is taken from the scenario file's folder")
    truth_file: Annotated[str, Field(min_length=1)] | None = Field(
        default=None, description="optional true state per step (Parquet or CSV), same folder rule")


MEASUREMENT_SOURCES = ("model", "images", "tracks")


class MeasurementsConfig(_Model):
    source: Literal[MEASUREMENT_SOURCES] = Field(
        default="model",
        description="model: the point model (N fixed points, Gaussian noise); images: rendered stereo images and "
        "the feature tracker; tracks: a file of your own tracks (docs/images.md)",
    )
    images: ImagesConfig = ImagesConfig()
    tracks: TracksConfig | None = Field(
        default=None, description="`{file, truth_file}` of source tracks (docs/images.md, Your own tracks)"
    )
    image_sigma: NonNeg = 1e-5
    flow_sigma: NonNeg = 1e-5
    disparity: bool = False
    disparity_sigma: NonNeg | None = Field(
        default=None, description="noise of the disparity channel; default sqrt(2) image_sigma"
    )
    inertia_pseudo_measurement: PseudoMeasurementConfig = PseudoMeasurementConfig()
    image_sigma_px: NonNeg | None = Field(
        default=None, description="image noise in pixels (needs camera.resolution_px); replaces image_sigma"
    )
    flow_sigma_pxps: NonNeg | None = Field(
        default=None, description="image-velocity noise in px/s (needs camera.resolution_px); replaces flow_sigma"
    )
    dropout_probability: Annotated[float, Field(ge=0, lt=1)] = Field(
        default=0.0, description="probability that the tracker loses a feature at a step (per feature and step)"
    )
    occlusion: bool = Field(
        default=False,
        description="with target.shape: a feature is measured only when its surface faces both cameras and no part of "
        "the body is in between (ray test)",
    )
    illumination: IlluminationConfig | None = Field(
        default=None, description="`{sun_direction_lvlh: [x, y, z]}` (needs target.shape): unlit features are not seen"
    )
    outliers: OutlierConfig | None = Field(
        default=None,
        description="tracker outliers `{probability: p, model: uniform_image | swapped_feature}` (per feature and "
        "step; model default uniform_image); see docs/realism.md",
    )

    @model_validator(mode="after")
    def _source_keys(self):
        # each message starts with the key that is set: the loader reports that key's line
        if self.source == "tracks" and self.tracks is None:
            raise ValueError("source tracks needs tracks: {file: ...}")
        if self.images != ImagesConfig() and self.source != "images":  # the defaults: a dumped scenario reloads
            raise ValueError(f"images needs source: images (source is {self.source})")
        if self.tracks is not None and self.source != "tracks":
            raise ValueError(f"tracks needs source: tracks (source is {self.source})")
        if self.source != "model":
            for key, on in (("dropout_probability", self.dropout_probability > 0), ("outliers", self.outliers),
                            ("occlusion", self.occlusion)):  # fmt: skip
                if on:
                    raise ValueError(f"{key} is a point-model effect; with source: {self.source} the tracker (or your "
                                     "file) decides what is measured")
        return self

    @property
    def disparity_sigma_value(self) -> float:
        return self.disparity_sigma if self.disparity_sigma is not None else float(np.sqrt(2.0)) * self.image_sigma


class CovarianceConfig(_Model):
    """Diagonal variances per state block."""

    rho_m2: NonNeg
    rho_dot_m2ps2: NonNeg
    omega_deg2ps2: NonNeg
    q: NonNeg
    feature_points_m2: NonNeg
    k: NonNeg


class DivergenceConfig(_Model):
    """When a trial is lost (the filter's own tests: it stops) or inconsistent (truth-based bounds: a flag only)."""

    rho_m: Pos = 1000.0
    rho_dot_mps: Pos = 100.0
    omega_degps: Pos = 180.0
    k: Pos = 20.0
    nis_ratio: Pos = Field(
        default=100.0,
        description="a trial is lost when its NIS averaged over nis_window_steps exceeds nis_ratio times its "
        "expected value (the measurement dimension), from nis_start_s on",
    )
    nis_window_steps: Annotated[int, Field(ge=1)] = 10
    nis_start_s: NonNeg = 10.0
    gated_fraction: Annotated[float, Field(gt=0, le=1)] = Field(
        default=0.5,
        description="a gated filter is lost when, from nis_start_s on, its gate rejected at least this fraction of "
        "the features it was given at each of nis_window_steps steps",
    )
    sigma_ratio: Pos = Field(
        default=30.0,
        description="a trial is 'inconsistent' when a block's error stays above sigma_ratio times the filter's own "
        "sigma for that block over nis_window_steps steps (docs/filters.md, Lost and inconsistent trials)",
    )
    nees_factor: Pos = Field(
        default=10.0,
        description="a trial is 'inconsistent' when its gauge-projected NEES stays above nees_factor times the "
        "chi-square 99.9% bound over nis_window_steps steps",
    )
    exclude_inconsistent: bool = Field(
        default=False,
        description="leave inconsistent trials out of the accuracy statistics as lost ones are (the report says so "
        "at the top); false: an inconsistent trial is a flag only, its errors count",
    )


class InitialEstimateConfig(_Model):
    """How the filters start (docs/filters.md, Initial estimate)."""

    method: Literal["truth_plus_noise", "measurements"] = Field(
        default="truth_plus_noise",
        description="truth_plus_noise: x0 ~ N(truth, P0) (the thesis); measurements: rho, rho_dot, omega and the "
        "feature points from the first stereo frame (triangulation and a rigid-body fit), q and k from the "
        "N(truth, P0) draw",
    )
    centre_of_mass_sigma_m: Pos = Field(
        default=1.0, description="measurements: standard deviation of the centre of mass about the points' centroid"
    )


class DragConfig(_Model):
    """Atmospheric drag on both spacecraft (exponential density, co-rotating atmosphere)."""

    density_model: Literal["exponential"] = "exponential"
    ballistic_coefficient_leader_kgpm2: Pos = Field(description="m / (C_D A) of the leader")
    ballistic_coefficient_target_kgpm2: Pos = Field(description="m / (C_D A) of the target")
    reference_density_kgpm3: Annotated[float, Field(gt=0, le=MAX_DENSITY_KGPM3)] = Field(
        default=3.614e-14, description="density at reference_altitude_km")
    reference_altitude_km: Annotated[float, Field(ge=0, le=MAX_A_KM)] = 700.0
    scale_height_km: Annotated[float, Field(ge=MIN_SCALE_HEIGHT_KM, le=MAX_A_KM)] = 88.667


class TruthModelConfig(_Model):
    """Model mismatch in the truth: the filters keep the Keplerian, torque-free model (docs/realism.md)."""

    j2: bool = Field(default=False, description="J2 on both spacecraft (propagated in the inertial frame)")
    drag: DragConfig | None = Field(
        default=None,
        description="`{density_model: exponential, ballistic_coefficient_leader_kgpm2, "
        "ballistic_coefficient_target_kgpm2}` (+ reference_density_kgpm3 = 3.614e-14, reference_altitude_km = 700, "
        "scale_height_km = 88.667); null = no drag",
    )
    gravity_gradient_torque: bool = Field(default=False, description="gravity-gradient torque on the target")


# ----------------------------------------------------------------- dispersions (issue 11)

Number = Annotated[float, Field(allow_inf_nan=False)]
Param = Union[Number, list[Number], list[list[Number]]]


class MagnitudeSpec(_Model):
    """The magnitude distribution of ``uniform_direction`` (a scalar draw)."""

    dist: Literal["normal", "truncnormal", "uniform", "lognormal", "choice"]
    mean: float = 0.0
    std: NonNeg | None = None
    low: float | None = None
    high: float | None = None
    sigma: NonNeg | None = None
    median: Pos = 1.0
    values: list[float] | None = None
    weights: list[NonNeg] | None = None


class DispersionSpec(_Model):
    """How trial j draws one scenario value (docs/scenarios.md, "Dispersions")."""

    dist: Literal["normal", "truncnormal", "uniform", "lognormal", "choice", "uniform_rotation", "uniform_direction"]
    mode: Literal["add", "scale", "replace"] | None = Field(
        default=None,
        description="add: nominal + draw (default for normal, truncnormal, uniform); scale: nominal x draw "
        "(default for lognormal); replace: the draw (default for choice, uniform_rotation, uniform_direction)",
    )
    applies_to: Literal["truth", "both"] = "truth"
    mean: Param = 0.0
    std: Param | None = None
    low: Param | None = None
    high: Param | None = None
    sigma: Param | None = None
    median: Param = 1.0
    values: Annotated[list[Param], Field(min_length=1)] | None = None
    weights: list[NonNeg] | None = None
    magnitude: MagnitudeSpec | Pos | None = None

    @model_validator(mode="after")
    def _parameters(self):
        need = {"normal": ("std",), "truncnormal": ("std", "low", "high"), "uniform": ("low", "high"),
                "lognormal": ("sigma",), "choice": ("values",), "uniform_direction": ("magnitude",)}  # fmt: skip
        missing = [k for k in need.get(self.dist, ()) if getattr(self, k) is None]
        if missing:
            raise ValueError(f"dist {self.dist} needs {', '.join(missing)}")
        if self.dist in ("uniform_rotation", "uniform_direction") and self.mode == "scale":
            raise ValueError(f"dist {self.dist} supports mode add or replace, not scale")
        if self.weights is not None and (self.values is None or len(self.weights) != len(self.values)):
            raise ValueError("weights needs one weight per entry of values")
        if self.weights is not None and sum(self.weights) <= 0:
            raise ValueError("weights must not all be zero")
        return self


class DispersionsConfig(BaseModel):
    """``dispersions:``: ``sampling`` plus one ``DispersionSpec`` per dotted scenario path."""

    model_config = ConfigDict(extra="allow", validate_default=True, allow_inf_nan=False)
    __pydantic_extra__: dict[str, DispersionSpec] = Field(init=False)

    sampling: Literal["random", "sobol", "lhs"] = Field(
        default="random", description="how the unit-cube coordinates of all dispersed scalars are drawn"
    )

    @property
    def specs(self) -> dict[str, DispersionSpec]:
        return dict(self.__pydantic_extra__ or {})


class Scenario(_Model):
    name: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")]
    description: str = ""
    seed: Annotated[int, Field(ge=0, le=MAX_SEED)]
    trials: Annotated[int, Field(ge=1)] = 100
    time: TimeConfig = TimeConfig()
    leader: LeaderConfig
    target: TargetConfig
    truth_initial_state: InitialStateConfig
    camera: CameraConfig = CameraConfig()
    measurements: MeasurementsConfig = MeasurementsConfig()
    initial_covariance: CovarianceConfig
    filters: Annotated[list[FilterConfig], Field(min_length=1)] = Field(
        default_factory=lambda: [IEKFConfig(type="iekf")]
    )
    percentiles: Annotated[list[Annotated[float, Field(ge=0, le=100)]], Field(min_length=1)] = [50, 70, 90, 100]
    divergence: DivergenceConfig = DivergenceConfig()
    truth_model: TruthModelConfig | None = Field(
        default=None,
        description="`{j2, drag, gravity_gradient_torque}`: the truth is propagated in the inertial frame with these "
        "and converted to the leader's LVLH; null = the thesis's Keplerian, torque-free relative model",
    )
    dispersions: DispersionsConfig | None = None
    initial_estimate: InitialEstimateConfig = InitialEstimateConfig()

    @model_validator(mode="after")
    def _pixel_noise_needs_pixels(self):
        m = self.measurements
        # each message starts with the key that is set: the loader reports that key's line
        if self.camera.resolution_px is None and (m.image_sigma_px is not None or m.flow_sigma_pxps is not None):
            key = "image_sigma_px" if m.image_sigma_px is not None else "flow_sigma_pxps"
            raise ValueError(f"measurements.{key} needs camera.resolution_px (a pixel camera)")
        slots = self.target.feature_slots is not None
        if m.source == "model" and slots:
            raise ValueError("target.feature_slots needs measurements.source images or tracks")
        if m.source != "model" and not slots:
            raise ValueError(f"measurements.source {m.source} needs target.feature_slots (the number of feature slots)")
        if m.source != "model" and self.camera.resolution_px is None:
            raise ValueError(f"measurements.source {m.source} needs camera.resolution_px (a pixel camera)")
        if m.source == "images" and self.target.shape is None:
            raise ValueError("measurements.source images needs target.shape (the body to render)")
        if m.source != "model":
            for f in self.filters:  # feature slots live in an error-state chart (filters/slots.py)
                if getattr(f, "error_state", "aligned") == "full":
                    raise ValueError(f"filter {f.label}: error_state full cannot hold feature slots (measurements."
                                     f"source {m.source}); use aligned (the default) or attitude")  # fmt: skip
            if self.initial_estimate.method == "measurements":
                raise ValueError(f"initial_estimate.method measurements needs the image velocities of the first frame, "
                                 f"which tracks do not have (measurements.source {m.source}): the slots are "
                                 f"initialized from their first stereo frame anyway")  # fmt: skip
            if m.source == "tracks" and self.dispersions is not None and self.dispersions.specs:
                raise ValueError("dispersions with measurements.source tracks: the tracks are given, they cannot "
                                 "follow a dispersed truth (use source images, which renders each trial's own)")
        if self.target.shape is None and (m.occlusion or m.illumination is not None):
            key = "occlusion" if m.occlusion else "illumination"
            raise ValueError(f"measurements.{key} needs target.shape")
        if self.camera.resolution_px is None:
            for f in self.filters:
                r = f.measurement_noise
                if r.image_sigma_px is not None or r.flow_sigma_pxps is not None:
                    raise ValueError(f"filter {f.label}: measurement_noise in pixels needs camera.resolution_px")
        if self.truth_model is not None and self.dispersions is not None and self.dispersions.specs:
            raise ValueError("dispersions with a perturbed truth_model are not supported yet: the dispersed "
                             "(batched) truth is the Keplerian relative model; drop one of the two")
        return self

    @field_validator("filters")
    @classmethod
    def _unique_labels(cls, v):
        labels = [f.label for f in v]
        if len(set(labels)) != len(labels):
            raise ValueError(f"filter labels must be unique (got {labels}); give each a 'name'")
        return v


def _rebuild_filters(union) -> None:
    """``Scenario.filters`` over the current filter types (``config.filters.register``)."""
    Scenario.model_fields["filters"].annotation = list[union]
    Scenario.model_rebuild(force=True)


_filters._REBUILD.append(_rebuild_filters)
