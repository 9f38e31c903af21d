"""The image sensor: exposure, optional defocus, photon (Poisson) and read noise, digitization.

For a relative radiance ``L`` (renderer.py: 1 for a white surface facing the Sun) the mean
signal is ``mu = exposure * full_well * L`` electrons (``exposure``: the fraction of the full
well a white sunlit surface fills). Optional defocus blurs ``L`` with a Gaussian of
``defocus_sigma_px`` before the noise (the optics blur light, not noise). The electrons are

    e = Poisson(mu) + N(0, read_noise^2)        (mean mu, variance mu + read_noise^2)

and the digital number ``DN = round(clip(e, 0, full_well) * (2^bits - 1) / full_well)``
(uniform quantization adds a variance of 1/12 DN^2). All randomness comes from the passed
``numpy.random.Generator``; a render can be cached and exposed many times with different
generators (repeated passes of the same geometry).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SensorModel:
    exposure: float = 0.8
    full_well_e: float = 20000.0
    read_noise_e: float = 10.0
    bits: int = 8
    defocus_sigma_px: float = 0.0

    @property
    def gain(self) -> float:
        """Digital numbers per electron."""
        return (2**self.bits - 1) / self.full_well_e


def mean_electrons(radiance: Array, sensor: SensorModel) -> Array:
    """Noise-free signal in electrons, after the optional defocus blur."""
    r = np.asarray(radiance, dtype=float)
    if sensor.defocus_sigma_px > 0.0:
        r = cv2.GaussianBlur(r, (0, 0), sensor.defocus_sigma_px, borderType=cv2.BORDER_REFLECT)
    return sensor.exposure * sensor.full_well_e * r


def electrons(radiance: Array, sensor: SensorModel, rng: np.random.Generator) -> Array:
    """Photon (Poisson) plus read (Gaussian) noise on the mean signal, in electrons."""
    mu = mean_electrons(radiance, sensor)
    return rng.poisson(mu).astype(float) + sensor.read_noise_e * rng.standard_normal(mu.shape)


def digitize(e: Array, sensor: SensorModel) -> NDArray:
    """Digital numbers (uint8 up to 8 bits, else uint16), saturating at the full well."""
    dn = np.rint(np.clip(e, 0.0, sensor.full_well_e) * sensor.gain)
    return dn.astype(np.uint8 if sensor.bits <= 8 else np.uint16)


def expose(radiance: Array, sensor: SensorModel, rng: np.random.Generator) -> NDArray:
    """The camera's image of a radiance map: noise drawn from ``rng``, then digitized."""
    return digitize(electrons(radiance, sensor, rng), sensor)
