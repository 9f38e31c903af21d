"""Truth trajectories and noisy measurements of a scenario."""

from .measurements import Measurements, noise_free, trial_rng
from .truth import Truth, simulate_truth

__all__ = ["Measurements", "Truth", "noise_free", "simulate_truth", "trial_rng"]
