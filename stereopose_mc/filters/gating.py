"""Per-feature chi-square gating of the innovation, and measurement masks (batched).

A measurement of ``F`` features stacks ``C`` rows per feature (then possibly other rows,
e.g. the inertia pseudo-measurement, which are never gated). Before an update, each
feature ``f`` of each trial is tested on its innovation ``nu_f = y_f - h_f(x-)``
against its predicted covariance, the ``C x C`` diagonal block

    S_f = H_f P- H_f^T + R_f                                   (EKF / IEKF at x- )

    d_f^2 = nu_f^T S_f^-1 nu_f  >  chi2_C^-1(p)   ->  rejected

(Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, 5.4; Stone Soup's ``gater.distance.DistanceGater`` with a Mahalanobis
measure). For a correct feature ``d_f^2 ~ chi2(C)``, so it is rejected with probability
``1 - p``. The IEKF gates once, at its first iterate (the prior), and keeps the set.

Any filter can use the gate: ``gate`` takes innovations and innovation-covariance
blocks however they were obtained (a UKF passes its sigma-point ``S`` blocks);
``linearized_blocks`` computes them for an EKF-type filter (the compiled filters: ``core.kernels.gate``, from
the row-sparse ``H``, with the distances). A rejected (or dropped)
feature is removed from the update by ``masked_measure``: its rows get ``h(x) = y`` and
``H = 0``, which is exactly the update without those rows (its column of the gain is
zero, it adds nothing to the NIS or to the IEKF's cost), at a fixed batch shape.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@functools.lru_cache(maxsize=64)
def threshold(probability: float, dof: int) -> float:
    """The gate ``chi2_dof^-1(probability) = 2 P^-1(dof/2, probability)`` on the squared Mahalanobis distance
    (``P`` the regularized lower incomplete gamma function; computed once per pair). ``scipy.special``, not
    ``scipy.stats``, whose import costs about a second of a run's start-up."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, probability))


def linearized_blocks(H: Array, P: Array, R: Array, n_features: int, channels: int) -> Array:
    """``S_f = H_f P H_f^T + R_f`` of the first ``n_features * channels`` rows, ``(b, F, C, C)``.

    ``H (b, m, n)``, ``P (b, n, n)``, ``R`` the diagonal ``(m,)`` or ``(b, m)``. ``H_F P`` for all the
    features' rows is one BLAS product (``b F C n^2``); each block is then that product's ``C`` rows
    times its own feature's rows of ``H`` (``b F C^2 n``). (In the aligned chart a feature's rows touch
    nearly every column, through the centroid, so gathering each feature's columns of ``P`` costs more.)
    """
    b, n = H.shape[0], H.shape[-1]
    FC = n_features * channels
    Hf = H[:, :FC]
    HP = (Hf @ P).reshape(b, n_features, channels, n)
    S = HP @ np.swapaxes(Hf.reshape(b, n_features, channels, n), -1, -2)
    Rf = np.broadcast_to(R, (b, R.shape[-1]))[:, :FC].reshape(b, n_features, channels)
    idx = np.arange(channels)
    S[..., idx, idx] += Rf
    return S


def distances2(nu: Array, S_blocks: Array) -> Array:
    """``d_f^2 = nu_f^T S_f^-1 nu_f``, ``(b, F)``, from ``nu (b, m)`` (first ``F C`` rows) and ``S_blocks``."""
    b, F, C, _ = S_blocks.shape
    v = nu[:, : F * C].reshape(b, F, C)
    return np.einsum("bfc,bfc->bf", v, np.linalg.solve(S_blocks, v[..., None])[..., 0])


def gate(d2: Array, probability: float, channels: int, keep: Array | None = None) -> tuple[Array, Array]:
    """``(keep, rejected)``: features passing the gate (and ``keep``), and per trial the count rejected.

    Features already excluded by ``keep`` (dropped by the tracker) are not counted as rejected.
    """
    ok = d2 <= threshold(probability, channels)
    prior = np.ones_like(ok) if keep is None else keep
    return prior & ok, np.sum(prior & ~ok, axis=-1)


LOCKOUT_FRACTION = 0.75  # inflate when the gate would reject at least this share of the features offered


@functools.lru_cache(maxsize=16)
def chi2_median(dof: int) -> float:
    """The median of chi-square with ``dof`` degrees of freedom, ``2 P^-1(dof/2, 1/2)``."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, 0.5))


def robust_gate(d2: Array, probability: float, channels: int, keep: Array | None = None,
                inflate: bool = True) -> tuple[Array, Array, Array]:  # fmt: skip
    """``(keep, rejected, lam)``: ``gate``, and where it would reject at least ``LOCKOUT_FRACTION`` of a trial's
    offered features, the same gate on ``d2 / lam`` with

        lam = max(1, median_f(d2_f) / median(chi2_C))

    the innovations' robust excess over their claimed covariance (the median ignores up to half of the
    features being outliers). A correct filter meets this with probability far below ``1 - probability``
    per feature; a filter briefly overconfident (its prior ``P`` too small) meets it at every step, and
    without it would reject every feature until it is lost (a gate lock-out). The update then uses the
    prior ``lam P`` (fading memory: the covariance the innovations say it has), which ``lam`` returns
    (``1`` where nothing changed; ``inflate`` False: always ``1``, the plain gate).
    """
    kept, rejected = gate(d2, probability, channels, keep)
    lam = np.ones(d2.shape[0])
    if not inflate:
        return kept, rejected, lam
    offered = np.ones_like(kept) if keep is None else keep
    n = offered.sum(axis=-1)
    lock = np.flatnonzero((n > 0) & (rejected >= LOCKOUT_FRACTION * n))
    if lock.size:
        med = np.array([np.median(d2[i][offered[i]]) for i in lock])
        lam[lock] = np.maximum(1.0, med / chi2_median(channels))
        k2, r2 = gate(d2[lock] / lam[lock, None], probability, channels, offered[lock])
        kept, rejected = kept.copy(), rejected.copy()
        kept[lock], rejected[lock] = k2, r2
    return kept, rejected, lam


def inflated(P: Array, lam: Array) -> Array:
    """``lam P`` per trial (``P`` itself when every ``lam`` is 1)."""
    if np.all(lam == 1.0):
        return P
    return P * lam[:, None, None]


def masked_measure(measure, y: Array, rows: Array, keep: Array, channels: int):
    """``measure`` with the rows of the features not in ``keep (b, F)`` taken out of the update.

    ``y (B, m)`` is the step's measurement of the whole chunk and ``rows (b,)`` the trials
    of the batch ``keep`` belongs to; the returned callable accepts any subset of them (as
    the IEKF's per-trial iteration does).
    """
    B, m = y.shape
    full = np.ones((B, m), bool)
    F = keep.shape[-1]
    full[rows, : F * channels] = np.repeat(keep, channels, axis=-1)

    def measure_masked(x: Array, sub: Array, jac: bool = True):
        hx, H = measure(x, sub, jac)
        mk = full[sub]
        hx = np.where(mk, hx, y[sub])
        if H is not None:
            H = H * mk[..., None]
        return hx, H

    return measure_masked
