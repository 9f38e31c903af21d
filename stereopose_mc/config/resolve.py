"""Scenario -> plain SI numbers for the simulator and the filters."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..core import state as st
from ..core.orbit import Orbit
from ..core.perturbed import Perturbations
from ..core.unmodelled import Unmodelled, bias_as_white_variance, unmodelled, white_acceleration
from .sensor import SensorSetup, feature_points_of, sensor_of, truth_sigmas
from .filters import FilterBase, FilterSetup
from .schema import CovarianceConfig, ProcessNoiseConfig, PseudoMeasurementConfig, Scenario

DEG = np.pi / 180.0
Array = NDArray[np.float64]


@dataclass(frozen=True)
class Setup:
    """Everything numeric a scenario fixes, in SI units."""

    orbit: Orbit
    x0: Array  # true initial state (n,)
    dt: float
    steps: int  # number of steps after t = 0
    window_start: float
    baseline: float
    focal: float
    disparity: bool
    pseudo: bool
    sigma_image: float
    sigma_flow: float
    sigma_disparity: float
    sigma_alpha: float
    P0_diag: Array
    truth_rtol: float
    # angular-acceleration source of the pseudo-measurement (docs/angular-acceleration.md)
    alpha_method: str = "truth_plus_noise"
    alpha_window: int = 9
    alpha_polyorder: int = 2
    alpha_tikhonov_lambda: float = 100.0
    alpha_tikhonov_order: int = 2
    alpha_td_r: float = 0.05  # rad/s^3
    alpha_td_h0: float = 1.5  # s
    alpha_sigma_floor: float = 1e-9  # rad/s^2
    sensor: SensorSetup = SensorSetup()  # pixel camera, tracker faults (config/sensor.py)
    perturbations: Perturbations | None = None  # perturbed truth (core/perturbed.py); None: Keplerian relative model
    initial_estimate: str = "truth_plus_noise"  # or "measurements" (filters/initialization.py)
    com_sigma: float = 1.0  # m, centre of mass about the points' centroid (measurements start)

    @property
    def n_points(self) -> int:
        return st.n_points(self.x0.size)

    @property
    def times(self) -> Array:
        return self.dt * np.arange(self.steps + 1)


def orbit_of(s: Scenario) -> Orbit:
    o = s.leader.orbit
    return Orbit(
        a=o.a_km * 1e3, e=o.e, i=o.i_deg * DEG, raan=o.raan_deg * DEG, argp=o.argp_deg * DEG, nu0=o.true_anomaly_deg * DEG
    )


def block_diag(c: CovarianceConfig | ProcessNoiseConfig, n_points: int) -> Array:
    """Diagonal (n,) of a per-block covariance given in the scenario's units."""
    d = np.empty(st.size(n_points))
    b = st.block_index(n_points)
    d[b["rho"]] = c.rho_m2
    d[b["rho_dot"]] = c.rho_dot_m2ps2
    d[b["omega"]] = c.omega_deg2ps2 * DEG**2
    d[b["q"]] = c.q
    d[b["feature_points"]] = c.feature_points_m2
    d[b["k"]] = c.k
    return d


def setup_of(s: Scenario) -> Setup:
    ti = s.truth_initial_state
    sensor = sensor_of(s)
    pts = feature_points_of(s, sensor.shape)[0]
    k = st.k_from_inertia(np.asarray(s.target.inertia_kgm2, dtype=float))
    x0 = st.assemble(ti.rho_m, ti.rho_dot_mps, np.asarray(ti.omega_degps) * DEG, ti.q, pts, k)
    m = s.measurements
    return Setup(
        orbit=orbit_of(s),
        x0=x0,
        dt=s.time.dt_s,
        steps=int(round(s.time.duration_s / s.time.dt_s)),
        window_start=s.time.error_window_start_s,
        baseline=s.camera.baseline_m,
        focal=s.camera.focal_length,
        disparity=m.disparity,
        pseudo=m.inertia_pseudo_measurement.enabled,
        sigma_image=truth_sigmas(s)[0],
        sigma_flow=truth_sigmas(s)[1],
        sigma_disparity=m.disparity_sigma_value if m.image_sigma_px is None or m.disparity_sigma is not None
        else float(np.sqrt(2.0)) * truth_sigmas(s)[0],
        sigma_alpha=m.inertia_pseudo_measurement.angular_acceleration_sigma_radps2,
        P0_diag=block_diag(s.initial_covariance, len(pts)),
        truth_rtol=s.time.truth_rtol,
        **_alpha_options(m.inertia_pseudo_measurement, s.time.dt_s),
        sensor=sensor,
        perturbations=perturbations_of(s),
        initial_estimate=s.initial_estimate.method,
        com_sigma=s.initial_estimate.centre_of_mass_sigma_m,
    )


def perturbations_of(s: Scenario) -> Perturbations | None:
    """The scenario's ``truth_model`` in SI (None without one)."""
    tm = s.truth_model
    if tm is None:
        return None
    d = tm.drag
    extra = {} if d is None else dict(
        drag=True, ballistic_leader=d.ballistic_coefficient_leader_kgpm2,
        ballistic_target=d.ballistic_coefficient_target_kgpm2, density_ref=d.reference_density_kgpm3,
        altitude_ref=d.reference_altitude_km * 1e3, scale_height=d.scale_height_km * 1e3,
    )  # fmt: skip
    return Perturbations(j2=tm.j2, gravity_gradient=tm.gravity_gradient_torque, **extra)


def _alpha_options(p: PseudoMeasurementConfig, dt: float) -> dict:
    """The ``alpha_*`` fields of ``Setup`` (SI; ``h0 = td_h0_steps dt``)."""
    return dict(
        alpha_method=p.angular_acceleration,
        alpha_window=p.window,
        alpha_polyorder=p.polyorder,
        alpha_tikhonov_lambda=p.tikhonov_lambda,
        alpha_tikhonov_order=p.tikhonov_order,
        alpha_td_r=p.td_r_radps3,
        alpha_td_h0=p.td_h0_steps * dt,
        alpha_sigma_floor=p.sigma_floor_radps2,
    )


def filter_setup_of(f: FilterBase, s: Setup) -> FilterSetup:
    """A filter entry in SI: the fields every filter shares, resolved here, and its type's own (the config
    model's ``setup``, config/filters.py)."""
    r = f.measurement_noise
    if s.sensor.pixels is not None:  # noise given in pixels -> normalized units (config/sensor.py)
        px = {"image_sigma": r.image_sigma_px, "flow_sigma": r.flow_sigma_pxps}
        r = r.model_copy(update={k: v / s.sensor.pixels.f_px for k, v in px.items() if v is not None})
    return f.setup(
        label=f.label,
        kind=f.type,
        sigma_image=r.image_sigma if r.image_sigma is not None else s.sigma_image,
        sigma_flow=r.flow_sigma if r.flow_sigma is not None else s.sigma_flow,
        sigma_disparity=r.disparity_sigma if r.disparity_sigma is not None else s.sigma_disparity,
        sigma_alpha=math.sqrt((r.angular_acceleration_sigma_radps2 if r.angular_acceleration_sigma_radps2 is not None
                               else s.sigma_alpha) ** 2 + pseudo_unmodelled_var(f.process_noise, s)),  # fmt: skip
        Q_diag=block_diag(process_noise_of(f.process_noise, s), s.n_points),
        transition=f.transition,
        taylor_order=f.taylor_order,
        substeps=f.integration_substeps,
        gate_probability=None if f.gating is None else f.gating.probability,
        gate_inflate=f.gating is not None and f.gating.inflate,
        error_state=f.error_state,
        second_order=f.linearization == "second_order",
    )


def unmodelled_of(s: Setup) -> Unmodelled:
    """Bounds on the truth's unmodelled accelerations (core/unmodelled.py) over the scenario: the separation
    ``|rho_0| + |rho_dot_0| T`` at most, the target's moments from its ratios ``k``."""
    x0 = s.x0
    rho_dot = float(np.linalg.norm(x0[st.RHO_DOT]))
    rho = float(np.linalg.norm(x0[st.RHO])) + rho_dot * s.steps * s.dt
    k = x0[st.block_index(s.n_points)["k"]]
    moments = np.exp([k[0] + k[1], k[1], 0.0])  # Ix : Iy : Iz from k = [ln(Ix/Iy), ln(Iy/Iz)]
    o = s.orbit
    return unmodelled(s.perturbations, o.a, o.e, o.i, rho, rho_dot, moments)


def process_noise_of(c: ProcessNoiseConfig, s: Setup) -> ProcessNoiseConfig:
    """The filter's Q per block in the scenario's units: ``c`` itself, or with ``auto`` its blocks (the defaults or
    the values given beside ``auto``) plus what covers the unmodelled accelerations on ``rho``, ``rho_dot`` and
    ``omega`` (``white_acceleration`` of ``unmodelled_of``; docs/filters.md, Process noise)."""
    if not c.auto:
        return c
    u = unmodelled_of(s)
    q_rho, q_rho_dot = white_acceleration(u.acceleration, s.dt)
    q_omega = white_acceleration(u.gravity_gradient, s.dt)[1] / DEG**2
    return c.model_copy(update={"auto": False, "rho_m2": c.rho_m2 + q_rho, "rho_dot_m2ps2": c.rho_dot_m2ps2 + q_rho_dot,
                                "omega_deg2ps2": c.omega_deg2ps2 + q_omega})  # fmt: skip


def pseudo_unmodelled_var(c: ProcessNoiseConfig, s: Setup) -> float:
    """What ``process_noise: auto`` adds to the variance of the pseudo rows (rad^2/s^4): they compare a measured
    angular acceleration, which carries the truth's gravity-gradient torque, with the filter's torque-free
    ``omega_dot(omega, k)``. Over the short runs of a scenario that torque is nearly constant, a bias of norm at most
    ``u.gravity_gradient`` in every row, which the filter averages over the run's ``steps`` rows
    (``core.unmodelled.bias_as_white_variance``). Zero without ``auto``, without the pseudo rows or without the
    torque in the truth (docs/filters.md, Process noise ``auto``)."""
    if not (c.auto and s.pseudo):
        return 0.0
    return bias_as_white_variance(unmodelled_of(s).gravity_gradient, s.steps)


def process_noise_note(c: ProcessNoiseConfig, s: Setup) -> str | None:
    """One line on what ``process_noise: auto`` chose (None without ``auto``)."""
    if not c.auto:
        return None
    if s.perturbations is None:
        return "process_noise auto: the defaults (no truth_model: the truth is the filters' Keplerian, torque-free model)"
    u, q, va = unmodelled_of(s), process_noise_of(c, s), pseudo_unmodelled_var(c, s)
    return (f"process_noise auto: rho {q.rho_m2:.3g} m^2, rho_dot {q.rho_dot_m2ps2:.3g} m^2/s^2 (J2 differential "
            f"{u.j2:.3g} m/s^2, drag differential {u.drag:.3g} m/s^2), omega {q.omega_deg2ps2:.3g} deg^2/s^2 "
            f"(gravity gradient {u.gravity_gradient:.3g} rad/s^2)"
            + (f"; pseudo rows' sigma + {math.sqrt(va):.3g} rad/s^2 (in quadrature)" if va > 0 else ""))  # fmt: skip
