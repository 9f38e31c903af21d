"""The compiled NEES (core/kernels/consistency.py) equals its numpy twin core.aligned.nees_report."""

import numpy as np
import pytest

pytest.importorskip("numba")

from stereopose_mc.core import aligned, quaternion as qt, state as st  # noqa: E402
from stereopose_mc.core.kernels import consistency as kc  # noqa: E402

RNG = np.random.default_rng(5)


def _case(B, N):
    q = qt.normalize(RNG.standard_normal((B, 4)))
    xt = st.assemble(RNG.standard_normal((B, 3)) + [0, 40, 0], 1e-2 * RNG.standard_normal((B, 3)),
                     1e-2 * RNG.standard_normal((B, 3)), q, RNG.standard_normal((B, N, 3)),
                     0.2 * RNG.standard_normal((B, 2)))  # fmt: skip
    ne = xt.shape[1] - 1
    A = RNG.standard_normal((B, ne, ne))
    P = A @ A.transpose(0, 2, 1) / ne * 1e-3 + 1e-5 * np.eye(ne)
    xh = aligned.chart(xt, 0.03 * RNG.standard_normal((B, ne)))
    return xh, P, xt


@pytest.mark.parametrize("N", [1, 3, 5, 8])
def test_compiled_nees_equals_the_numpy_report(N):
    xh, P, xt = _case(40, N)
    ref = aligned.nees_report(xh, P, xt)
    got = kc.nees_report(xh, P, xt)
    assert set(got) == set(ref)
    for k in kc.KEYS:
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-10, err_msg=k)
    # one shared truth (the engine's usual case) broadcasts like the numpy report
    one = kc.nees_report(xh, P, xt[0])
    np.testing.assert_allclose(one["nees"], aligned.nees_report(xh, P, xt[0])["nees"], rtol=1e-10)


def test_broken_trials_give_nan_like_numpy():
    xh, P, xt = _case(4, 2)
    P[1, 0, 0] = -1.0  # not positive definite
    xh[2, 0] = np.nan  # a lost trial
    got, ref = kc.nees_report(xh, P, xt), aligned.nees_report(xh, P, xt)
    assert np.isnan(got["nees"][1]) and np.isnan(ref["nees"][1])
    assert all(np.isnan(got[k][2]) for k in kc.KEYS)
    np.testing.assert_allclose(got["nees"][[0, 3]], ref["nees"][[0, 3]], rtol=1e-10)


def test_gauge_nees_with_a_wide_gauge_direction():
    """The gauge-projected NEES from the full NEES's factor (projection of ``L^-1 e`` off ``L^-1 G``) against an
    exact value: ``P`` block-diagonal in an orthonormal basis ``[V, G]`` (``G`` the gauge, 10 m wide; ``V`` its
    complement, 1 cm to 1 m) and ``e = V a + G g``: the gauge-projected NEES is ``a^T C^-1 a`` whatever ``g``."""
    N = 5
    xh, _, xt = _case(20, N)
    ne = xh.shape[-1] - 1
    G = np.zeros((ne, 3))
    G[12 : 12 + 3 * N] = np.tile(np.eye(3), (N, 1)) / np.sqrt(N)
    V = aligned.gauge_complement(ne + 1)
    V = np.linalg.qr(V)[0]  # orthonormal, orthogonal to G
    for b in range(20):
        Cr = RNG.standard_normal((ne - 3, ne - 3)) * np.logspace(-2, 0, ne - 3)[:, None]  # 1 cm to 1 m
        C = Cr @ Cr.T / ne + 1e-6 * np.eye(ne - 3)
        P = V @ C @ V.T + 1e2 * G @ G.T
        a = np.linalg.cholesky(C) @ RNG.standard_normal(ne - 3)
        exact = a @ np.linalg.solve(C, a)
        e_target = V @ a + G @ (10.0 * RNG.standard_normal(3))
        # estimate whose aligned error is e_target: x_hat = x_true [-] e; use the chart at the truth instead
        xh_b = xt[b]
        xt_b = aligned.chart(xh_b[None], e_target[None])[0]
        got = kc.nees_report(xh_b[None], P[None], xt_b[None])["nees_gauge"][0]
        e = aligned.local(xh_b[None], xt_b[None])[0]
        np.testing.assert_allclose(e, e_target, rtol=1e-9, atol=1e-12)  # the chart's inverse (tested elsewhere)
        np.testing.assert_allclose(got, exact, rtol=1e-7)


def test_pd_flag_is_the_factorization_of_P():
    xh, P, xt = _case(3, 2)
    P[1] = -P[1]
    _, pd = kc.nees_and_pd(xh, P, xt)
    assert pd.tolist() == [True, False, True]


def test_full_state_covariance_is_mapped_like_the_numpy_path():
    """A full-state filter's ``P (n x n)`` enters as ``T P T^T`` (``mc.trial.aligned_covariance``): same NEES."""
    from stereopose_mc.mc import trial

    xh, _, xt = _case(25, 4)
    n = xh.shape[-1]
    A = RNG.standard_normal((25, n, n))
    P = A @ A.transpose(0, 2, 1) / n * 1e-3 + 1e-6 * np.eye(n)
    ref = trial.nees_of(xh, P, xt, "full", "numpy")
    got, pd = kc.nees_and_pd(xh, P, xt)
    assert pd.all()
    for k in kc.KEYS:
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-9, err_msg=k)
    P[3] = -P[3]  # not positive definite: flagged (the engine's divergence check reads the flag)
    assert not kc.nees_and_pd(xh, P, xt)[1][3]


def test_attitude_chart_covariance_is_mapped_like_the_numpy_path():
    """An attitude-chart filter's ``P (n-1 x n-1)`` enters as ``M^-1 P M^-T`` (``aligned.from_attitude_chart``, two
    solves in numpy; ``T_aligned S_attitude`` in the kernel): the same NEES, and ``pd`` that of ``P`` itself."""
    from stereopose_mc.mc import trial

    xh, Pa, xt = _case(25, 4)
    P = aligned.to_attitude_chart(xh, Pa)  # an aligned covariance seen in the attitude chart
    assert np.abs(P - Pa).max() > 1e-3 * np.abs(Pa).max()  # really another matrix
    ref = trial.nees_of(xh, P, xt, "attitude", "numpy")
    got, pd = kc.nees_and_pd(xh, P, xt, attitude=True)
    assert pd.all()
    for k in kc.KEYS:
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-9, err_msg=k)
        np.testing.assert_allclose(got[k], aligned.nees_report(xh, Pa, xt)[k], rtol=1e-9, err_msg=k)
    # the engine's entry point picks the mapping from the filter's error state
    eng, _ = trial.nees_and_pd(xh, P, xt, "attitude", "compiled")
    np.testing.assert_array_equal(eng["nees"], got["nees"])
    P[3] = -P[3]
    assert not kc.nees_and_pd(xh, P, xt, attitude=True)[1][3]
