"""Independent reference for the truth model: two point masses and a rigid body in the inertial frame.

Nothing here uses ``stereopose_mc``'s dynamics, orbit or quaternion code. The leader and
the target are integrated as two independent Keplerian point masses in the Earth-centred
inertial frame ``I``,

    r_L'' = -mu r_L / |r_L|^3,        r_T'' = -mu r_T / |r_T|^3,

and the target's attitude as a torque-free rigid body with an *inertial* quaternion
``q_IT`` (``v^I = R(q_IT) v^T``, scalar first) and body rate ``w_T``:

    I w_T' = -w_T x I w_T,            q_IT' = 1/2 q_IT (x) [0, w_T].

The LVLH frame ``L`` of the leader is built from ``(r_L, v_L)`` (x = r/|r|, z = h/|h|,
y = z x x); it rotates at ``w_L = [0, 0, |h|/|r|^2]`` in ``L``. The relative quantities are

    rho     = R_IL^T (r_T - r_L)
    rho_dot = R_IL^T (v_T - v_L) - w_L x rho
    D       = R_IL^T R_IT                      (target -> L)
    omega   = D w_T - w_L                      (T relative to L, in L)

Rotation matrices <-> quaternions go through ``scipy.spatial.transform.Rotation``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

MU = 3.986004418e14
Array = NDArray[np.float64]


@dataclass(frozen=True)
class Elements:
    """Keplerian elements (m, rad)."""

    a: float
    e: float
    i: float
    raan: float
    argp: float
    nu0: float
    mu: float = MU


def kepler_rv(el: Elements, nu: float) -> tuple[Array, Array]:
    """Inertial position and velocity at true anomaly ``nu``.

    Perifocal ``r = p/(1+e cos nu) [cos nu, sin nu, 0]``, ``v = sqrt(mu/p) [-sin nu, e + cos nu, 0]``,
    rotated by ``Rz(raan) Rx(i) Rz(argp)`` (scipy intrinsic ZXZ).
    """
    p = el.a * (1.0 - el.e**2)
    r = p / (1.0 + el.e * np.cos(nu))
    r_pf = np.array([r * np.cos(nu), r * np.sin(nu), 0.0])
    v_pf = np.sqrt(el.mu / p) * np.array([-np.sin(nu), el.e + np.cos(nu), 0.0])
    R = Rotation.from_euler("ZXZ", [el.raan, el.i, el.argp]).as_matrix()
    return R @ r_pf, R @ v_pf


def lvlh_axes(r: Array, v: Array) -> Array:
    """``R_IL`` (columns: the LVLH x, y, z axes in ``I``)."""
    x = r / np.linalg.norm(r)
    h = np.cross(r, v)
    z = h / np.linalg.norm(h)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


def lvlh_rate(r: Array, v: Array) -> float:
    """``nu_dot = |r x v| / |r|^2`` (the LVLH frame's rate about its z axis)."""
    return float(np.linalg.norm(np.cross(r, v)) / np.dot(r, r))


def quat_rate_matrix(w: Array) -> Array:
    """``Omega(w)`` with ``q (x) [0, w] = Omega(w) q`` (Hamilton, scalar first)."""
    w1, w2, w3 = w
    return np.array([[0.0, -w1, -w2, -w3], [w1, 0.0, w3, -w2], [w2, -w3, 0.0, w1], [w3, w2, -w1, 0.0]])


def quat_to_matrix(q: Array) -> Array:
    return Rotation.from_quat(np.asarray(q), scalar_first=True).as_matrix()


def matrix_to_quat(R: Array) -> Array:
    return Rotation.from_matrix(R).as_quat(scalar_first=True)


@dataclass(frozen=True)
class Relative:
    """Reference relative quantities at times ``t`` (leading axis: time)."""

    t: Array
    rho: Array
    rho_dot: Array
    omega: Array
    q: Array  # target -> L, scalar first
    D: Array
    nu_swept: Array  # leader's true anomaly minus its initial value (unwrapped)
    r_L: Array  # |r_L|
    nu_dot: Array  # |h|/r^2


def propagate(
    el: Elements,
    rho0: Array,
    rho_dot0: Array,
    omega0: Array,
    q0: Array,
    inertia: Array,
    t: Array,
    rtol: float = 1e-13,
) -> Relative:
    """Integrate the inertial two-body + rigid-body problem from an LVLH initial state; sample at ``t``."""
    inertia = np.asarray(inertia, dtype=float)
    mu = el.mu
    rL, vL = kepler_rv(el, el.nu0)
    R_IL = lvlh_axes(rL, vL)
    wL = np.array([0.0, 0.0, lvlh_rate(rL, vL)])
    D0 = quat_to_matrix(q0)
    rT = rL + R_IL @ rho0
    vT = vL + R_IL @ (np.asarray(rho_dot0) + np.cross(wL, rho0))
    w_T = D0.T @ (np.asarray(omega0) + wL)
    q_IT = matrix_to_quat(R_IL @ D0)
    y0 = np.concatenate([rL, vL, rT, vT, q_IT, w_T])

    def rhs(_t: float, y: Array) -> Array:
        r1, v1, r2, v2, q, w = y[0:3], y[3:6], y[6:9], y[9:12], y[12:16], y[16:19]
        a1 = -mu * r1 / np.linalg.norm(r1) ** 3
        a2 = -mu * r2 / np.linalg.norm(r2) ** 3
        qd = 0.5 * quat_rate_matrix(w) @ q
        wd = -np.cross(w, inertia * w) / inertia
        return np.concatenate([v1, a1, v2, a2, qd, wd])

    atol = np.concatenate(
        [np.full(3, 1e-9), np.full(3, 1e-12), np.full(3, 1e-9), np.full(3, 1e-12), np.full(4, 1e-15), np.full(3, 1e-17)]
    )
    sol = solve_ivp(rhs, (t[0], t[-1]), y0, method="DOP853", t_eval=t, rtol=rtol, atol=atol)
    assert sol.success, sol.message
    Y = sol.y.T
    out = {k: [] for k in ("rho", "rho_dot", "omega", "q", "D", "r_L", "nu_dot", "angle")}
    x_first = Y[0, 0:3] / np.linalg.norm(Y[0, 0:3])
    h_hat = np.cross(Y[0, 0:3], Y[0, 3:6])
    h_hat /= np.linalg.norm(h_hat)
    for y in Y:
        r1, v1, r2, v2, q, w = y[0:3], y[3:6], y[6:9], y[9:12], y[12:16], y[16:19]
        R = lvlh_axes(r1, v1)
        nd = lvlh_rate(r1, v1)
        wLk = np.array([0.0, 0.0, nd])
        rho = R.T @ (r2 - r1)
        D = R.T @ quat_to_matrix(q)
        out["rho"].append(rho)
        out["rho_dot"].append(R.T @ (v2 - v1) - np.cross(wLk, rho))
        out["omega"].append(D @ w - wLk)
        out["D"].append(D)
        out["q"].append(matrix_to_quat(D))
        out["r_L"].append(np.linalg.norm(r1))
        out["nu_dot"].append(nd)
        xk = r1 / np.linalg.norm(r1)
        out["angle"].append(np.arctan2(np.dot(np.cross(x_first, xk), h_hat), np.dot(x_first, xk)))
    arr = {k: np.asarray(v) for k, v in out.items()}
    return Relative(
        t=np.asarray(t, dtype=float),
        rho=arr["rho"],
        rho_dot=arr["rho_dot"],
        omega=arr["omega"],
        q=arr["q"],
        D=arr["D"],
        nu_swept=np.unwrap(arr["angle"]),
        r_L=arr["r_L"],
        nu_dot=arr["nu_dot"],
    )
