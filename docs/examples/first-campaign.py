# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # A first campaign from Python
#
# Build a scenario, run a Monte Carlo campaign, look at the errors over time and ask what
# drives the outcome. Open as a notebook with `jupytext --to ipynb docs/examples/first-campaign.py`
# (or run it as a script). The test suite runs it on a few short trials
# (`tests/docs/test_examples.py`), so it stays in step with the API (docs/api.md).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np

from stereopose_mc import api

TRIALS = int(os.environ.get("SPMC_EXAMPLE_TRIALS", "100"))
DURATION_S = float(os.environ.get("SPMC_EXAMPLE_DURATION_S", "100"))  # thesis case B: 100 s

# %% [markdown]
# ## The scenario
# Thesis case B (100 s; the test runs it shorter), error window from 10 s (or half a shorter run).
# `api.edit` takes the key paths of `spmc sweep --set`; the result is validated like a file.

# %%
scn = api.load("configs/caseB.yaml")
scn = api.edit(scn, {"time.duration_s": DURATION_S, "time.error_window_start_s": min(10.0, DURATION_S / 2)})
print(scn.name, [f.label for f in scn.filters], scn.time)

# %% [markdown]
# ## The campaign
# `api.run` writes an ordinary run directory and returns a `Run`; its tables are pandas DataFrames
# with the unit of each column in `.attrs["units"]`.

# %%
run = api.run(scn, trials=TRIALS, out="runs/first-campaign", overwrite=True)
print(run.summary())
trials, ts = run.trials, run.timeseries
units = ts.attrs["units"]
trials.head()

# %% [markdown]
# ## Errors against their 3-sigma
# The standard Monte Carlo plot: every trial's error on each axis (thin lines) and the filter's own
# +-3 sigma (the median over trials of `sigma_<axis>`, red). A consistent filter keeps about 99.7 %
# of the errors inside. Trials the filter lost stop at their last step; the count is in the title.

# %%
label0 = scn.filters[0].label
kept = trials.loc[(trials["filter"] == label0) & ~trials["lost"], ["trial", "filter"]]
g = ts.merge(kept, on=["trial", "filter"])
axes = ["rho_x", "rho_y", "rho_z", "theta_x", "theta_y", "theta_z"]
fig, axs = plt.subplots(2, 3, figsize=(12, 6), sharex=True)
for ax, a in zip(axs.ravel(), axes):
    for _, tr in g.groupby("trial"):
        ax.plot(tr["t"], tr[f"err_{a}"], lw=0.5, color="0.6")
    s3 = 3 * g.groupby("t")[f"sigma_{a}"].median()
    ax.plot(s3.index, s3, "r", s3.index, -s3, "r")
    late = g[g["t"] >= scn.time.error_window_start_s]
    inside = float((late[f"err_{a}"].abs() <= 3 * late[f"sigma_{a}"]).mean())
    ax.set_title(f"{a} [{units[f'err_{a}']}]: {inside:.1%} inside 3 sigma")
    ax.set_xlabel("t [s]")
fig.suptitle(f"{scn.name}, {label0}: {len(kept)} trials not lost of {TRIALS}")
fig.tight_layout()

# %% [markdown]
# ## What drives the outcome?
# Each trial starts from its own initial estimate error (step 0 of the time series). Does a larger
# initial error mean a larger error later, or divergence? Spearman's rank correlation between the
# initial and the window-mean error, per filter, with the trial count it rests on.

# %%
from scipy.stats import spearmanr  # noqa: E402

names = ["e_rho", "e_rho_dot", "e_omega", "e_theta", "e_k1", "e_k2"]

start = ts[ts["step"] == 0][["trial", "filter", *names]].rename(columns={n: f"initial_{n}" for n in names})
outcome = trials.merge(start, on=["trial", "filter"])
for label, g in outcome.groupby("filter", sort=False):
    good = g[~g["lost"]]
    rho = {n: spearmanr(good[f"initial_{n}"], good[n]).statistic if len(good) > 2 else np.nan for n in names[:4]}
    print(f"{label}: {len(good)} not lost of {len(g)}; lost {int(g['lost'].sum())}; "
          + ", ".join(f"rank corr. {n} {v:+.2f}" for n, v in rho.items()))

fig, axs = plt.subplots(1, 2, figsize=(10, 4))
for ax, name in zip(axs, ["e_rho", "e_theta"]):
    for label, g in outcome.groupby("filter", sort=False):
        ax.scatter(g[f"initial_{name}"], g[name].where(~g["lost"]), s=12, label=label)
        ax.scatter(g.loc[g["lost"], f"initial_{name}"], np.full(int(g["lost"].sum()), g[name].max()),
                   marker="x", color="k")
    ax.set_xlabel(f"initial {name} [{units[name]}]")
    ax.set_ylabel(f"window-mean {name} [{units[name]}] (x: lost)")
    ax.set_yscale("log")
axs[0].legend()
fig.tight_layout()

# %% [markdown]
# ## Keep going
# `run.rerun(trial)` reproduces one trial from its seed; `run.report()` writes the HTML report;
# `run.export("mat")` writes a MATLAB file with a struct per table (units included).

# %%
worst = int(outcome.sort_values("e_rho").iloc[-1]["trial"])
again = run.rerun(worst)
print(f"trial {worst} again: identical = {again.identical}")
print(run.export("mat", overwrite=True))
