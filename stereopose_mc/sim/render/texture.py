"""Seeded procedural albedo textures of a spacecraft's surface and their mip-map sampling.

Three materials, each a periodic square tile of ``TILE`` texels (albedo in [0, 1]):

- ``MLI``: crinkled multilayer insulation, band-limited noise at three scales (3, 10 and 40
  texels) around a mid grey, with bright tape seams;
- ``EQUIPMENT``: boxes, plates and bolts, random rectangles and discs on a darker base;
- ``CELLS``: solar cells, dark cells on a bright interconnect grid with thin bus bars.

A texel is ``TEXEL_M`` metres on the body (the tile repeats every ``TILE * TEXEL_M`` m).
Or one tile read from an image file (:func:`file_atlas`: grayscale, ``w x h`` metres).
Sampling is trilinear over a mip-map (Williams 1983): level ``L = log2(footprint / texel)``
(``texel``: the level-0 texel's larger side in metres) for a pixel footprint on the surface,
bilinear within the levels ``floor(L)`` and ``floor(L) + 1`` and linear between them, so a
texture finer than a pixel is averaged, not aliased (aliasing would make the rendered texture
flicker and the tracker drift).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates

from ...config.texturefile import read_albedo

Array = NDArray[np.float64]

MLI, EQUIPMENT, CELLS = 0, 1, 2
MATERIALS = ("mli", "equipment", "cells")
TILE = 1024  # texels per tile side (a power of two: the mip levels halve it exactly)
TEXEL_M = 0.002  # metres per texel at level 0
LEVELS = 8  # mip levels 0..7 (the coarsest 8 x 8 texels)


def band_noise(rng: np.random.Generator, n: int, scale: float) -> NDArray[np.float32]:
    """Periodic Gaussian-filtered white noise ``(n, n)`` of unit standard deviation (filter sigma ``scale`` texels).

    Filtered in the Fourier domain (``exp(-2 pi^2 s^2 |f|^2)``), so the tile wraps seamlessly.
    """
    w = rng.standard_normal((n, n))
    f = np.fft.fftfreq(n)
    g = np.exp(-2.0 * np.pi**2 * scale**2 * (f[:, None] ** 2 + np.fft.rfftfreq(n)[None, :] ** 2))
    out = np.fft.irfft2(np.fft.rfft2(w) * g, s=(n, n))
    return (out / out.std()).astype(np.float32)


def mli_tile(rng: np.random.Generator, n: int = TILE) -> NDArray[np.float32]:
    t = 0.55 + 0.10 * band_noise(rng, n, 3.0) + 0.08 * band_noise(rng, n, 10.0) + 0.06 * band_noise(rng, n, 40.0)
    for _ in range(3):  # tape seams, 8 texels wide
        k = int(rng.integers(n))
        if rng.random() < 0.5:
            t[:, k : k + 8] = 0.8
        else:
            t[k : k + 8, :] = 0.8
    return np.clip(t, 0.05, 0.95)


def equipment_tile(rng: np.random.Generator, n: int = TILE) -> NDArray[np.float32]:
    t = (0.4 + 0.03 * band_noise(rng, n, 2.0)).astype(np.float32)
    for _ in range(60):  # boxes and plates with a darker rim
        x, y = (int(v) for v in rng.integers(0, n, 2))
        w, h = (int(v) for v in rng.integers(15, 160, 2))
        a = float(rng.uniform(0.1, 0.85))
        cv2.rectangle(t, (x, y), (x + w, y + h), a, thickness=-1)
        cv2.rectangle(t, (x, y), (x + w, y + h), 0.5 * a, thickness=3)
    for _ in range(150):  # bolts
        x, y = (int(v) for v in rng.integers(0, n, 2))
        cv2.circle(t, (x, y), int(rng.integers(3, 7)), 0.9, thickness=-1)
    return np.clip(t, 0.05, 0.95)


def cells_tile(rng: np.random.Generator, n: int = TILE) -> NDArray[np.float32]:
    cw, ch, gap = 32, 21, 3  # a cell 6.4 x 4.2 cm with a 6 mm interconnect at 2 mm per texel
    rows, cols = np.mgrid[0:n, 0:n]
    shade = rng.uniform(0.15, 0.22, size=(n // ch + 1, n // cw + 1)).astype(np.float32)
    t = shade[rows // ch, cols // cw]
    t[(rows % 7 == 3) & (rows % ch > gap)] = 0.45  # bus bars
    t[(rows % ch < gap) | (cols % cw < gap)] = 0.7  # interconnect grid
    return t.astype(np.float32)


@dataclass(frozen=True)
class Atlas:
    """Mip pyramids ``pyramids[material][level]`` of the material tiles; ``size_m[material] = (w, h)``: the
    tile's width (along ``a``, its columns) and height (along ``b``, its rows) in metres (None: every tile is
    ``TILE * TEXEL_M`` square)."""

    pyramids: tuple[tuple[NDArray[np.float32], ...], ...]
    size_m: tuple[tuple[float, float], ...] | None = None

    def texel_m(self, material: int, level: int) -> tuple[float, float]:
        """Width and height of a texel of ``level`` in metres (the tile's size over the level's texels)."""
        w, h = (TILE * TEXEL_M,) * 2 if self.size_m is None else self.size_m[material]
        rows, cols = self.pyramids[material][level].shape
        return w / cols, h / rows

    def sample(self, material: int, a: Array, b: Array, footprint_m: Array) -> Array:
        """Albedo at texture coordinates ``a, b`` (metres on the tile, periodic) for a pixel footprint (m)."""
        n = len(self.pyramids[material])
        lev = np.clip(np.log2(np.maximum(footprint_m, 1e-12) / max(self.texel_m(material, 0))), 0.0, n - 1.0)
        lo = np.floor(lev).astype(int)
        w = lev - lo
        out = np.empty_like(a)
        for L in np.unique(lo):
            m = lo == L
            sa, sb = self.texel_m(material, L)
            v0 = self._bilinear(material, L, a[m] / sa, b[m] / sb)
            if L + 1 < n:
                sa, sb = self.texel_m(material, L + 1)
                v1 = self._bilinear(material, L + 1, a[m] / sa, b[m] / sb)
                out[m] = (1.0 - w[m]) * v0 + w[m] * v1
            else:
                out[m] = v0
        return out

    def _bilinear(self, material: int, level: int, col: Array, row: Array) -> Array:
        img = self.pyramids[material][level]
        # texel centres at integer coordinates; grid-wrap: the tile is periodic
        return map_coordinates(img, [row - 0.5, col - 0.5], order=1, mode="grid-wrap")


def slant_footprint(footprint_m: Array, n: Array, d: Array) -> Array:
    """A pixel's footprint (m) on a surface of unit normal ``n (m, 3)`` seen along ``d (m, 3)``: ``footprint /
    sqrt(max(|n . d|, 0.1))`` (the geometric mean of the footprint's two sides, capped at grazing incidence)."""
    return footprint_m / np.sqrt(np.maximum(np.abs(np.einsum("ij,ij->i", n, d)), 0.1))


def pyramid(tile: NDArray[np.float32], levels: int = LEVELS) -> tuple[NDArray[np.float32], ...]:
    """``tile`` and its mip levels (2 x 2 box filter per level), at most ``levels``, down to one texel."""
    out = [tile]
    while len(out) < levels and min(out[-1].shape) > 1:
        out.append(cv2.resize(out[-1], None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
    return tuple(out)


def atlas(rng: np.random.Generator) -> Atlas:
    """The three material tiles drawn from ``rng`` and their mip pyramids."""
    return Atlas(tuple(pyramid(t) for t in (mli_tile(rng), equipment_tile(rng), cells_tile(rng))))


def file_atlas(path: str | Path, size_m: tuple[float, float]) -> Atlas:
    """One material: the image file's albedo as a tile ``size_m = (w, h)`` metres (image columns along ``w``)."""
    return Atlas((pyramid(read_albedo(path)),), ((float(size_m[0]), float(size_m[1])),))
