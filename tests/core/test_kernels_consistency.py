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
