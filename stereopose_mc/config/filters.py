"""The filter entries of a scenario: one config model per filter type, and its SI setup.

Each filter type declares here, in one place, the keys of its ``filters:`` entry (a pydantic
model whose ``type`` tag is the discriminator of the scenario's union, with field
descriptions) and how they resolve to a plain frozen dataclass of SI parameters (the
model's ``setup`` method, from the fields every filter shares, ``config.resolve``). Its
numerics (steps, compiled steps, chart) are declared in ``filters/registry.py``, which a new
filter type joins with one entry (docs/filters.md, "Adding a filter").

``FILTER_CONFIGS`` lists the types in the union's order (the order of the tags in error
messages); ``register`` adds a type from outside the package (the filter registry calls it)
and rebuilds the scenario schema.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Literal, NamedTuple, Union

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, field_validator, model_serializer

from .base import NonNeg, Pos, _Model

Array = NDArray[np.float64]


class Iteration(NamedTuple):
    """The knobs of an iterated (Gauss-Newton) update (docs/filters.md, IEKF)."""

    tolerance: float
    max_iterations: int
    step_control: str
    stopping: str


# ``first_update: iterated`` of the EKF and the UKF: the IEKF's defaults
FIRST_ITERATED = Iteration(0.01, 10, "line_search", "mahalanobis")


@dataclass(frozen=True)
class FilterSetup:
    """What every filter type resolves to, in SI: R's standard deviations, Q's diagonal, the prediction."""

    label: str
    kind: str  # the entry's ``type`` (the key of its filters/registry.py entry)
    sigma_image: float
    sigma_flow: float
    sigma_disparity: float
    sigma_alpha: float
    Q_diag: Array
    transition: str
    taylor_order: int
    substeps: int
    gate_probability: float | None = None  # per-feature chi-square gate (filters/gating.py); None: no gate
    gate_inflate: bool = False  # the gate's covariance inflation when it would reject most features (gating.py)
    error_state: str = "full"  # "full" (additive, quaternion covariance) | "attitude" | "aligned" (docs/filters.md)
    second_order: bool = True  # the flow and pseudo rows' R, omega's Q add their linearization's variance (core)

    def iteration(self, first: bool) -> Iteration | None:
        """The Gauss-Newton knobs of an update (``first``: the update at ``t = dt``); None: the EKF update."""
        return None


@dataclass(frozen=True)
class EKFSetup(FilterSetup):
    first_update: str = "ekf"  # "iterated": the first update runs the IEKF's iterations

    def iteration(self, first: bool) -> Iteration | None:
        return FIRST_ITERATED if first and self.first_update == "iterated" else None


@dataclass(frozen=True)
class IEKFSetup(FilterSetup):
    tolerance: float = 0.01
    max_iterations: int = 10
    step_control: str = "line_search"
    stopping: str = "mahalanobis"

    def iteration(self, first: bool) -> Iteration | None:
        return Iteration(self.tolerance, self.max_iterations, self.step_control, self.stopping)


@dataclass(frozen=True)
class MEKFSetup(IEKFSetup):
    """``max_iterations`` 1: the MEKF's plain (not iterated) update; ``first_update`` as the EKF's."""

    first_update: str = "ekf"  # "iterated": the first update runs the IEKF's iterations

    def iteration(self, first: bool) -> Iteration | None:
        if self.max_iterations > 1:
            return super().iteration(first)
        return FIRST_ITERATED if first and self.first_update == "iterated" else None


@dataclass(frozen=True)
class UKFSetup(FilterSetup):
    alpha: float = 0.5  # sigma-point scaling (Merwe): alpha, beta, kappa
    beta: float = 2.0
    kappa: float = 0.0
    first_update: str = "ukf"  # "iterated": the first update is the error-state filter's iterated one

    def iteration(self, first: bool) -> Iteration | None:
        return FIRST_ITERATED if first and self.first_update == "iterated" else None


class FilterMeasurementNoise(_Model):
    """The filter's own R, per measurement type (standard deviations); default: the truth's."""

    image_sigma: Pos | None = None
    flow_sigma: Pos | None = None
    disparity_sigma: Pos | None = None
    angular_acceleration_sigma_radps2: Pos | None = None
    image_sigma_px: Pos | None = Field(default=None, description="σ for u, v in pixels (pixel camera); replaces image_sigma")
    flow_sigma_pxps: Pos | None = Field(
        default=None, description="σ for the image velocities in px/s (pixel camera); replaces flow_sigma"
    )


class ProcessNoiseConfig(_Model):
    """The filter's Q, variances added per step, per state block (derivation: docs/filters.md, Process noise)."""

    auto: bool = Field(
        default=False,
        description="add to the blocks (the defaults, or the values given beside it) the Q that covers the "
        "truth_model's unmodelled J2 and drag differential accelerations (rho, rho_dot) and gravity-gradient torque "
        "(omega); nothing without a truth_model (docs/filters.md, Process noise). `process_noise: auto` is short "
        "for `{auto: true}`",
    )
    rho_m2: NonNeg = 1e-8
    rho_dot_m2ps2: NonNeg = 1e-12
    omega_deg2ps2: NonNeg = 1e-10
    q: NonNeg = 3e-11
    feature_points_m2: NonNeg = 3e-10
    k: NonNeg = 1e-10

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        """Without ``auto`` the dump is the blocks alone, as before ``auto`` existed (run directories' scenario
        text and hashes)."""
        d = handler(self)
        if isinstance(d, dict) and not self.auto:
            d.pop("auto", None)
        return d


class GatingConfig(_Model):
    """Per-feature chi-square gate on the innovation before the update (docs/filters.md)."""

    probability: Annotated[float, Field(gt=0, lt=1)] = Field(
        default=0.999, description="probability that a correct feature passes the gate"
    )
    inflate: bool = Field(
        default=True,
        description="when the gate would reject at least half of a step's features, take it as the filter's "
        "overconfidence, not as that many outliers: scale the prior covariance by the innovations' robust "
        "(median) excess over chi-square and gate again (docs/filters.md, Gating)",
    )


class FilterBase(_Model):
    name: str | None = Field(default=None, description="label in outputs; default the type")
    gating: GatingConfig | None = Field(
        default=None,
        description="`{probability: 0.999}`: per-feature chi-square gate on the innovation before the update (the "
        "IEKF at its first iterate); null = no gate; not for the UKF, which has none. See docs/filters.md",
    )
    measurement_noise: FilterMeasurementNoise = FilterMeasurementNoise()
    process_noise: ProcessNoiseConfig = ProcessNoiseConfig()
    transition: Literal["expm", "taylor"] = "taylor"
    taylor_order: Annotated[int, Field(ge=1, le=12)] = 4
    integration_substeps: Annotated[int, Field(ge=1, le=1000)] = 1
    linearization: Literal["second_order", "first_order"] = Field(
        default="second_order",
        description="R of the rows whose model multiplies two uncertain blocks, and Q of the rate's dynamics: "
        "'second_order' adds the variance their linearization leaves out (the image velocities hold omega x points, "
        "the inertia pseudo-measurement and omega's dynamics omega^2 and k: large while those are uncertain); "
        "'first_order': the noise alone (the thesis). See docs/filters.md, Second-order R and Q")

    @field_validator("process_noise", mode="before")
    @classmethod
    def _auto(cls, v):
        if isinstance(v, str):
            if v != "auto":
                raise ValueError(f"must be 'auto' or a mapping of per-block variances (got {v!r})")
            return {"auto": True}
        return v

    @property
    def label(self) -> str:
        return self.name or self.type  # type: ignore[attr-defined]

    def setup(self, **common: Any) -> FilterSetup:
        """The SI setup of this entry from the fields every filter shares (``config.resolve.filter_setup_of``)."""
        return FilterSetup(**common)


_ERROR_STATE_DOC = (
    "the coordinates the filter's covariance and iterations live in (docs/filters.md, Error state): 'aligned' "
    "(centroid of the points in L, body-frame rotation, points in the rotated body frame: the near-symmetries are "
    "straight lines, so the filter stays consistent), 'attitude' (3-parameter attitude error in L, additive "
    "elsewhere) or 'full' (the thesis: additive on the whole state, quaternion covariance)"
)


class EKFConfig(FilterBase):
    type: Literal["ekf"]
    error_state: Literal["aligned", "full", "attitude"] = Field(default="aligned", description=_ERROR_STATE_DOC)
    first_update: Literal["ekf", "iterated"] = Field(
        default="ekf",
        description="'iterated': the first update (t = dt) runs the IEKF's iterations (line search, Mahalanobis "
        "stopping, tolerance 0.01, at most 10), the later ones are plain EKF updates",
    )

    def setup(self, **common: Any) -> EKFSetup:
        return EKFSetup(**common, first_update=self.first_update)


class _GaussNewtonBase(FilterBase):
    """The iterated update's knobs (docs/filters.md, IEKF)."""

    tolerance: Pos = 0.01
    max_iterations: Annotated[int, Field(ge=1, le=1000)] = 10
    step_control: Literal["line_search", "levenberg_marquardt", "none"] = "line_search"
    stopping: Literal["mahalanobis", "prior", "scaled", "raw"] = "mahalanobis"


class IEKFConfig(_GaussNewtonBase):
    type: Literal["iekf"]
    error_state: Literal["aligned", "full", "attitude"] = Field(default="aligned", description=_ERROR_STATE_DOC)

    def setup(self, **common: Any) -> IEKFSetup:
        return IEKFSetup(**common, tolerance=self.tolerance, max_iterations=self.max_iterations,
                         step_control=self.step_control, stopping=self.stopping)  # fmt: skip


class MEKFConfig(_GaussNewtonBase):
    """Multiplicative EKF (docs/filters.md): error-state covariance, 3-parameter attitude error, a plain (not
    iterated) update: the filter a GNC engineer calls the MEKF. ``error_state: aligned`` and ``iterated: true`` are
    options (with both it is the default IEKF)."""

    type: Literal["mekf"]
    error_state: Literal["aligned", "attitude"] = Field(default="attitude", description=_ERROR_STATE_DOC)
    iterated: bool = Field(default=False, description="run the IEKF's Gauss-Newton iterations in the update")
    first_update: Literal["ekf", "iterated"] = Field(
        default="ekf",
        description="'iterated': the first update (t = dt) runs the IEKF's iterations (line search, Mahalanobis "
        "stopping, tolerance 0.01, at most 10), the later ones are plain MEKF updates (with `iterated: true` every "
        "update is iterated already)",
    )

    def setup(self, **common: Any) -> MEKFSetup:
        return MEKFSetup(**common, tolerance=self.tolerance, max_iterations=self.max_iterations if self.iterated else 1,
                         step_control=self.step_control, stopping=self.stopping,
                         first_update=self.first_update)  # fmt: skip


class UKFConfig(FilterBase):
    """Unscented filter with multiplicative attitude (docs/filters.md); scaled sigma points (Merwe)."""

    type: Literal["ukf"]
    error_state: Literal["aligned", "attitude"] = Field(default="aligned", description=_ERROR_STATE_DOC)
    alpha: Annotated[float, Field(gt=0, le=1)] = 0.5
    beta: NonNeg = 2.0
    kappa: float = 0.0
    first_update: Literal["ukf", "iterated"] = Field(
        default="ukf",
        description="'iterated': the first update (t = dt) is the MEKF's iterated update (line search, Mahalanobis "
        "stopping, tolerance 0.01, at most 10 iterations), the later ones unscented",
    )

    @field_validator("gating")
    @classmethod
    def _no_gate(cls, v):
        if v is not None:  # it used to be accepted and ignored
            raise ValueError("the UKF has no innovation gate (its update is unscented); remove 'gating', or use "
                             "type iekf, ekf or mekf for a gated filter")  # fmt: skip
        return v

    def setup(self, **common: Any) -> UKFSetup:
        # its sigma points see the products of uncertain blocks themselves: no second-order R
        common = {**common, "second_order": False}
        return UKFSetup(**common, alpha=self.alpha, beta=self.beta, kappa=self.kappa, first_update=self.first_update)






#: The filter types, in the order of the scenario union (and of the tags in its error messages).
FILTER_CONFIGS: list[type[FilterBase]] = [IEKFConfig, EKFConfig, MEKFConfig, UKFConfig]


def tag(model: type[FilterBase]) -> str:
    """The ``type`` tag of a filter's config model."""
    return model.model_fields["type"].annotation.__args__[0]


def filter_union() -> Any:
    """The discriminated union of the filter entries (``Scenario.filters``' item type)."""
    return Annotated[Union[tuple(FILTER_CONFIGS)], Field(discriminator="type")]


FilterConfig = filter_union()
_REBUILD: list = []  # the schema's rebuild hook (config.schema: Scenario with the current union)


def register(model: type[FilterBase]) -> None:
    """Add a filter type's config model to the scenario schema (an entry of ``filters/registry.py`` from outside
    the package); the same model again is a no-op, another model under a known tag an error."""
    known = {tag(m): m for m in FILTER_CONFIGS}
    if known.get(tag(model)) is model:
        return
    if tag(model) in known:
        raise ValueError(f"filter type {tag(model)!r} is already registered")
    FILTER_CONFIGS.append(model)
    _rebuild()


def unregister(name: str) -> None:
    """Remove a registered filter type from the scenario schema (tests)."""
    FILTER_CONFIGS[:] = [m for m in FILTER_CONFIGS if tag(m) != name]
    _rebuild()


def _rebuild() -> None:
    global FilterConfig
    FilterConfig = filter_union()
    for hook in _REBUILD:
        hook(FilterConfig)
