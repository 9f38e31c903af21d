"""The layout of the state vector and of its error-state charts: offsets, sizes, names and units.

The full state (``n = 13 + 3N + 2``, docs/model.md)::

    x = [rho0 (3), rho0_dot (3), omega (3), q (4), P_1 .. P_N (3N), k1, k2]

and the error state of both charts (``n_e = n - 1``: the quaternion's 4 become a 3-vector rotation)::

    e = [e_c (3), e_cdot (3), e_omega (3), delta (3), e_P1 .. e_PN (3N), e_k (2)]  (aligned, core.aligned)
    eps = [d rho (3), d rho_dot (3), d omega (3), a (3), d P_1 .. d P_N (3N), d k (2)]  (attitude, core.errorstate)

Everything that indexes a state reads it here: ``core.state``, ``core.aligned``, ``core.errorstate`` and the
compiled kernels (``core/kernels``; Numba reads these module-level ints as compile-time constants, and the
kernels' cache stamp covers this file: ``core/kernels/_cache.py``). A block after the quaternion and before the
points changes the offsets below and nothing else; the inertia ratios ``k`` are always the last 2 entries.

The helpers are plain integer arithmetic, so that a kernel can compile them (``njit(layout.n_points)``).
"""

from __future__ import annotations

VEC = 3  # a 3-vector block (rho, rho_dot, omega, a point, a rotation error)

# --- the full state x ---------------------------------------------------------------------------------------------
RHO = 0  # target centre of mass relative to the leader, in L (m)
RHO_DOT = 3  # its velocity, in L (m/s)
OMEGA = 6  # angular velocity of T relative to L, components in L (rad/s)
QUAT = 9  # scalar-first quaternion, v^L = D(q) v^T (-)
QUAT_SIZE = 4
POINTS = 13  # first feature point P_1, in T (m); point i at POINTS + 3 i
K_SIZE = 2  # k1 = ln(Ix/Iy), k2 = ln(Iy/Iz) (-): the last two entries
COMMON = POINTS  # rho, rho_dot, omega, q: the blocks before the points (every feature's measurement rows see them)
FIXED = COMMON + K_SIZE  # the entries that do not depend on the number of points

# the columns of F = df/dx that are not zero: 0 .. COMMON-1, then k (REDUCED = COMMON + K_SIZE of them); the
# translation (rho, rho_dot) sees only its own 6, the rotation (omega, q) the rest
REDUCED = COMMON + K_SIZE
TRANSLATION = OMEGA  # rho, rho_dot: rows and columns 0 .. TRANSLATION-1 of F's reduced block
R_K = COMMON  # k's first column in the reduced block

NAMES = ("rho", "rho_dot", "omega", "q", "feature_points", "k")
UNITS = {"rho": "m", "rho_dot": "m/s", "omega": "rad/s", "q": "-", "feature_points": "m", "k": "-"}

# --- the error state of both charts (aligned e, attitude eps) ---------------------------------------------------
E_RHO = 0  # e_c (aligned: the centroid's position) / d rho (attitude), m
E_RHO_DOT = 3  # e_cdot / d rho_dot, m/s
E_OMEGA = 6  # e_omega / d omega, rad/s
E_ROT = 9  # delta (aligned, body-frame rotation) / a (attitude), rad
E_POINTS = 12  # e_P1 / d P_1, m; point i at E_POINTS + 3 i
E_COMMON = E_POINTS  # the error-state blocks before the points
E_FIXED = E_COMMON + K_SIZE
E_SHIFT = QUAT_SIZE - VEC  # the error state is this much shorter than the state (past the rotation)

E_NAMES = {
    "aligned": ("e_c", "e_cdot", "e_omega", "delta", "e_P", "e_k"),
    "attitude": ("d_rho", "d_rho_dot", "d_omega", "a", "d_P", "d_k"),
}
E_UNITS = ("m", "m/s", "rad/s", "rad", "m", "-")

# --- the charts, as the kernels take them ------------------------------------------------------------------------
CHART_FULL = 0  # the full state: x + dx, quaternion renormalized (filters.relnav)
CHART_ALIGNED = 1  # the aligned error state (core.aligned)
CHART_ATTITUDE = 2  # the attitude error state (core.errorstate)
CHARTS = {"full": CHART_FULL, "aligned": CHART_ALIGNED, "attitude": CHART_ATTITUDE}


# --- the measurement vector y of one step ---------------------------------------------------------------------------
# per visible feature its channels (core.camera.channels: u_R, v_R, u_L, v_L and their rates, + the disparity d),
# feature after feature, then the inertia pseudo-measurement's rows (filters.relnav)
FEATURE_CHANNELS = 8  # u_R, v_R, u_L, v_L, du_R, dv_R, du_L, dv_L
DISPARITY_CHANNELS = 1  # d, with the scenario's disparity channel
PSEUDO_ROWS = 3  # the pseudo-measurement of the angular acceleration, in T


def n_channels(disparity: bool) -> int:
    """Channels per visible feature: 8, or 9 with the disparity."""
    return FEATURE_CHANNELS + (DISPARITY_CHANNELS if disparity else 0)


def n_measurements(n_visible: int, disparity: bool, pseudo: bool) -> int:
    """Length of a step's measurement vector: the visible features' channels (``n_channels``, written out: the
    kernels compile this function alone), then the pseudo rows."""
    return n_visible * (FEATURE_CHANNELS + (DISPARITY_CHANNELS if disparity else 0)) + (PSEUDO_ROWS if pseudo else 0)


def n_state(N: int) -> int:
    """Length of the state with ``N`` feature points."""
    return FIXED + VEC * N


def n_points(n: int) -> int:
    """Number of feature points of a state of length ``n``."""
    return (n - FIXED) // VEC


def point(i: int) -> int:
    """Offset of feature point ``i`` (0-based) in the state."""
    return POINTS + VEC * i


def k_offset(n: int) -> int:
    """Offset of ``k1`` in a state of length ``n`` (``k2`` follows)."""
    return n - K_SIZE


def n_error(N: int) -> int:
    """Length of the error state (either chart) with ``N`` feature points."""
    return E_FIXED + VEC * N


def e_n_points(ne: int) -> int:
    """Number of feature points of an error state of length ``ne``."""
    return (ne - E_FIXED) // VEC


def e_point(i: int) -> int:
    """Offset of feature point ``i`` in the error state."""
    return E_POINTS + VEC * i


def e_k_offset(ne: int) -> int:
    """Offset of ``e_k1`` in an error state of length ``ne``."""
    return ne - K_SIZE
