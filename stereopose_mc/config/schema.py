"""The scenario schema (the public contract of a scenario YAML file).

Units follow the key names: ``_km``, ``_m``, ``_deg``, ``_degps`` (deg/s), ``_m2``
(variances), ``_deg2ps2`` (deg^2/s^2). Everything is converted to SI (m, s, rad) by
``stereopose_mc.config.resolve``; the numerical core never sees degrees.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

SCHEMA_VERSION = 1

Pos = Annotated[float, Field(gt=0)]
NonNeg = Annotated[float, Field(ge=0)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_default=True, allow_inf_nan=False)


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
    a_km: Pos
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


class TargetConfig(_Model):
    inertia_kgm2: Annotated[list[Pos], Field(min_length=3, max_length=3)] = Field(
        description="principal moments Ix, Iy, Iz (kg m^2); only their ratios matter torque-free"
    )
    feature_points_m: Annotated[list[Vec3], Field(min_length=1)]

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

    @field_validator("q")
    @classmethod
    def _nonzero(cls, v):
        n = float(np.linalg.norm(v))
        if not np.isfinite(n) or n < 1e-12:
            raise ValueError("quaternion must be non-zero")
        return [float(c) / n for c in v]


class CameraConfig(_Model):
    baseline_m: Pos = 1.0
    focal_length: Pos = 1.0


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


class MeasurementsConfig(_Model):
    image_sigma: NonNeg = 1e-5
    flow_sigma: NonNeg = 1e-5
    disparity: bool = False
    disparity_sigma: NonNeg | None = Field(
        default=None, description="noise of the disparity channel; default sqrt(2) image_sigma"
    )
    inertia_pseudo_measurement: PseudoMeasurementConfig = PseudoMeasurementConfig()

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


class FilterMeasurementNoise(_Model):
    """The filter's own R, per measurement type (standard deviations); default: the truth's."""

    image_sigma: Pos | None = None
    flow_sigma: Pos | None = None
    disparity_sigma: Pos | None = None
    angular_acceleration_sigma_radps2: Pos | None = None


class ProcessNoiseConfig(_Model):
    """The filter's Q, variances added per step, per state block (derivation: docs/filters.md, Process noise)."""

    rho_m2: NonNeg = 1e-5
    rho_dot_m2ps2: NonNeg = 1e-12
    omega_deg2ps2: NonNeg = 1e-10
    q: NonNeg = 3e-11
    feature_points_m2: NonNeg = 3e-9
    k: NonNeg = 1e-10


class _FilterBase(_Model):
    name: str | None = Field(default=None, description="label in outputs; default the type")
    measurement_noise: FilterMeasurementNoise = FilterMeasurementNoise()
    process_noise: ProcessNoiseConfig = ProcessNoiseConfig()
    transition: Literal["expm", "taylor"] = "taylor"
    taylor_order: Annotated[int, Field(ge=1, le=12)] = 4
    integration_substeps: Annotated[int, Field(ge=1, le=1000)] = 1

    @property
    def label(self) -> str:
        return self.name or self.type  # type: ignore[attr-defined]


class EKFConfig(_FilterBase):
    type: Literal["ekf"]
    first_update: Literal["ekf", "iterated"] = Field(
        default="ekf",
        description="'iterated': the first update (t = dt) runs the IEKF's iterations (line search, Mahalanobis "
        "stopping, tolerance 0.01, at most 10), the later ones are plain EKF updates",
    )


class _GaussNewtonBase(_FilterBase):
    """The iterated update's knobs (docs/filters.md, IEKF)."""

    tolerance: Pos = 0.01
    max_iterations: Annotated[int, Field(ge=1, le=1000)] = 10
    step_control: Literal["line_search", "levenberg_marquardt", "none"] = "line_search"
    stopping: Literal["mahalanobis", "prior", "scaled", "raw"] = "mahalanobis"


class IEKFConfig(_GaussNewtonBase):
    type: Literal["iekf"]


class MEKFConfig(_GaussNewtonBase):
    """Multiplicative EKF (docs/filters.md): error-state covariance, 3-parameter attitude error."""

    type: Literal["mekf"]
    iterated: bool = Field(default=True, description="run the IEKF's Gauss-Newton iterations in the update")


class UKFConfig(_FilterBase):
    """Unscented filter with multiplicative attitude (docs/filters.md); scaled sigma points (Merwe)."""

    type: Literal["ukf"]
    alpha: Annotated[float, Field(gt=0, le=1)] = 0.5
    beta: NonNeg = 2.0
    kappa: float = 0.0
    first_update: Literal["ukf", "iterated"] = Field(
        default="ukf",
        description="'iterated': the first update (t = dt) is the MEKF's iterated update (line search, Mahalanobis "
        "stopping, tolerance 0.01, at most 10 iterations), the later ones unscented",
    )


FilterConfig = Annotated[Union[IEKFConfig, EKFConfig, MEKFConfig, UKFConfig], Field(discriminator="type")]


class DivergenceConfig(_Model):
    """Bounds on the estimation error beyond which a trial is marked diverged."""

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
    sigma_ratio: Pos = Field(
        default=30.0,
        description="a trial is 'inconsistent' when a block's error stays above sigma_ratio times the filter's own "
        "sigma for that block over nis_window_steps steps (docs/filters.md, Divergence)",
    )
    nees_factor: Pos = Field(
        default=1000.0,
        description="a trial is 'inconsistent' when its gauge-projected NEES stays above nees_factor times the "
        "chi-square 99.9% bound over nis_window_steps steps",
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


class Scenario(_Model):
    name: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")]
    description: str = ""
    seed: Annotated[int, Field(ge=0)]
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
    initial_estimate: InitialEstimateConfig = InitialEstimateConfig()

    @field_validator("filters")
    @classmethod
    def _unique_labels(cls, v):
        labels = [f.label for f in v]
        if len(set(labels)) != len(labels):
            raise ValueError(f"filter labels must be unique (got {labels}); give each a 'name'")
        return v
