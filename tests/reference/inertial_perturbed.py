"""Independent reference for the perturbed truth: two spacecraft with J2 (and drag), a target with gravity-gradient torque.

Nothing here uses ``stereopose_mc``. The J2 acceleration is the gradient of the
potential ``U = mu / r (1 - J2 (R_E / r)^2 P2(z / r))``, taken by complex-step
differentiation; the LVLH frame's angular velocity is ``1/2 sum_i e_i x e_i'`` from the
time derivatives of its unit vectors (``x = r/|r|``, ``z = h/|h|``, ``y = z x x``), with
``h' = r x a``. The target's attitude is an inertial quaternion integrated with the
torque ``3 mu / |r|^3 (c x J c)``, ``c`` the unit vector to the target in its body axes.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from reference.inertial import Elements, kepler_rv, matrix_to_quat, quat_rate_matrix, quat_to_matrix

MU = 3.986004418e14
J2 = 1.08262668e-3
RE = 6378137.0
WE = 7.292115e-5


def potential(r):
    rn = np.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2)
    s = r[2] / rn
    return MU / rn * (1.0 - J2 * (RE / rn) ** 2 * 0.5 * (3.0 * s * s - 1.0))


def gravity(r, j2: bool):
    """Central + J2 gravity by complex-step gradient of the potential (or central only)."""
    if not j2:
        return -MU * r / np.linalg.norm(r) ** 3
    h = 1e-20 * np.linalg.norm(r)
    g = np.empty(3)
    for i in range(3):
        rc = r.astype(complex)
        rc[i] += 1j * h
        g[i] = potential(rc).imag / h
    return g


def drag(r, v, B, rho0=3.614e-14, h0=700e3, H=88667.0):
    vr = v - np.cross([0.0, 0.0, WE], r)
    rho = rho0 * np.exp(-(np.linalg.norm(r) - RE - h0) / H)
    return -0.5 * rho * np.linalg.norm(vr) * vr / B


def frame(r, v, a):
    """LVLH axes ``R_IL`` and the frame's angular velocity in LVLH components, from r, v and the acceleration a."""
    rn = np.linalg.norm(r)
    x = r / rn
    h = np.cross(r, v)
    hn = np.linalg.norm(h)
    z = h / hn
    y = np.cross(z, x)
    xd = (v - x * np.dot(x, v)) / rn
    hd = np.cross(r, a)
    zd = (hd - z * np.dot(z, hd)) / hn
    yd = np.cross(zd, x) + np.cross(z, xd)
    w = 0.5 * (np.cross(x, xd) + np.cross(y, yd) + np.cross(z, zd))
    R = np.column_stack([x, y, z])
    return R, R.T @ w


def propagate(el: Elements, rho0, rho_dot0, omega0, q0, inertia, t, j2=True, gg=True, drag_b=None, rtol=1e-13):
    """Relative rho, rho_dot, omega, q (target -> L) at times ``t``, from an LVLH initial state."""
    J = np.asarray(inertia, float)

    def acc(r, v, b):
        a = gravity(r, j2)
        if drag_b is not None:
            a = a + drag(r, v, b)
        return a

    rL, vL = kepler_rv(el, el.nu0)
    bL, bT = (None, None) if drag_b is None else drag_b
    R, wF = frame(rL, vL, acc(rL, vL, bL))
    D0 = quat_to_matrix(q0)
    y0 = np.concatenate([rL, vL, rL + R @ rho0, vL + R @ (np.asarray(rho_dot0) + np.cross(wF, rho0)),
                         matrix_to_quat(R @ D0), D0.T @ (np.asarray(omega0) + wF)])  # fmt: skip

    def rhs(_t, y):
        r1, v1, r2, v2, q, w = y[0:3], y[3:6], y[6:9], y[9:12], y[12:16], y[16:19]
        N = np.zeros(3)
        if gg:
            c = quat_to_matrix(q).T @ r2
            rn = np.linalg.norm(c)
            c = c / rn
            N = 3.0 * MU / rn**3 * np.cross(c, J * c)
        wd = (N - np.cross(w, J * w)) / J
        return np.concatenate([v1, acc(r1, v1, bL), v2, acc(r2, v2, bT), 0.5 * quat_rate_matrix(w) @ q, wd])

    atol = np.concatenate([np.full(6, 1e-10), np.full(6, 1e-10), np.full(4, 1e-15), np.full(3, 1e-17)])
    sol = solve_ivp(rhs, (t[0], t[-1]), y0, method="DOP853", t_eval=t, rtol=rtol, atol=atol)
    assert sol.success
    out = {k: [] for k in ("rho", "rho_dot", "omega", "q")}
    for y in sol.y.T:
        r1, v1, r2, v2, q, w = y[0:3], y[3:6], y[6:9], y[9:12], y[12:16], y[16:19]
        R, wF = frame(r1, v1, acc(r1, v1, bL))
        rho = R.T @ (r2 - r1)
        D = R.T @ quat_to_matrix(q)
        out["rho"].append(rho)
        out["rho_dot"].append(R.T @ (v2 - v1) - np.cross(wF, rho))
        out["omega"].append(D @ w - wF)
        out["q"].append(Rotation.from_matrix(D).as_quat(scalar_first=True))
    return {k: np.asarray(v) for k, v in out.items()}
