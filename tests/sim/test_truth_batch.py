"""Per-trial truth propagated as a batch (``simulate_truth_batch``): accuracy and batch independence."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from reference import inertial
from reference.truth_setups import ECCENTRIC, elements_of, setup_from

from stereopose_mc.core import quaternion as qt
from stereopose_mc.core import state as st
from stereopose_mc.core.orbit import Orbit
from stereopose_mc.sim.truth import simulate_truth, simulate_truth_batch


@pytest.fixture(scope="module")
def setup():
    return setup_from(**ECCENTRIC)


def test_batched_truth_matches_inertial_reference(setup):
    """Each trial of a batch (different rate, range and orbit) against the independent inertial propagation."""
    x0 = np.repeat(setup.x0[None], 3, axis=0)
    x0[1, st.OMEGA] *= -1.5  # faster, other sense
    x0[2, st.RHO] = [-5.0, 40.0, 12.0]
    orbits = [setup.orbit, setup.orbit, dataclasses.replace(setup.orbit, e=0.05, a=7200e3, nu0=1.0)]
    truth = simulate_truth_batch(x0, orbits, setup.times, setup.truth_rtol)
    assert truth.x.shape == (3, setup.times.size, setup.x0.size) and truth.alpha.shape == (3, setup.times.size, 3)
    moments = np.asarray(ECCENTRIC["target"]["inertia_kgm2"], dtype=float)
    for b in range(3):
        el = dataclasses.replace(elements_of(setup), a=orbits[b].a, e=orbits[b].e, nu0=orbits[b].nu0)
        ref = inertial.propagate(el, x0[b, st.RHO], x0[b, st.RHO_DOT], x0[b, st.OMEGA], x0[b, st.QUAT], moments,
                                 setup.times)  # fmt: skip
        x = truth.x[b]
        # the single-trial truth's bounds (docs/truth-accuracy.md)
        assert np.linalg.norm(x[:, st.RHO] - ref.rho, axis=-1).max() < 1e-6
        assert np.linalg.norm(x[:, st.RHO_DOT] - ref.rho_dot, axis=-1).max() < 1e-9
        assert np.linalg.norm(x[:, st.OMEGA] - ref.omega, axis=-1).max() < 1e-10
        assert qt.error_angle(ref.q, x[:, st.QUAT]).max() < 1e-8


def test_batched_truth_agrees_with_single_truth(setup):
    """Same trial, two integrators (scipy's solve_ivp vs the batched DOP853): states, alpha and nu agree."""
    one = simulate_truth(setup)
    b = simulate_truth_batch(setup.x0[None], [setup.orbit], setup.times, setup.truth_rtol)
    assert np.abs(b.x[0] - one.x).max() < 1e-8
    assert np.abs(b.alpha[0] - one.alpha).max() < 1e-12
    assert np.abs(b.nu[0] - one.nu).max() < 1e-12
    assert np.abs(b.nu_dot[0] - one.nu_dot).max() < 1e-15


def test_trial_truth_does_not_depend_on_its_batch(setup):
    """A trial's truth is the same bits alone or among others (each trial has its own step size)."""
    rng = np.random.default_rng(0)
    x0 = np.repeat(setup.x0[None], 5, axis=0)
    x0[:, st.OMEGA] += rng.normal(0, 0.02, (5, 3))
    orbits = [Orbit(a=8e6 + 1e4 * i, e=0.01 * i, nu0=0.1 * i) for i in range(5)]
    t = setup.times[:30]
    many = simulate_truth_batch(x0, orbits, t, 1e-12)
    for b in (0, 3):
        alone = simulate_truth_batch(x0[b : b + 1], orbits[b : b + 1], t, 1e-12)
        assert np.array_equal(alone.x[0], many.x[b]) and np.array_equal(alone.alpha[0], many.alpha[b])
