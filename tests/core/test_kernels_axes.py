"""The compiled per-axis errors (core/kernels/axes.py) equal their numpy twin mc.trial.axis_errors."""

import numpy as np
import pytest

pytest.importorskip("numba")

from stereopose_mc.core import aligned, quaternion as qt, state as st  # noqa: E402
from stereopose_mc.core.kernels import axes  # noqa: E402
from stereopose_mc.mc import trial  # noqa: E402

RNG = np.random.default_rng(11)


def _case(B, N, full):
    q = qt.normalize(RNG.standard_normal((B, 4)))
    xt = st.assemble(RNG.standard_normal((B, 3)) + [0, 40, 0], 1e-2 * RNG.standard_normal((B, 3)),
                     1e-2 * RNG.standard_normal((B, 3)), q, RNG.standard_normal((B, N, 3)),
                     0.2 * RNG.standard_normal((B, 2)))  # fmt: skip
    m = xt.shape[1] - (0 if full else 1)
    A = RNG.standard_normal((B, m, m))
    P = A @ A.transpose(0, 2, 1) / m * 1e-3 + 1e-5 * np.eye(m)
    xh = aligned.chart(xt, 0.03 * RNG.standard_normal((B, xt.shape[1] - 1)))
    if full:  # an unnormalized quaternion: Xi normalizes it (the aligned chart's M holds for a unit one, as the NEES's)
        xh[:, st.QUAT] *= 1.0 + 0.1 * RNG.random((B, 1))
    return xh, P, xt


@pytest.mark.parametrize("N", [1, 3, 8, 24])
@pytest.mark.parametrize("chart", ["full", "aligned", "attitude"])
def test_compiled_axis_errors_equal_numpy(N, chart):
    xh, P, xt = _case(30, N, chart == "full")
    ref_e, ref_s = trial.axis_errors(xh, P, xt, chart)
    got_e, got_s = axes.axis_errors(xh, P, xt, chart, trial._AXIS_SCALE)
    assert got_e.shape == ref_e.shape == (30, 14)
    np.testing.assert_allclose(got_e, ref_e, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(got_s, ref_s, rtol=1e-10)
    # one shared truth broadcasts as in numpy
    np.testing.assert_allclose(axes.axis_errors(xh, P, xt[0], chart, trial._AXIS_SCALE)[0],
                               trial.axis_errors(xh, P, xt[0], chart)[0], rtol=1e-10, atol=1e-14)  # fmt: skip


@pytest.mark.parametrize("chart", ["full", "aligned"])
def test_broken_trials_give_nan_like_numpy(chart):
    xh, P, xt = _case(4, 3, chart == "full")
    P[1, 0, 0] = -1.0  # a negative variance of rho_x
    xh[2, 0] = np.nan  # a lost trial
    got, ref = axes.axis_errors(xh, P, xt, chart, trial._AXIS_SCALE), trial.axis_errors(xh, P, xt, chart)
    for g, r in zip(got, ref):
        assert np.array_equal(np.isnan(g), np.isnan(r))
        np.testing.assert_allclose(g[[0, 3]], r[[0, 3]], rtol=1e-10, atol=1e-14)
    assert np.isnan(got[1][1, 0]) and np.isnan(got[0][2]).any()
