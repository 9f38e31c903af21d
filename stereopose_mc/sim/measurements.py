"""Noisy stereo measurements and angular accelerations, one draw per trial.

Randomness: trial ``j`` of a scenario with root seed ``s`` draws from
``numpy.random.default_rng(SeedSequence(s, spawn_key=(j,)))``, the ``j``-th child of
the root, in this fixed order:

1. ``z0 ~ N(0, I_n)``: the initial estimation error (scaled by ``sqrt(P0)``);
2. ``(K+1, N, 9)`` standard normals for the image channels (all nine, disparity
   included, whether or not it is enabled, so the other channels do not change when it is);
3. ``(K+1, 3)`` standard normals for the angular acceleration.

So a trial's numbers never depend on chunking, ``--jobs`` or order, and any single
trial can be rerun alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import Setup
from ..core import camera, state as st
from . import visibility
from .truth import Truth

Array = NDArray[np.float64]
N_IMAGE_CHANNELS = 9


def trial_rng(seed: int, trial: int) -> np.random.Generator:
    """The generator of one trial: the ``trial``-th ``SeedSequence`` child of ``seed``."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(trial,)))


@dataclass(frozen=True)
class Measurements:
    """Measurements of one or more trials (leading axes ``...``)."""

    y: Array  # (..., K+1, N, C) image coordinates and velocities (+ disparity)
    alpha: Array  # (..., K+1, 3) measured angular acceleration in L
    visible: Array  # (K+1, N) shared visibility (from the truth)


def noise_free(setup: Setup, truth: Truth) -> Measurements:
    """The exact measurements of the truth (no noise)."""
    y = camera.h_features(truth.x, setup.baseline, setup.disparity, setup.focal)
    vis = visibility.visible(setup, truth.x)
    return Measurements(y=y, alpha=truth.alpha.copy(), visible=vis)


def channel_sigmas(setup: Setup) -> Array:
    """Per-channel noise standard deviations of the truth (8 or 9,)."""
    s = [setup.sigma_image] * 4 + [setup.sigma_flow] * 4
    if setup.disparity:
        s.append(setup.sigma_disparity)
    return np.asarray(s)


@dataclass(frozen=True)
class TrialDraws:
    """The standard normal draws of a batch of trials, in the documented order."""

    z0: Array  # (B, n)
    image: Array  # (B, K+1, N, 9)
    alpha: Array  # (B, K+1, 3)


def draw_trials(seed: int, trials, n: int, steps: int, n_points: int) -> TrialDraws:
    """Draws of the given trial indices, each from its own generator."""
    z0, img, al = [], [], []
    for j in trials:
        rng = trial_rng(seed, int(j))
        z0.append(rng.standard_normal(n))
        img.append(rng.standard_normal((steps + 1, n_points, N_IMAGE_CHANNELS)))
        al.append(rng.standard_normal((steps + 1, 3)))
    return TrialDraws(np.array(z0), np.array(img), np.array(al))


def noisy(setup: Setup, exact: Measurements, draws: TrialDraws) -> Measurements:
    """Exact measurements plus the trials' noise, ``(B, K+1, ...)``."""
    sig = channel_sigmas(setup)
    C = sig.size
    y = exact.y[None] + draws.image[..., :C] * sig
    alpha = exact.alpha[None] + setup.sigma_alpha * draws.alpha
    return Measurements(y=y, alpha=alpha, visible=exact.visible)


def initial_estimates(setup: Setup, draws: TrialDraws, x0: Array | None = None) -> Array:
    """``x_hat(0) ~ N(x0, P0)`` with the quaternion renormalized, ``(B, n)``.

    ``x0``: the centre, ``(n,)`` or per trial ``(B, n)``; default the true ``setup.x0``.
    """
    x = (setup.x0[None] if x0 is None else x0) + np.sqrt(setup.P0_diag) * draws.z0
    q = x[:, st.QUAT]
    x[:, st.QUAT] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return x
