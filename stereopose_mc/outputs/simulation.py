"""``spmc simulate``: the truth and one set of noisy measurements of a scenario."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from ..config.resolve import setup_of
from ..config.schema import SCHEMA_VERSION, Scenario
from ..core import camera, state as st
from ..rundir.store import atomic_write_text, base_manifest, build_dir, check_replaceable, now_iso, write_json, write_parquet
from ..sim import measurements as meas
from ..sim.truth import Truth, simulate_truth

TRUTH_COLUMNS = [
    "t", "nu", "rho_x", "rho_y", "rho_z", "rho_dot_x", "rho_dot_y", "rho_dot_z",
    "omega_x", "omega_y", "omega_z", "q0", "q1", "q2", "q3",
]  # fmt: skip


def sim_units(columns) -> dict[str, str]:
    """Units of the truth and measurement columns (image channels: normalized image units, focal length 1)."""
    fixed = {"t": "s", "nu": "rad", "feature": "-", "k1": "-", "k2": "-", "d": "1"}
    prefix = (("rho_dot_", "m/s"), ("rho_", "m"), ("omega_", "rad/s"), ("alpha_", "rad/s^2"), ("q", "-"),
              ("du_", "1/s"), ("dv_", "1/s"), ("u_", "1"), ("v_", "1"))  # fmt: skip
    out = {}
    for c in columns:
        out[c] = fixed.get(c) or next((u for p, u in prefix if c.startswith(p)), "-")
    return out


def truth_frame(truth: Truth) -> pd.DataFrame:
    x = truth.x
    cols = {"t": truth.t, "nu": truth.nu}
    names = TRUTH_COLUMNS[2:]
    for j, name in enumerate(names):
        cols[name] = x[:, j]
    for j, a in enumerate("xyz"):
        cols[f"alpha_{a}"] = truth.alpha[:, j]
    k = x[:, st.k_slice(truth.n_points)]
    cols["k1"], cols["k2"] = k[:, 0], k[:, 1]
    return pd.DataFrame(cols)


def measurement_frame(t: np.ndarray, m: meas.Measurements, disparity: bool) -> pd.DataFrame:
    """One row per (time, feature); invisible features are left out."""
    K1, N, _ = m.y.shape
    names = camera.channels(disparity)
    tt, ff = np.meshgrid(t, np.arange(N), indexing="ij")
    vis = m.visible.reshape(-1)
    cols = {"t": tt.reshape(-1)[vis], "feature": ff.reshape(-1)[vis].astype(np.int32)}
    flat = m.y.reshape(K1 * N, -1)[vis]
    for j, name in enumerate(names):
        cols[name] = flat[:, j]
    return pd.DataFrame(cols)


@dataclass(frozen=True)
class SimulateSummary:
    steps: int
    features: int
    range_min: float
    range_max: float
    visible_fraction: float
    out: Path


def simulate(scenario: Scenario, out: Path, noise: bool = True, seed: int | None = None,
             overwrite: bool = False, command: list[str] | None = None, trial: int | None = None) -> SimulateSummary:
    """Write ``truth.parquet``, ``measurements.parquet``, ``config.yaml``, ``manifest.json``.

    The noise is trial 0's draw of the scenario's root seed (or ``seed``), the same
    numbers trial 0 of ``spmc run`` sees. With ``trial`` j: trial j's truth (its dispersed
    values, if the scenario has dispersions) and noise, as in ``spmc run``.
    """
    check_replaceable(out, overwrite)  # before any computation
    start = now_iso()
    root = scenario.seed if seed is None else seed
    setup = setup_of(scenario)
    dispersed_values: dict = {}
    if trial is not None and scenario.dispersions is not None and scenario.dispersions.specs:
        from ..sim import dispersions as sd

        d = sd.draw(scenario.model_copy(update={"seed": root}), [trial])
        if d.invalid[0]:
            raise ValueError(f"trial {trial} is an invalid draw: {d.invalid[0]}")
        dispersed_values = {k: float(v[0]) for k, v in d.columns.items()}
        setup = setup_of(d.truth[0])
        bt = sd.truth_of([setup], setup.times, setup.truth_rtol)
        truth = Truth(t=bt.t, nu=bt.nu[0], nu_dot=bt.nu_dot[0], nu_ddot=bt.nu_ddot[0], x=bt.x[0], alpha=bt.alpha[0])
    else:
        truth = simulate_truth(setup)
    exact = meas.noise_free(setup, truth)
    if noise:
        stream = 0 if trial is None else trial
        if dispersed_values:
            stream = int(sd.noise_streams(scenario, [trial])[0])
        draws = meas.draw_trials(root, [stream], setup.x0.size, setup.steps, setup.n_points)
        noisy = meas.noisy(setup, exact, draws)
        m = meas.Measurements(y=noisy.y[0], alpha=noisy.alpha[0], visible=exact.visible)
    else:
        m = exact

    def populate(d: Path) -> None:
        md = {"scenario": scenario.name, "schema_version": str(SCHEMA_VERSION), "seed": str(root), "noise": str(noise)}
        if trial is not None:
            md["trial"] = str(trial)
        tf = truth_frame(truth)
        for j, a in enumerate("xyz"):
            tf[f"alpha_meas_{a}"] = m.alpha[:, j]
        write_parquet(d / "truth.parquet", tf, md, units=sim_units(tf.columns))
        mf = measurement_frame(truth.t, m, setup.disparity)
        write_parquet(d / "measurements.parquet", mf, md, units=sim_units(mf.columns))
        atomic_write_text(d / "config.yaml", yaml.safe_dump(scenario.model_dump(mode="json"), sort_keys=False))
        manifest = base_manifest(command)
        manifest.update(kind="simulate", scenario=scenario.name, seed=root, noise=noise, start=start, end=now_iso())
        if trial is not None:
            manifest.update(trial=trial, dispersed_values=dispersed_values)
        write_json(d / "manifest.json", manifest)

    build_dir(out, overwrite, populate)
    rng = np.linalg.norm(camera.feature_kinematics(truth.x)[0], axis=-1)
    return SimulateSummary(
        steps=setup.steps,
        features=setup.n_points,
        range_min=float(rng.min()),
        range_max=float(rng.max()),
        visible_fraction=float(exact.visible.mean()),
        out=out,
    )
