"""``initial_estimate: measurements`` on case B: a positive definite P0 whose claims the errors bear out."""

import numpy as np
import yaml
from scipy import stats

from stereopose_mc.config import load_scenario_text
from stereopose_mc.core import errorstate as es
from stereopose_mc.mc import engine
from stereopose_mc.filters.initialization import measurement_start
from stereopose_mc.sim import measurements as meas

from scenarios import scenario_dict


def test_measurement_start_is_positive_definite_and_honest_for_the_fitted_blocks():
    scn = load_scenario_text(yaml.safe_dump(scenario_dict("caseB", initial_estimate={"method": "measurements"})))
    pr = engine.prepare(scn)
    s = pr.setup
    M = 200
    d = meas.draw_trials(scn.seed, np.arange(M), s.x0.size, s.steps, s.n_points)
    noisy = meas.noisy(s, pr.exact, d)
    x_draw = meas.initial_estimates(s, d)
    x0, P0 = measurement_start(s, pr.filters[0], noisy.y[:, 0], pr.exact.visible[0], x_draw)
    assert np.all(np.linalg.eigvalsh(P0)[:, 0] > 0)
    # q and k are the prior draw's; the centroid replaces rho
    np.testing.assert_allclose(x0[:, 9:13], x_draw[:, 9:13], rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(x0[:, :3].mean(0), pr.truth.x[0, :3], atol=0.5)
    v = es.nees_all(es.estimation_error(x0, pr.truth.x[0]), es.to_error_covariance(x0, P0), x0)
    # omega comes only from the flow fit: its NEES is chi-square with 3 dof
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 3 * M) / M
    assert lo < v["nees_omega"].mean() < hi, v["nees_omega"].mean()
    # the centre of mass is claimed at 1 m about the centroid, which is 0.17 m from it here: pessimistic
    assert v["nees_rho"].mean() < 0.1
    # the whole start (the neglected cross terms between points' triangulation errors) within 1.5 x its dof
    assert v["nees"].mean() < 1.5 * 29
