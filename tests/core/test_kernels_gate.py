"""The gate's compiled innovation-covariance blocks and distances (core/kernels/gate.py) against their numpy twins,
``filters.gating.linearized_blocks`` on the dense ``H`` and ``gating.distances2``, in the three charts."""

from __future__ import annotations

import numpy as np
import pytest

from stereopose_mc.core.kernels import charts as kch, gate as kg, model as km
from stereopose_mc.core.layout import E_FIXED, E_POINTS
from stereopose_mc.filters import gating

from .test_kernels_charts import ND, NDD, VIS, case

NONE = np.empty((0, VIS.size), bool)  # every feature offered to the kernel


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
    nu = np.random.default_rng(8).normal(size=R.shape) * np.sqrt(R) * 3.0
    S, d2 = kg.innovation_blocks_batch(Hval, cols, P, R, nu, VIS.size, C, chart == 1, NONE)
    ref = gating.linearized_blocks(H, P, R, VIS.size, C)
    assert S.shape == (3, VIS.size, C, C) and d2.shape == (3, VIS.size)
    scale = np.sqrt(np.einsum("bfii,bfjj->bfij", ref, ref))  # |S_ij| <= sqrt(S_ii S_jj)
    assert np.max(np.abs(S - ref) / scale) < 1e-12
    assert np.array_equal(S, np.swapaxes(S, -1, -2))  # each block exactly symmetric
    np.testing.assert_allclose(d2, gating.distances2(nu, ref), rtol=1e-9, atol=0)


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
    one = np.empty((0, 1), bool)
    S, d2 = kg.innovation_blocks_batch(Hval, cols, P, np.array([[0.5]]), np.array([[3.0]]), 1, 1, True, one)
    assert S[0, 0, 0, 0] == N + 0.5
    np.testing.assert_allclose(d2[0, 0], 9.0 / (N + 0.5), rtol=1e-15)
    P[0, E_POINTS, E_POINTS + 3] = P[0, E_POINTS + 3, E_POINTS] = 0.25  # points 0 and 1, axis 0: +2 * 0.25
    P[0, E_POINTS + 1, E_POINTS + 1] = 9.0  # axis 1: not read
    S, _ = kg.innovation_blocks_batch(Hval, cols, P, np.array([[0.5]]), np.array([[3.0]]), 1, 1, True, one)
    assert S[0, 0, 0, 0] == N + 0.5 + 0.5


def test_distance_by_hand_and_a_block_that_is_not_positive_definite():
    """Full chart, two features of two rows on columns 0 and 1: ``S_0 = diag(2, 3) + R``, ``nu = (1, 1)``:
    ``d^2 = 1/3 + 1/4``; a negative variance on the second feature (``S_1`` indefinite): NaN from the kernel (LU,
    ``gating.distances2``, gives a number there: ``compiled.gate_distances`` hands such trials to it)."""
    cols = np.zeros((4, 16), np.int64)
    cols[:, 1] = 1
    Hval = np.zeros((1, 4, 16))
    Hval[0, [0, 2], 0] = 1.0
    Hval[0, [1, 3], 1] = 1.0
    P = np.diag([2.0, 3.0])[None].copy()
    R = np.array([[1.0, 1.0, 1.0, -5.0]])
    nu = np.ones((1, 4))
    S, d2 = kg.innovation_blocks_batch(Hval, cols, P, R, nu, 2, 2, False, np.empty((0, 2), bool))
    np.testing.assert_array_equal(S[0, 0], [[3.0, 0.0], [0.0, 4.0]])
    np.testing.assert_allclose(d2[0, 0], 1.0 / 3.0 + 1.0 / 4.0, rtol=1e-15)
    assert np.isnan(d2[0, 1])
    np.testing.assert_allclose(gating.distances2(nu, S)[0], [1.0 / 3.0 + 1.0 / 4.0, 1.0 / 3.0 - 1.0 / 2.0])


def test_gate_distances_match_numpy_and_fall_back_on_an_indefinite_prior():
    """``compiled.gate_distances`` against ``gating.distances2`` on the dense blocks; trial 1's ``P`` indefinite (a
    filter losing track): its blocks go to LU as before, the same numbers."""
    from stereopose_mc.filters import compiled

    x, _, alpha = case(B=2, N=6)
    n, C = x.shape[-1], 8
    model = km.StepModel(VIS, 0.7, False, 1.0, True, ND, NDD)
    cols = km.measurement_columns(n, VIS, C, True)
    P = spd(2, n, seed=3)
    v = np.zeros(n)
    v[:3] = 1.0  # rho: seen by every feature
    P[1] -= 10.0 * np.outer(v, v)
    R = np.full((2, cols.shape[0]), 1e-6)
    hx, Hval = km.measure_batch(x, model, alpha, True)
    y = hx + np.random.default_rng(4).normal(size=hx.shape) * 1e-3
    _, d2k = kg.innovation_blocks_batch(Hval, cols, P, R, y - hx, VIS.size, C, False, NONE)
    assert not np.isnan(d2k[0]).any() and np.isnan(d2k[1]).any()
    ref = gating.distances2(y - hx, gating.linearized_blocks(km.dense(Hval, cols, n), P, R, VIS.size, C))
    d2 = compiled.gate_distances(x, P, y, R, alpha, model, cols, 0, VIS.size, C)
    np.testing.assert_allclose(d2, ref, rtol=1e-8)


@pytest.mark.parametrize("chart", [0, 1])
def test_features_not_offered_are_skipped_and_the_others_unchanged(chart):
    """``offered``: the offered features' blocks and distances are those computed without it, bit for bit; the
    others' are NaN (not computed)."""
    x, _, alpha = case(B=3, N=6)
    C = 8
    n = x.shape[-1] if chart == 0 else x.shape[-1] - 1
    model = km.StepModel(VIS, 0.7, False, 1.0, True, ND, NDD)
    if chart == 0:
        _, Hval = km.measure_batch(x, model, alpha, True)
        cols = km.measurement_columns(n, VIS, C, True)
    else:
        _, Hval = kch.measure_batch(chart, x, np.zeros((3, n)), model, alpha, True)
        cols = kch.measurement_columns(chart, n, VIS, C, True)
    P = spd(3, n, seed=11)
    R = 10.0 ** np.random.default_rng(12).uniform(-10, -6, size=(3, Hval.shape[1]))
    nu = np.random.default_rng(13).normal(size=R.shape) * np.sqrt(R) * 3.0
    offered = np.random.default_rng(14).random((3, VIS.size)) < 0.5
    offered[0] = True
    S0, d0 = kg.innovation_blocks_batch(Hval, cols, P, R, nu, VIS.size, C, chart == 1, NONE)
    S, d2 = kg.innovation_blocks_batch(Hval, cols, P, R, nu, VIS.size, C, chart == 1, offered)
    assert np.array_equal(S[offered], S0[offered]) and np.array_equal(d2[offered], d0[offered])
    assert np.isnan(S[~offered]).all() and np.isnan(d2[~offered]).all() and (~offered).any()


def test_gate_distances_check_only_offered_features_and_leave_the_others_to_the_caller():
    """With ``offered`` (a batch updated as one, ``compiled.masks_visibility``): a block that is not positive definite
    outside a trial's view is not redone (its distance NaN, unread); one inside raises ``NotMaskable`` (LU on the
    trial's blocks would meet the others': the caller updates that step per pattern)."""
    from stereopose_mc.filters import compiled

    x, _, alpha = case(B=2, N=6)
    n, C = x.shape[-1], 8
    model = km.StepModel(VIS, 0.7, False, 1.0, True, ND, NDD)
    cols = km.measurement_columns(n, VIS, C, True)
    P = spd(2, n, seed=5)
    R = np.full((2, cols.shape[0]), 1e-6)
    R[1, 2 * C : 3 * C] = -5.0  # trial 1, feature 2: S_2 indefinite
    hx, Hval = km.measure_batch(x, model, alpha, True)
    y = hx + np.random.default_rng(6).normal(size=hx.shape) * 1e-3
    offered = np.ones((2, VIS.size), bool)
    offered[1, 2] = False
    d2 = compiled.gate_distances(x, P, y, R, alpha, model, cols, 0, VIS.size, C, offered)
    _, d0 = kg.innovation_blocks_batch(Hval, cols, P, R, y - hx, VIS.size, C, False, NONE)
    assert np.isnan(d2[1, 2]) and np.array_equal(d2[offered], d0[offered])
    with pytest.raises(compiled.NotMaskable):
        compiled.gate_distances(x, P, y, R, alpha, model, cols, 0, VIS.size, C, np.ones((2, VIS.size), bool))
