"""``studies.observability``: the filter-state Gramian of the bundled thesis cases.

References: an empirical observability Gramian from central differences of the NONLINEAR
simulator (truth integrator + camera model + pseudo-measurement), which uses neither the
analytic Jacobians nor the expm chain; the exact invariance of h under the quaternion's
scale; the second-order convergence of the chained-expm transition in dt; and the
physics of the thesis cases (k is seen only through the rotational dynamics, whose effect
grows with the spin rate; the pseudo-measurement sees it directly).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stereopose_mc.config import load_scenario
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.core import camera
from stereopose_mc.core import observability as ob
from stereopose_mc.core import state as st
from stereopose_mc.core.inertia import h_pseudo
from stereopose_mc.studies.observability import (
    analyse,
    filter_gramian,
    filter_state_observability,
    measurement_model,
    with_duration,
)
from stereopose_mc.sim.truth import integrate

from scenarios import CONFIGS

HORIZON = 30.0


def _setup(case: str, duration: float = HORIZON, dt: float | None = None):
    s = setup_of(load_scenario(CONFIGS / f"{case}.yaml"))
    if dt is not None:
        s = dataclasses.replace(s, dt=dt)
    return with_duration(s, duration)


@pytest.fixture(scope="module")
def results():
    return {
        c: filter_state_observability(load_scenario(CONFIGS / f"{c}.yaml"), HORIZON, weak=5)
        for c in ("caseB", "caseE", "caseF")
    }


@pytest.mark.parametrize("case", ["caseE", "caseB"])
def test_gramian_equals_the_empirical_gramian_of_the_nonlinear_simulator(case):
    setup = _setup(case)
    g = filter_gramian(setup)
    tr = g.truth
    _, w = measurement_model(setup, tr)
    scale = np.sqrt(setup.P0_diag)

    def measurements(x0):
        x = integrate(x0, tr.t, setup, 1e-12)
        y = camera.h_features(x, setup.baseline, setup.disparity, setup.focal).reshape(tr.t.size, -1)
        if setup.pseudo:  # the observed alpha is the true one, whatever the state
            y = np.concatenate([y, h_pseudo(x, tr.alpha, tr.nu_dot, tr.nu_ddot)], axis=1)
        return y

    cols = []
    for i in range(scale.size):
        e = np.zeros(scale.size)
        e[i] = 1e-4 * scale[i]
        cols.append((measurements(tr.x[0] + e) - measurements(tr.x[0] - e)) / (2 * e[i]))
    O = np.stack(cols, axis=-1)  # (K+1, m, n)
    W_emp = np.einsum("kmi,km,kmj->ij", O, w, O)
    Ws, We = (scale[:, None] * W * scale for W in (g.W, W_emp))
    assert np.linalg.norm(Ws - We) < 1e-4 * np.linalg.norm(We)
    # the weak part agrees too: what the measurements alone say about k
    ks = st.k_slice(setup.n_points)
    mask = np.zeros(scale.size, bool)
    mask[ks] = True
    sk = [np.sqrt(np.diag(ob.crlb_covariance(W, setup.P0_diag, mask))[ks]) for W in (g.W, W_emp)]
    np.testing.assert_allclose(sk[0], sk[1], rtol=1e-3)


def test_quaternion_norm_direction_is_unobservable(results):
    r = results["caseE"]
    assert r["q_norm"]["max_rel_H_eq"] < 1e-14  # h is neutral to q's scale at every step
    assert r["q_norm"]["relative_rayleigh"] < r["roundoff_floor"] / r["lambda_max"]  # zero to round-off
    assert "q_norm" in r["projected_out"] and len(r["eigenvalues"]) == len(r["state_names"]) - 4


def test_quaternion_norm_residual_is_the_second_order_discretization_of_phi():
    # fast spin: the chained expm(F(t_k) dt) moves e_q off e_q(t) by O(dt^2) per step;
    # the relative Rayleigh quotient of e_q then falls as dt^2
    rq = [analyse(filter_gramian(_setup("caseF", dt=dt)))["q_norm"]["relative_rayleigh"] for dt in (1.0, 0.5)]
    assert rq[0] / rq[1] == pytest.approx(4.0, rel=0.05)


def _k_dominated(r):
    return [d for d in r["weak_directions"] if d["k_share"] >= 0.5]


def test_case_e_k_is_weak_compared_with_cases_f_and_b(results):
    b, e, f = results["caseB"], results["caseE"], results["caseF"]
    # measurements alone (prior on everything but k): case E's k is much less determined
    sb, se, sf = (np.array([r["k_sigma_measurements_only"][k] for k in ("k1", "k2")]) for r in (b, e, f))
    assert np.all(se > 4.0 * sb) and np.all(sb > 4.0 * sf)
    # in case E the k axes are among the five weakest directions, named by state element
    names = set().union(*(d["components"] for d in e["weak_directions"]))
    assert {"k1", "k2"} <= names
    ke = min(d["relative"] for d in _k_dominated(e))
    kb = min(d["relative"] for d in _k_dominated(b))
    assert ke < kb / 30.0
    # case F: its weak directions that involve k are far stronger than case E's
    kf = [d["relative"] for d in f["weak_directions"] if d["k_share"] >= 0.1]
    assert kf and min(kf) > 1e3 * ke


def test_gauge_is_weak_and_stronger_at_fast_spin(results):
    e, f = results["caseE"], results["caseF"]
    assert "gauge_x" in e["projected_out"]
    assert all(d["gauge_share"] < 0.01 for d in e["weak_directions"])  # projected out
    assert max(e["gauge_relative_eigenvalues"]) < 1e-12  # seen only through the slow dynamics
    assert max(f["gauge_relative_eigenvalues"]) > 100 * max(e["gauge_relative_eigenvalues"])
    kept = analyse(filter_gramian(_setup("caseE")), fix_gauge=False)
    assert kept["projected_out"] == ["q_norm"] and len(kept["eigenvalues"]) == len(kept["state_names"]) - 1
    assert kept["weak_directions"][0]["gauge_share"] > 0.9


def test_crlb_is_below_the_prior_and_reports_every_element(results):
    r = results["caseB"]
    setup = _setup("caseB")
    sig = np.array([r["crlb_sigma"][k] for k in r["state_names"]])
    assert np.all(sig <= np.sqrt(setup.P0_diag) * (1 + 1e-9))
    assert r["crlb_sigma"]["rho_y"] < 1.0 and r["crlb_sigma"]["k1"] < 1.0
    assert r["scaling"]["q0"] == pytest.approx(np.sqrt(1e-5))


def test_with_duration():
    s = _setup("caseE", 100.0)
    assert with_duration(s, 12.0).steps == 12 and with_duration(s, None) is s
    with pytest.raises(ValueError):
        with_duration(s, 0.2)
