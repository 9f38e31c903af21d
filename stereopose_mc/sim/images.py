"""The image measurement source of a campaign: render once, expose per trial, track, audit (docs/images.md).

``measurements.source: images``. For the trials of a call:

1. **Render** the radiance of both cameras at every step of the truth (sim/render/). With a
   shared truth this happens once per campaign: the radiance inside the region the target
   covers over the sequence (the union of its per-step footprints, ``MARGIN_PX`` wider) is
   kept as float32 stacks in ``<cache>/<key>.npz`` (plain arrays, no pickle), where ``key``
   is the SHA-256 of the true poses, the camera, the baseline, the textured scene (mesh,
   surfaces, materials, texture seed and texels), the Sun, the background (with the Earth: its
   map and per-step position), the render settings, the versions of the rendering code and of
   numpy / trimesh / embreex. A second call with the same key loads it. With the Earth in view
   the kept region also covers the pixels that see it (up to the whole image).
   A per-trial (dispersed) truth ``x (B, K+1, n)`` is rendered per trial, in memory.
2. **Expose** each trial's own sensor noise on that radiance (sim/render/sensor.py), from
   ``SeedSequence(seed, spawn_key=(j, IMAGES_STREAM))``, a child stream no other draw uses
   (so adding images changes no other number, and a trial rerun alone gets the same images):
   per step, the right image, then the left. Outside the kept region the radiance is 0 and
   the image is the sensor's digitized read noise; it is drawn exactly but sparsely (how many
   pixels digitize to 1, 2, ... DN, then where), or by exposing the whole frame when that
   noise is not sparse (``SPARSE_BACKGROUND``).
3. **Track** (sim/tracker/klt.py) and **audit** (sim/tracker/audit.py) the trial's frames.

Trials run one after the other inside a call; the engine parallelizes over chunks of trials.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from importlib import metadata
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
from scipy.stats import norm

from ..config.resolve import Setup
from ..config.schema import Scenario
from ..core.orbit import Orbit
from .render import earth as ea
from .render import renderer as rr
from .render import sensor as ss
from .render.scene import Panels
from .render.setup import TEXTURE_KEY, ImageSetup, image_setup
from .tracker import audit, klt
from .truth import Truth
from .truth_cache import _num, cache_dir as _truth_cache_dir, disabled as _cache_disabled, store_npz

IMAGES_STREAM = 0x696D67  # "img": second entry of the spawn key of a trial's image-noise stream
CACHE_FORMAT = 1
MARGIN_PX = 16  # kept around the target's footprint (zero radiance; room for a defocus blur of ~4 px)
SPARSE_BACKGROUND = 1e-3  # draw the background sparsely while fewer pixels than this fraction are non-zero
RENDER_SOURCES = ("renderer.py", "scene.py", "texture.py", "setup.py", "earth.py")  # in sim/render/: a change changes every key

Progress = Callable[[str, int, int], None]  # (stage "render" | "track", done, total)


@dataclass(frozen=True)
class ImageConfig:
    """``measurements.images`` in the renderer's and tracker's own types."""

    panels: Panels | None
    render: rr.RenderSettings
    sensor: ss.SensorModel
    tracker: klt.TrackerSettings
    cache: bool


def image_config(s: Scenario) -> ImageConfig:
    c = s.measurements.images
    panels = None if c.panels is None else Panels(**c.panels.model_dump())
    return ImageConfig(panels, rr.RenderSettings(supersample=c.supersample, ambient=c.ambient),
                       ss.SensorModel(**c.sensor.model_dump()),
                       klt.TrackerSettings(detector=c.detector, **c.tracker.model_dump()), c.cache)  # fmt: skip


def images_rng(seed: int, trial: int) -> np.random.Generator:
    """The image-noise generator of trial ``trial``: ``SeedSequence(seed, spawn_key=(trial, IMAGES_STREAM))``."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(int(trial), IMAGES_STREAM)))


# ----------------------------------------------------------------------------------------------- rendering


@dataclass(frozen=True)
class Radiance:
    """Both cameras' radiance at every step inside a fixed window: ``right``/``left`` ``(K+1, h, w)`` float32,
    ``window[c] = (row0, row1, col0, col1)`` of camera ``c`` (0 right, 1 left) in the ``(H, W)`` image."""

    right: np.ndarray
    left: np.ndarray
    window: np.ndarray  # (2, 4) int64
    shape: tuple[int, int]


def earth_views(img: ImageSetup, orbit: Orbit, nu) -> list[ea.EarthView] | None:
    """The Earth at each step (true anomalies ``nu (K+1,)`` of the leader on ``orbit``: ``r = p / (1 + e cos
    nu)``), or None with a black background."""
    if img.earth is None:
        return None
    nu = np.asarray(nu, dtype=float)
    r = orbit.p / (1.0 + orbit.e * np.cos(nu))
    return [ea.view(img.earth, float(rk), float(nk)) for rk, nk in zip(r, nu)]


def _window(img: ImageSetup, poses, cam: str, earth=None) -> tuple[int, int, int, int]:
    wins = [rr.footprint_window(img.scene, img.rig, rho, D, cam) for rho, D in poses]
    if earth is not None:
        wins += [w for w in (rr.earth_window(img.rig, e, cam) for e in earth) if w[0].stop > w[0].start]
    H, W = img.rig.camera.height, img.rig.camera.width
    return (max(0, min(w[0].start for w in wins) - MARGIN_PX), min(H, max(w[0].stop for w in wins) + MARGIN_PX),
            max(0, min(w[1].start for w in wins) - MARGIN_PX), min(W, max(w[1].stop for w in wins) + MARGIN_PX))  # fmt: skip


def render_radiance(img: ImageSetup, poses, settings: rr.RenderSettings = rr.RenderSettings(),
                    progress: Progress | None = None, earth: list[ea.EarthView] | None = None) -> Radiance:  # fmt: skip
    """Render both cameras at every pose; the radiance inside the target's window over the sequence (and the
    Earth's, with ``earth``: :func:`earth_views`, one per pose)."""
    win = np.array([_window(img, poses, c, earth) for c in ("right", "left")], dtype=np.int64)
    stacks = [np.zeros((len(poses), r1 - r0, c1 - c0), np.float32) for r0, r1, c0, c1 in win]
    for k, (rho, D) in enumerate(poses):
        f = rr.render_stereo(img.scene, img.rig, rho, D, img.sun_L, settings, None if earth is None else earth[k])
        for stack, view, (r0, r1, c0, c1) in zip(stacks, (f.right, f.left), win):
            stack[k] = view.radiance[r0:r1, c0:c1]
        if progress is not None:
            progress("render", k + 1, len(poses))
    return Radiance(stacks[0], stacks[1], win, (img.rig.camera.height, img.rig.camera.width))


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "-"


def render_inputs(s: Scenario, img: ImageSetup, poses, settings: rr.RenderSettings,
                  earth: list[ea.EarthView] | None = None) -> dict:  # fmt: skip
    """Everything the cached radiance depends on, JSON-ready (floats exact, arrays by digest)."""
    sc, cam = img.scene, img.rig.camera
    code = Path(rr.__file__).parent
    return {
        "format": CACHE_FORMAT,
        "code": _digest(*(np.frombuffer((code / f).read_bytes(), np.uint8) for f in RENDER_SOURCES)),
        "versions": {d: _version(d) for d in ("numpy", "trimesh", "embreex")},
        "poses": _digest(*(np.asarray(a, float) for p in poses for a in p)),
        "steps": len(poses),
        "camera": {k: _num(v) for k, v in asdict(cam).items()},
        "baseline": _num(img.rig.baseline),
        "scene": _digest(sc.mesh.vertices, sc.mesh.faces, sc.normals, sc.surface, sc.material, sc.offset),
        "texture_seed": int(np.random.SeedSequence(s.seed, spawn_key=TEXTURE_KEY).generate_state(1)[0]),
        "texture": _digest(*(p[0] for p in sc.atlas.pyramids), np.asarray(sc.atlas.size_m or (), float)),
        "sun": [_num(v) for v in img.sun_L],
        "background": "black" if earth is None else _digest(
            img.earth.atlas.pyramids[0][0], np.array([img.earth.radius]), *(a for e in earth for a in (e.centre_L, e.to_map))),
        "render": {k: _num(v) if isinstance(v, float) else v for k, v in asdict(settings).items()},
        "margin": MARGIN_PX,
    }


def render_key(s: Scenario, img: ImageSetup, poses, settings: rr.RenderSettings,
               earth: list[ea.EarthView] | None = None) -> str:  # fmt: skip
    canon = json.dumps(render_inputs(s, img, poses, settings, earth), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canon.encode()).hexdigest()


def default_cache_dir() -> Path:
    """``<the truth cache's root>/images`` (sim/truth_cache.py: ``SPMC_CACHE_DIR``, XDG, ``~/.cache``)."""
    return _truth_cache_dir().parent / "images"


def load_radiance(path: Path, key: str) -> Radiance | None:
    """The radiance stored at ``path`` under ``key``, or None (missing, unreadable, another key)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"][()]) != key:
                return None
            r = Radiance(z["right"], z["left"], z["window"], tuple(int(v) for v in z["shape"]))
    except Exception:  # noqa: BLE001 - missing or corrupt (zip, header, truncated, no such member): re-render
        return None
    ok = r.window.shape == (2, 4) and all(
        a.dtype == np.float32 and a.shape[1:] == (w[1] - w[0], w[3] - w[2]) for a, w in zip((r.right, r.left), r.window)
    )
    return r if ok else None


def store_radiance(path: Path, key: str, r: Radiance) -> None:
    """Write ``r`` to ``path`` atomically (temporary file, then rename); a failure leaves no file and is ignored."""
    store_npz(path, key=np.array(key), right=r.right, left=r.left, window=r.window, shape=np.array(r.shape))


def cached_radiance(s: Scenario, img: ImageSetup, poses, settings: rr.RenderSettings, cache_dir: Path | None,
                    progress: Progress | None = None, earth: list[ea.EarthView] | None = None,
                    ) -> tuple[Radiance, bool]:  # fmt: skip
    """The radiance of ``poses``: from ``cache_dir/<key>.npz`` when it is there (True), else rendered and stored
    (False). ``cache_dir`` None: rendered, not stored."""
    if cache_dir is None:
        return render_radiance(img, poses, settings, progress, earth), False
    key = render_key(s, img, poses, settings, earth)
    path = Path(cache_dir) / f"{key}.npz"
    r = load_radiance(path, key)
    if r is not None:
        return r, True
    r = render_radiance(img, poses, settings, progress, earth)
    store_radiance(path, key, r)
    return r, False


# ----------------------------------------------------------------------------------------------- exposure


def background_probabilities(sensor: ss.SensorModel) -> np.ndarray:
    """``p[d]``: probability that a pixel of zero radiance digitizes to ``d`` DN (read noise only,
    ``DN = round(clip(N(0, read^2), 0, full_well) gain)``), up to the last ``d`` with ``p[d] > 1e-16``."""
    if sensor.read_noise_e == 0.0:
        return np.array([1.0])
    top = int(min(2**sensor.bits - 1, np.ceil(40.0 * sensor.read_noise_e * sensor.gain)))
    edges = (np.arange(top + 1) + 0.5) / sensor.gain / sensor.read_noise_e  # e / read between d and d + 1
    sf = norm.sf(edges)
    p = np.r_[1.0 - sf[0], sf[:-1] - sf[1:]]
    p[-1] += sf[-1]  # saturation
    keep = np.flatnonzero(p > 1e-16)
    return p[: keep[-1] + 1] / p[: keep[-1] + 1].sum()


def expose_window(radiance: np.ndarray, window, shape: tuple[int, int], sensor: ss.SensorModel,
                  rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """One camera's ``(H, W)`` image: the window exposed with :func:`sensor.expose`, the rest (radiance 0) the
    sensor's digitized read noise, drawn sparsely (counts per DN, then positions) when it is sparse."""
    r0, r1, c0, c1 = (int(v) for v in window)
    p = background_probabilities(sensor)
    dtype = np.uint8 if sensor.bits <= 8 else np.uint16
    if 1.0 - p[0] > SPARSE_BACKGROUND:
        full = np.zeros(shape)
        full[r0:r1, c0:c1] = radiance
        return ss.expose(full, sensor, rng)
    out = np.zeros(shape, dtype)
    n = shape[0] * shape[1]
    counts = rng.multinomial(n, p)
    hot = int(n - counts[0])
    if hot:
        where = rng.choice(n, size=hot, replace=False)
        out.reshape(-1)[where] = np.repeat(np.arange(len(p)), counts)[counts[0]:].astype(dtype)
    out[r0:r1, c0:c1] = ss.expose(np.asarray(radiance, dtype=float), sensor, rng)
    return out


def trial_frames(r: Radiance, sensor: ss.SensorModel, rng: np.random.Generator):
    """The noisy ``(right, left)`` uint8 pairs of one trial, step by step (right first)."""
    for k in range(r.right.shape[0]):
        yield (expose_window(r.right[k], r.window[0], r.shape, sensor, rng),
               expose_window(r.left[k], r.window[1], r.shape, sensor, rng))  # fmt: skip


# ----------------------------------------------------------------------------------------------- campaign


def trial_tracks(r: Radiance, img: ImageSetup, poses, cfg: ImageConfig, dt: float, seed: int, trial: int,
                 t0: float = 0.0) -> pd.DataFrame:  # fmt: skip
    """Tracks and audit of one trial: its noise on ``r``, the tracker, the truth audit; a ``trial`` column first."""
    frames = trial_frames(r, cfg.sensor, images_rng(seed, trial))
    tracks = klt.track_sequence(frames, dt, cfg.tracker, t0)
    out = audit.audit(tracks, img, poses)
    out.insert(0, "trial", np.full(len(out), int(trial), np.int64))
    return out


TRACK_TABLE_COLUMNS = {"trial": "int64: the trial", **klt.COLUMNS, **audit.AUDIT_COLUMNS}


def campaign_tracks(scenario: Scenario, setup: Setup, truth: Truth, trials, seed: int,
                    cache_dir: Path | str | None = None, progress: Progress | None = None) -> pd.DataFrame:  # fmt: skip
    """The audited track tables of ``trials`` (one DataFrame, ``trial`` first, then klt.COLUMNS and
    audit.AUDIT_COLUMNS; rows by trial, then step, then track).

    ``truth``: shared (``x (K+1, n)``: rendered once, cached when ``measurements.images.cache``) or per trial
    (``x (B, K+1, n)`` aligned with ``trials``: rendered per trial, not cached). ``cache_dir``: where the cache
    lives (None: :func:`default_cache_dir`; ``SPMC_NO_CACHE`` turns it off). ``progress(stage, done, total)``.
    """
    trials = [int(j) for j in trials]
    if not trials:
        return pd.DataFrame({c: pd.Series(dtype=v.split(":")[0]) for c, v in TRACK_TABLE_COLUMNS.items()})
    cfg = image_config(scenario)
    img = image_setup(scenario, cfg.panels)
    x = np.asarray(truth.x)
    shared = x.ndim == 2
    if not shared and x.shape[0] != len(trials):
        raise ValueError(f"campaign_tracks: a per-trial truth has {x.shape[0]} trials, not {len(trials)}")
    where = None
    if shared and cfg.cache and not _cache_disabled():
        where = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    t = np.asarray(truth.t)
    t0 = float(t[0] if t.ndim == 1 else t[0, 0])
    out = []
    nu = np.asarray(truth.nu)
    if shared:
        poses = [rr.pose_of(xk) for xk in x]
        r, _ = cached_radiance(scenario, img, poses, cfg.render, where, progress, earth_views(img, setup.orbit, nu))
    for i, j in enumerate(trials):
        if not shared:
            poses = [rr.pose_of(xk) for xk in x[i]]
            r = render_radiance(img, poses, cfg.render, earth=earth_views(img, setup.orbit, nu[i] if nu.ndim == 2 else nu))
        out.append(trial_tracks(r, img, poses, cfg, setup.dt, seed, j, t0))
        if progress is not None:
            progress("track", i + 1, len(trials))
    return pd.concat(out, ignore_index=True)
