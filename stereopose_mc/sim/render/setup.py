"""A scenario's rendering setup: the textured target, the stereo rig and the Sun (docs/images.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...config.schema import Scenario
from ...config.sensor import pixel_camera_of, shape_of
from . import earth as ea
from .renderer import DEFAULT_SUN_L, Rig
from .scene import Panels, Scene, scene
from .texture import file_atlas

TEXTURE_KEY = (0x7E47, 0, 0)  # spawn key of the texture stream (no trial or feature stream uses it)
EARTH_KEY = (0x7E47, 1, 0)  # spawn key of the Earth's albedo map (background: earth)


@dataclass(frozen=True)
class ImageSetup:
    scene: Scene
    rig: Rig
    sun_L: np.ndarray  # (3,) unit vector toward the Sun in L
    earth: ea.Earth | None = None  # the Earth behind the target (background: earth), else black


def image_setup(s: Scenario, panels: Panels | None = None) -> ImageSetup:
    """The rendering of scenario ``s``: needs ``target.shape`` and a pixel camera (``camera.resolution_px``).

    The texture is drawn from ``SeedSequence(seed, spawn_key=TEXTURE_KEY)`` or read from
    ``measurements.images.texture.file``; the Sun is ``measurements.illumination.sun_direction_lvlh``
    or, without it, ``DEFAULT_SUN_L``; with ``background: earth`` the Earth's map is drawn from
    ``SeedSequence(seed, spawn_key=EARTH_KEY)``.
    """
    shape = shape_of(s)
    if shape is None:
        raise ValueError("target.shape: rendering images needs the target's shape")
    cam = pixel_camera_of(s)
    if cam is None:
        raise ValueError("camera.resolution_px: rendering images needs a pixel camera")
    ill = s.measurements.illumination
    sun = DEFAULT_SUN_L if ill is None else np.asarray(ill.sun_direction_lvlh, dtype=float)
    seed = int(np.random.SeedSequence(s.seed, spawn_key=TEXTURE_KEY).generate_state(1)[0])
    c = s.measurements.images
    tile = None if c.texture is None else file_atlas(c.texture.file, c.texture.size_m)
    earth = None
    if c.background == "earth":
        earth = ea.earth(np.random.default_rng(np.random.SeedSequence(s.seed, spawn_key=EARTH_KEY)))
    return ImageSetup(scene(shape, seed, panels, tile), Rig(cam, float(s.camera.baseline_m)),
                      sun / np.linalg.norm(sun), earth)  # fmt: skip
