"""The gate's compiled innovation-covariance blocks (core/kernels/gate.py) against their numpy twin,
``filters.gating.linearized_blocks`` on the dense ``H``, in the three charts."""

from __future__ import annotations

import numpy as np
import pytest

from stereopose_mc.core.kernels import charts as kch, gate as kg, model as km
from stereopose_mc.core.layout import E_FIXED, E_POINTS
from stereopose_mc.filters import gating

from .test_kernels_charts import ND, NDD, VIS, case


def spd(B, n, seed):
    """Random covariances with the scales of a filter's (eigenvalues 1e-6 .. 1)."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(B, n, n)))
    lam = 10.0 ** rng.uniform(-6, 0, size=(B, 1, n))
    P = (Q * lam) @ np.swapaxes(Q, -1, -2)
    return 0.5 * (P + np.swapaxes(P, -1, -2))


@pytest.mark.parametrize("chart", [0, 1, 2])  # full state, aligned (virtual point-sum columns), attitude
@pytest.mark.parametrize("disparity", [False, True])
def test_blocks_match_the_dense_product(chart, disparity):
    x, e, alpha = case(B=3, N=6)
    C = 9 if disparity else 8
    n = x.shape[-1] if chart == 0 else x.shape[-1] - 1
    model = km.StepModel(VIS, 0.7, disparity, 1.0, True, ND, NDD)
    if chart == 0:
        _, Hval = km.measure_batch(x, model, alpha, True)
        cols = km.measurement_columns(n, VIS, C, True)
        H = km.dense(Hval, cols, n)
    else:
        _, Hval = kch.measure_batch(chart, x, np.zeros((3, n)), model, alpha, True)
        cols = kch.measurement_columns(chart, n, VIS, C, True)
        H = kch.dense(chart, Hval, cols, n)
    P = spd(3, n, seed=chart)
    R = 10.0 ** np.random.default_rng(7).uniform(-10, -6, size=(3, Hval.shape[1]))
    S = kg.innovation_blocks_batch(Hval, cols, P, R, VIS.size, C, chart == 1)
    ref = gating.linearized_blocks(H, P, R, VIS.size, C)
    assert S.shape == (3, VIS.size, C, C)
    scale = np.sqrt(np.einsum("bfii,bfjj->bfij", ref, ref))  # |S_ij| <= sqrt(S_ii S_jj)
    assert np.max(np.abs(S - ref) / scale) < 1e-12
    assert np.array_equal(S, np.swapaxes(S, -1, -2))  # each block exactly symmetric


def test_virtual_columns_are_the_point_sums():
    """A hand case: one feature's row with a single virtual value 1 at column ``n`` (point sum of axis 0) reads
    ``sum_p sum_q P[p0, q0]``; with ``P = I`` that is the number of points."""
    N = 4
    n = E_FIXED + 3 * N  # the aligned error state of 4 points
    cols = np.zeros((1, 16), np.int64)
    cols[0, 0] = n  # the virtual column of axis 0
    Hval = np.zeros((1, 1, 16))
    Hval[0, 0, 0] = 1.0
    P = np.eye(n)[None].copy()
    S = kg.innovation_blocks_batch(Hval, cols, P, np.array([[0.5]]), 1, 1, True)
    assert S[0, 0, 0, 0] == N + 0.5
    P[0, E_POINTS, E_POINTS + 3] = P[0, E_POINTS + 3, E_POINTS] = 0.25  # points 0 and 1, axis 0: +2 * 0.25
    P[0, E_POINTS + 1, E_POINTS + 1] = 9.0  # axis 1: not read
    S = kg.innovation_blocks_batch(Hval, cols, P, np.array([[0.5]]), 1, 1, True)
    assert S[0, 0, 0, 0] == N + 0.5 + 0.5
