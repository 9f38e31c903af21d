"""The Earth behind the target (``measurements.images.background: earth``, docs/images.md).

A sphere of radius ``R_EARTH_M`` centred, in the leader's frame ``L``, at ``[-r, 0, 0]`` (``r``:
the leader's distance from the Earth's centre at that step; ``L``'s ``x`` is radially outward).
A ray from ``o`` along the unit ``d`` meets it at the smaller root ``t = b - sqrt(b^2 - (|c - o|^2 -
R^2))``, ``b = d . (c - o)``, when the discriminant is not negative and ``t > 0``. Radiance
(relative, as the target's): ``albedo max(0, n . s)``, ``n`` the sphere's outward normal, ``s``
toward the Sun in ``L`` (the target's Sun); the target casts no shadow on the Earth.

The albedo is a seeded equirectangular map (longitude ``MAP_COLS``, latitude ``MAP_ROWS``
texels) fixed in the leader orbit's perifocal frame (``v^P = Rz(nu) v^L``, no Earth rotation;
the orbit runs along the map's equator): ocean ``OCEAN``, land ``LAND`` where a smooth noise
field is high, clouds blended towards ``CLOUD`` by a second one. It is one material of a
``texture.Atlas`` (a tile ``2 pi R`` by ``pi R``), sampled with the target's mip-mapping.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import texture

Array = NDArray[np.float64]

R_EARTH_M = 6378137.0
MAP_ROWS, MAP_COLS = 512, 1024  # ~39 km per texel at the equator
OCEAN, LAND, CLOUD = 0.06, 0.2, 0.6  # albedos
LAND_SCALE, CLOUD_SCALE = 12.0, 5.0  # noise filter sigmas (texels): continents, cloud systems


@dataclass(frozen=True)
class Earth:
    atlas: texture.Atlas  # one material: the albedo map, a tile 2 pi R x pi R (longitude x latitude)
    radius: float = R_EARTH_M


@dataclass(frozen=True)
class EarthView:
    """The Earth at one step: its centre in ``L`` and ``to_map`` (``v^P = to_map v^L``)."""

    earth: Earth
    centre_L: Array
    to_map: Array


def _smoothstep(x: Array, lo: float, hi: float) -> Array:
    u = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def earth(rng: np.random.Generator) -> Earth:
    """The albedo map drawn from ``rng``: land where a noise field exceeds ~0.5 sigma (about a third of the
    surface), clouds where a second one exceeds ~0.3 sigma, both with soft edges."""
    land = _smoothstep(texture.band_noise(rng, MAP_COLS, LAND_SCALE)[:MAP_ROWS], 0.4, 0.6)
    cloud = _smoothstep(texture.band_noise(rng, MAP_COLS, CLOUD_SCALE)[:MAP_ROWS], 0.3, 1.2)
    albedo = (1.0 - cloud) * (OCEAN + (LAND - OCEAN) * land) + cloud * CLOUD
    size = (2.0 * np.pi * R_EARTH_M, np.pi * R_EARTH_M)
    return Earth(texture.Atlas((texture.pyramid(albedo.astype(np.float32)),), (size,)))


def view(e: Earth, r: float, nu: float) -> EarthView:
    """The Earth seen from a leader at distance ``r`` from its centre and true anomaly ``nu``."""
    c, s = np.cos(nu), np.sin(nu)
    return EarthView(e, np.array([-float(r), 0.0, 0.0]), np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))


def intersect(o: Array, d: Array, centre: Array, radius: float) -> Array:
    """Distance ``t (m,)`` along unit rays ``o + t d`` (``o (3,)``, ``d (m, 3)``) to a sphere; nan on a miss."""
    oc = np.asarray(centre, float) - np.asarray(o, float)
    b = d @ oc
    disc = b * b - (oc @ oc - radius * radius)
    with np.errstate(invalid="ignore"):
        t = b - np.sqrt(disc)
    return np.where((disc >= 0.0) & (t > 0.0), t, np.nan)


def radiance(ev: EarthView, o: Array, d: Array, sun: Array, pixel_rad: float) -> Array:
    """Radiance ``(m,)`` of rays from ``o (3,)`` along unit ``d (m, 3)`` in ``L`` (0 where they miss the Earth);
    ``pixel_rad``: the angle between neighbouring rays (the footprint at distance ``t`` is ``t pixel_rad``)."""
    t = intersect(o, d, ev.centre_L, ev.earth.radius)
    out = np.zeros(len(d))
    hit = np.isfinite(t)
    if not hit.any():
        return out
    p = o + t[hit, None] * d[hit]
    n = (p - ev.centre_L) / ev.earth.radius
    q = n @ ev.to_map.T
    a = np.mod(np.arctan2(q[:, 1], q[:, 0]), 2.0 * np.pi) * ev.earth.radius
    b = (np.arcsin(np.clip(q[:, 2], -1.0, 1.0)) + 0.5 * np.pi) * ev.earth.radius
    foot = texture.slant_footprint(t[hit] * pixel_rad, n, d[hit])
    out[hit] = ev.earth.atlas.sample(0, a, b, foot) * np.clip(n @ sun, 0.0, None)
    return out
