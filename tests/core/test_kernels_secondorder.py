"""The compiled second-order R and Q terms (core/kernels/secondorder.py) equal their numpy twins (core.camera's
flow_second_order_variance, core.inertia's pseudo_second_order_variance and rate_second_order_variance, as
filters.relnav applies them)."""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("numba")

from stereopose_mc.config.loader import load_scenario  # noqa: E402
from stereopose_mc.config.resolve import setup_of  # noqa: E402
from stereopose_mc.core import quaternion as qt, state as st  # noqa: E402
from stereopose_mc.filters import compiled, relnav  # noqa: E402

from scenarios import ROOT  # noqa: E402

RNG = np.random.default_rng(23)


@pytest.fixture(scope="module")
def setup_b():
    """Case B's resolved setup (camera, orbit)."""
    return setup_of(load_scenario(ROOT / "configs" / "caseB.yaml"))


def _case(B, N, ne_shift):
    """``B`` states with ``N`` points near case B's geometry and random SPD covariances of size ``n - ne_shift``
    (0: the full state's, 1: an error state's), scaled like a prior (1 deg/s, 1 m, k 0.3)."""
    q = qt.normalize(RNG.standard_normal((B, 4)))
    x = st.assemble(RNG.standard_normal((B, 3)) + [10, 60, 10], 1e-2 * RNG.standard_normal((B, 3)),
                    np.radians(RNG.standard_normal((B, 3))), q, 1.5 * RNG.standard_normal((B, N, 3)),
                    0.2 * RNG.standard_normal((B, 2)))  # fmt: skip
    m = x.shape[1] - ne_shift
    A = RNG.standard_normal((B, m, m))
    scale = np.ones(m)
    scale[st.OMEGA] = np.radians(1.0)
    scale[-2:] = 0.3
    P = (A @ A.transpose(0, 2, 1) / m + 0.1 * np.eye(m)) * scale[:, None] * scale[None, :]
    return x, P


@pytest.mark.parametrize("N", [1, 5, 24])
@pytest.mark.parametrize("ne_shift", [0, 1])
@pytest.mark.parametrize(("disparity", "focal"), [(False, 1.0), (True, 1000.0)])
def test_compiled_flow_variance_equals_numpy(setup_b, N, ne_shift, disparity, focal):
    x, P = _case(40, N, ne_shift)
    setup = dataclasses.replace(setup_b, disparity=disparity, focal=focal, baseline=0.7)
    ref = relnav.flow_linearization_variance(x, P, setup)
    got = compiled.flow_linearization_variance(x, P, setup)
    assert got.shape == ref.shape == (40, N, 9 if disparity else 8)
    assert (ref[..., 4:8] > 0).all()  # the test compares real numbers, not zeros
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=0.0)
    # a trial alone gives the same bits as in its batch
    np.testing.assert_array_equal(compiled.flow_linearization_variance(x[3:4], P[3:4], setup)[0], got[3])


@pytest.mark.parametrize("N", [1, 5, 24])
@pytest.mark.parametrize("ne_shift", [0, 1])
def test_compiled_pseudo_variance_equals_numpy(setup_b, N, ne_shift):
    x, P = _case(40, N, ne_shift)
    t = 17.0
    ref = relnav.pseudo_linearization_variance(x, P, setup_b, t)
    got = compiled.pseudo_linearization_variance(x, P, setup_b, t)
    assert got.shape == ref.shape == (40, 3)
    assert (ref > 0).all()
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=0.0)
    np.testing.assert_array_equal(compiled.pseudo_linearization_variance(x[3:4], P[3:4], setup_b, t)[0], got[3])


@pytest.mark.parametrize("N", [1, 5, 24])
@pytest.mark.parametrize("ne_shift", [0, 1])
def test_compiled_process_noise_equals_numpy(setup_b, N, ne_shift):
    """The prediction's Q with the rate's second-order term (``relnav.process_noise``), full state and error state."""
    x, P = _case(40, N, ne_shift)
    t = 17.0
    fs = dataclasses.replace(_filter(setup_b), Q_diag=RNG.uniform(1e-12, 1e-8, x.shape[1]))
    ref = relnav.process_noise(x, P, t, fs, setup_b)
    got = compiled.process_noise(x, P, t, fs, setup_b)
    assert got.shape == ref.shape == x.shape
    added = ref - fs.Q_diag
    assert (added[:, st.OMEGA] > 0).all() and not added[:, :6].any() and not added[:, 9:].any()
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=0.0)
    np.testing.assert_array_equal(compiled.process_noise(x[3:4], P[3:4], t, fs, setup_b)[0], got[3])
    # first order: Q itself, per trial
    plain = dataclasses.replace(fs, second_order=False)
    np.testing.assert_array_equal(compiled.process_noise(x, P, t, plain, setup_b), np.tile(fs.Q_diag, (40, 1)))
    np.testing.assert_array_equal(relnav.process_noise(x, P, t, plain, setup_b), np.tile(fs.Q_diag, (40, 1)))


def _filter(setup):
    """Case B's first filter setup."""
    from stereopose_mc.config.resolve import filter_setup_of

    return filter_setup_of(load_scenario(ROOT / "configs" / "caseB.yaml").filters[0], setup)


def test_compiled_second_order_propagates_nan_like_numpy(setup_b):
    x, P = _case(3, 5, 1)
    x[1, 0] = np.nan
    P[2, st.OMEGA.start, st.OMEGA.start] = np.nan
    for f, args in ((relnav.flow_linearization_variance, ()), (relnav.pseudo_linearization_variance, (5.0,))):
        with np.errstate(all="ignore"):
            ref = f(x, P, setup_b, *args)
        got = getattr(compiled, f.__name__)(x, P, setup_b, *args)
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        np.testing.assert_allclose(got[0], ref[0], rtol=1e-12)
    fs = _filter(setup_b)
    with np.errstate(all="ignore"):
        ref = relnav.process_noise(x, P, 5.0, fs, setup_b)
    got = compiled.process_noise(x, P, 5.0, fs, setup_b)
    assert np.isnan(ref[2, st.OMEGA]).all() and np.array_equal(np.isnan(got), np.isnan(ref))  # (rho: not read)
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-12)
