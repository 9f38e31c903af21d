"""Tracker faults: dropped features and outliers (wrong correspondences), per trial.

Randomness: the faults of trial ``j`` come from their own stream, the generator of
``SeedSequence(seed, spawn_key=(j, FAULT_STREAM))``, a child independent of the trial's
noise stream ``spawn_key=(j,)`` (sim/measurements.py). So switching faults on or off,
or changing their probabilities, never changes the noise or the initial error of a
trial, and a trial's faults do not depend on chunking. Per trial, in this order:

1. ``(K+1, N)`` uniforms ``u_d``: the feature is dropped when ``u_d < dropout``;
2. ``(K+1, N)`` uniforms ``u_o``: it is an outlier when ``u_o < outlier_probability``
   (and it was not dropped);
3. ``(K+1, N, 3)`` uniforms: the image position ``(u_R, u_L, v)`` of a ``uniform_image``
   outlier, scaled to the image;
4. ``(K+1, N)`` uniforms: the index of the other feature a ``swapped_feature`` outlier
   takes, uniform over the other features visible at that step.

All four are drawn whatever the options (so raising a probability only adds faults;
the same numbers decide them).

Outlier models:

- ``uniform_image``: a spurious, static point: ``u_R``, ``u_L`` uniform over the image
  width and ``v`` over its height (same row in both rectified images), image
  velocities zero, disparity ``u_L - u_R``; the channel noise is added on top as for any
  feature;
- ``swapped_feature``: the tracker follows another feature of the target: every
  channel is that feature's (noise included).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..config.sensor import SensorSetup

Array = NDArray[np.float64]
FAULT_STREAM = 0xFA  # second entry of the spawn key of the fault stream


def fault_rng(seed: int, trial: int) -> np.random.Generator:
    """The fault generator of one trial (see the module docstring)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(int(trial), FAULT_STREAM)))


@dataclass(frozen=True)
class Faults:
    """The faults of a batch of trials."""

    kept: Array  # (B, K+1, N) bool: not dropped by the tracker (True for features out of view)
    outlier: Array  # (B, K+1, N) bool


def draw_faults(seed: int, trials, steps: int, n_points: int) -> tuple[Array, Array, Array, Array]:
    """The four uniform draws (stacked over trials) in the documented order."""
    shape = (steps + 1, n_points)
    ud, uo, up, us = [], [], [], []
    for j in trials:
        rng = fault_rng(seed, j)
        ud.append(rng.random(shape))
        uo.append(rng.random(shape))
        up.append(rng.random(shape + (3,)))
        us.append(rng.random(shape))
    return np.array(ud), np.array(uo), np.array(up), np.array(us)


def apply_faults(sensor: SensorSetup, seed: int, trials, y: Array, exact: Array, visible: Array
                 ) -> tuple[Array, Faults]:  # fmt: skip
    """Faulty measurements ``y (B, K+1, N, C)`` (a new array) and the faults.

    ``y`` are the noisy measurements of the trials, ``exact (K+1, N, C)`` (or per trial
    ``(B, K+1, N, C)``) the noise-free ones (``y - exact`` is the noise a ``uniform_image``
    outlier keeps), ``visible
    (K+1, N)`` the features in view (a ``swapped_feature`` outlier takes a visible one).
    """
    B, K1, N, C = y.shape
    ud, uo, up, us = draw_faults(seed, trials, K1 - 1, N)
    kept = (ud >= sensor.dropout) | ~visible[None]  # a feature out of view is not "dropped" (visibility masks it)
    outlier = kept & (uo < sensor.outlier_probability) & visible[None]
    y0, y = y, y.copy()
    if not outlier.any():
        return y, Faults(kept, outlier)
    if sensor.outlier_model == "uniform_image":
        u0, u1, v0, v1 = sensor.image_bounds()
        u_r = u0 + (u1 - u0) * up[..., 0]
        u_l = u0 + (u1 - u0) * up[..., 1]
        v = v0 + (v1 - v0) * up[..., 2]
        fake = np.zeros((B, K1, N, C))
        fake[..., 0], fake[..., 1], fake[..., 2], fake[..., 3] = u_r, v, u_l, v
        if C > 8:
            fake[..., 8] = u_l - u_r
        y[outlier] = fake[outlier] + (y0 - (exact[None] if exact.ndim == 3 else exact))[outlier]
    else:
        for b, k, i in zip(*np.nonzero(outlier)):
            others = np.flatnonzero(visible[k])
            others = others[others != i]
            if others.size:
                j = others[min(int(us[b, k, i] * others.size), others.size - 1)]
                y[b, k, i] = y0[b, k, j]
            else:
                outlier[b, k, i] = False
    return y, Faults(kept, outlier)
