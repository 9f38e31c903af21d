"""Bounds on what a perturbed truth does that the filters' model leaves out, and the Q that covers it.

The filters propagate the Keplerian relative motion about the leader's osculating orbit and
a torque-free target (core/dynamics.py); a ``truth_model`` (core/perturbed.py) adds J2,
drag and the gravity-gradient torque. What the filters miss, per unit time (SI):

- **J2, differential.** Both spacecraft feel ``a_J2`` (core/perturbed.py); the leader's part
  moves its osculating orbit, which the filters follow, so what is left on ``rho_dot`` is the
  difference ``a_J2(r_T) - a_J2(r_L) = G (r_T - r_L) + O(|rho|^2)`` with ``G`` the gradient
  (the Hessian of the J2 potential). Its eigenvalues at radius ``r`` and latitude ``phi``
  (``s = sin phi``) are, in units of ``J2 mu R_E^2 / r^5``, ``-3/2 (1 - 5 s^2)`` and
  ``3/4 (1 - 5 s^2) +- 3/4 sqrt(49 - 10 s^2 + 105 s^4)``, so

      |a_J2,diff| <= c(s_max) J2 mu R_E^2 / r_p^5 |rho|_max,
      c(s) = 3/4 (|1 - 5 s^2| + sqrt(49 - 10 s^2 + 105 s^4))

  (``c(0) = 6`` on the equator, ``c(1) = 12`` over a pole). ``c`` is convex in ``s^2``, so
  its largest value on an orbit of inclination ``i`` (latitudes up to ``s_max = |sin i|``)
  is ``max(c(0), c(s_max))``; ``r_p`` is the closest approach to the Earth's centre.
- **Drag, differential** (``a = -1/2 rho(h) |v_rel| v_rel / B``): the ballistic coefficients'
  difference, the density's change over the separation (scale height ``H``) and the relative
  speed's change, each to first order at perigee:

      |a_drag,diff| <= 1/2 rho(h_p) v^2 (|1/B_T - 1/B_L| + (|rho|_max / H + 2 dv / v) / B_T),
      v = v_p + w_E r_p,  dv = |rho_dot_0| + 2 v |rho|_max / r_p

  (``v`` bounds the speed in the co-rotating atmosphere, ``dv`` the relative velocity in the
  inertial frame: the filter's own plus the LVLH frame's rotation ``|w_F| <= v_p / r_p``, twice
  for the Earth's rotation as a margin).
- **Gravity-gradient torque** ``N = 3 mu / r^5 (r_b x J r_b)``: per body axis
  ``|N_i| / I_i = 3 mu / r^3 |I_j - I_k| / I_i |r_j r_k| / r^2 <= 3 mu / (2 r^3) |I_j - I_k| / I_i``
  (``|r_j r_k| <= r^2 / 2``), and the relative angular velocity's equation takes the body
  vector through the attitude, so its every component is bounded by the norm

      |alpha_GG| <= 3 mu / (2 r_p^3) sqrt(sum_i ((I_j - I_k) / I_i)^2)        (i, j, k cyclic).

Left out (measured small by ``spmc dynamics``, ``studies/truth_mismatch.py``): the LVLH
frame's out-of-plane rate that J2 and drag give the leader (the osculating orbit has none),
second order in ``|rho|`` and in the errors of the osculating orbit.

**Q from a bound.** An unmodelled acceleration bounded by ``a`` is taken as white noise of
spectral density ``q_c = a^2 dt`` (its square held over one step), which adds per step the
variances ``q_c dt = (a dt)^2`` on the velocity and ``q_c dt^3 / 3 = a^2 dt^4 / 3`` on the
position; the filters' Q is diagonal, so the position-velocity covariance ``q_c dt^2 / 2`` is
dropped. The same with ``alpha`` on ``omega``; its effect on the attitude, ``alpha^2 dt^4 / 12``
per quaternion component, is orders below the attitude's floor and left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .perturbed import J2, MU, OMEGA_EARTH, R_EARTH, Perturbations, density


@dataclass(frozen=True)
class Unmodelled:
    """Bounds on the unmodelled accelerations (SI): ``rho_dot`` in m/s^2, ``omega`` in rad/s^2."""

    j2: float = 0.0
    drag: float = 0.0
    gravity_gradient: float = 0.0

    @property
    def acceleration(self) -> float:
        """The bound on ``rho``'s unmodelled acceleration (the two differential terms add)."""
        return self.j2 + self.drag


def j2_gradient_constant(sin_lat_max: float) -> float:
    """``max c(s)`` over ``|s| <= sin_lat_max`` with ``c(s) = 3/4 (|1 - 5 s^2| + sqrt(49 - 10 s^2 + 105 s^4))``."""

    def c(s2):
        return 0.75 * (abs(1.0 - 5.0 * s2) + np.sqrt(49.0 - 10.0 * s2 + 105.0 * s2 * s2))

    return float(max(c(0.0), c(min(sin_lat_max, 1.0) ** 2)))


def j2_differential(r: float, sin_lat_max: float, rho: float) -> float:
    """``c(s_max) J2 mu R_E^2 / r^5 |rho|`` (m/s^2): the J2 acceleration's change over a separation ``rho`` (m)."""
    return j2_gradient_constant(sin_lat_max) * J2 * MU * R_EARTH**2 / r**5 * rho


def drag_differential(r_p: float, a: float, rho: float, rho_dot: float, p: Perturbations) -> float:
    """The differential drag bound of the module docstring (m/s^2) at perigee ``r_p`` of an orbit of axis ``a``."""
    v = np.sqrt(MU * (2.0 / r_p - 1.0 / a)) + OMEGA_EARTH * r_p
    dv = rho_dot + 2.0 * v * rho / r_p
    rho_atm = float(density(np.array([r_p, 0.0, 0.0]), p))
    return float(0.5 * rho_atm * v**2 * (abs(1.0 / p.ballistic_target - 1.0 / p.ballistic_leader)
                                         + (rho / p.scale_height + 2.0 * dv / v) / p.ballistic_target))  # fmt: skip


def gravity_gradient_alpha(r: float, moments) -> float:
    """``3 mu / (2 r^3) sqrt(sum_i ((I_j - I_k) / I_i)^2)`` (rad/s^2) for principal moments ``(3,)``."""
    J = np.asarray(moments, dtype=float)
    ratios = (np.roll(J, -1) - np.roll(J, -2)) / J
    return float(1.5 * MU / r**3 * np.sqrt(np.sum(ratios**2)))


def unmodelled(p: Perturbations | None, a: float, e: float, i: float, rho: float, rho_dot: float,
               moments) -> Unmodelled:  # fmt: skip
    """The bounds of the module docstring for an orbit ``a`` (m), ``e``, ``i`` (rad), the largest separation
    ``rho`` (m), the relative speed ``rho_dot`` (m/s) and the target's principal moments; all zero without ``p``."""
    if p is None:
        return Unmodelled()
    r_p = a * (1.0 - e) - rho  # the closer of the two spacecraft at perigee
    return Unmodelled(
        j2=j2_differential(r_p, abs(np.sin(i)), rho) if p.j2 else 0.0,
        drag=drag_differential(r_p, a, rho, rho_dot, p) if p.drag else 0.0,
        gravity_gradient=gravity_gradient_alpha(r_p, moments) if p.gravity_gradient else 0.0,
    )


def white_acceleration(a: float, dt: float) -> tuple[float, float]:
    """Per-step variances ``(position a^2 dt^4 / 3, velocity (a dt)^2)`` of white noise ``q_c = a^2 dt``."""
    return a * a * dt**4 / 3.0, (a * dt) ** 2


def bias_as_white_variance(b: float, rows: int, axes: int = 3) -> float:
    """The variance ``rows b^2 / axes`` that a measurement row must add to stay consistent under a bias of norm at
    most ``b`` spread over ``axes`` components, when the filter averages ``rows`` such rows.

    A bias ``beta`` in a row the filter treats as white noise of variance ``s^2`` leaves the mean of ``K`` rows off
    by ``beta`` while the filter claims ``s / sqrt(K)``: its NEES along that combination is ``1 + K beta^2 / s^2``,
    near 1 only when ``s^2 >= K beta^2``. Per component ``beta^2 ~ b^2 / axes``.
    """
    return rows * b * b / axes

