"""Per-trial dispersed scenario values: distributions, sampling plans, the dispersion stream.

Every dispersed scalar is the image of one coordinate ``u`` of the unit cube
``[0, 1)^D`` (D = all unit dimensions of the scenario's dispersions, in the order they
are declared) under its distribution's inverse CDF; ``uniform_rotation`` uses three
coordinates (Shoemake's uniform quaternion), ``uniform_direction`` two (plus one for a
dispersed magnitude), ``choice`` one. The plan chooses the points ``u_j``:

- ``random``: trial ``j`` draws ``u_j`` from its own dispersion stream,
  ``default_rng(SeedSequence(seed, spawn_key=(j, DISPERSION_STREAM)))``, separate from
  the noise and initial-error stream ``spawn_key=(j,)`` (so adding a dispersion never
  changes any other draw);
- ``sobol``: row ``j`` of SALib's Saltelli design (``SALib.sample.sobol.sample``, scrambled
  Sobol' base sequence, ``calc_second_order=False``) with ``N = ceil(trials / (D + 2))``
  base points, seeded from the root seed; the design's blocks are what
  ``SALib.analyze.sobol`` needs for first-order and total indices;
- ``lhs``: row ``j`` of ``scipy.stats.qmc.LatinHypercube(d=D).random(trials)`` seeded from
  the root seed.

A row depends only on the root seed, the trial count and ``j``: never on chunking,
``--jobs`` or backend, and ``spmc rerun`` reproduces it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..config.dispersions import apply_values, component_names, get_path, invalid_reason, mode_of, MODEL_PREFIXES
from ..config.schema import DispersionSpec, MagnitudeSpec, Scenario
from ..config.resolve import Setup
from ..core import camera, quaternion as qt
from . import measurements as meas
from . import visibility
from .truth import Truth, simulate_truth_batch

Array = NDArray[np.float64]
DISPERSION_STREAM = 0x64697370  # "disp": the spawn-key tag of the dispersion child stream
PLAN_STREAM = 0x706C616E  # "plan": the root-level stream seeding the quasi-random plans
_EPS = 1e-12


def dispersion_rng(seed: int, trial: int) -> np.random.Generator:
    """The dispersion stream of trial ``trial``."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(trial, DISPERSION_STREAM)))


def plan_seed(seed: int) -> int:
    return int(np.random.SeedSequence(seed, spawn_key=(PLAN_STREAM,)).generate_state(1)[0])


def _magnitude_dims(m: MagnitudeSpec | float | None) -> int:
    return 1 if isinstance(m, MagnitudeSpec) else 0


def unit_dims(spec: DispersionSpec, shape: tuple[int, ...]) -> int:
    """Coordinates of the unit cube one dispersion uses."""
    if spec.dist == "uniform_rotation":
        return 3
    if spec.dist == "uniform_direction":
        return 2 + _magnitude_dims(spec.magnitude)
    if spec.dist == "choice":
        return 1
    return int(np.prod(shape, dtype=int))


def _scalar_ppf(spec, u: Array, shape: tuple[int, ...]) -> Array:
    """Inverse CDF of a per-component distribution; ``u (B, *shape)``."""
    b = lambda name: np.broadcast_to(np.asarray(getattr(spec, name), float), shape)  # noqa: E731
    from scipy import special  # here, not at import: scipy.special costs ~0.1 s of every run's start-up

    if spec.dist == "normal":
        return b("mean") + b("std") * special.ndtri(u)
    if spec.dist == "uniform":
        return b("low") + (b("high") - b("low")) * u
    if spec.dist == "truncnormal":
        mean, std = b("mean"), np.maximum(b("std"), 1e-300)
        from scipy.stats import truncnorm  # here: scipy.stats costs ~0.2 s of every run's start-up

        return truncnorm.ppf(u, (b("low") - mean) / std, (b("high") - mean) / std, loc=mean, scale=std)
    if spec.dist == "lognormal":
        return b("median") * np.exp(b("sigma") * special.ndtri(u))
    raise ValueError(spec.dist)  # pragma: no cover


def _choice(spec, u: Array, shape: tuple[int, ...]) -> Array:
    """``u (B,)`` -> one of ``values`` per trial, ``(B, *shape)``."""
    w = np.ones(len(spec.values)) if spec.weights is None else np.asarray(spec.weights, float)
    cdf = np.cumsum(w) / w.sum()
    idx = np.minimum(np.searchsorted(cdf, u, side="right"), len(w) - 1)
    vals = np.stack([np.broadcast_to(np.asarray(v, float), shape) for v in spec.values])
    return vals[idx]


def uniform_quaternion(u: Array) -> Array:
    """Shoemake's uniform unit quaternion (scalar first) from ``u (..., 3)`` uniform on the unit cube."""
    u1, u2, u3 = np.moveaxis(u, -1, 0)
    a, b = np.sqrt(1.0 - u1), np.sqrt(u1)
    return np.stack([b * np.cos(2 * np.pi * u3), a * np.sin(2 * np.pi * u2), a * np.cos(2 * np.pi * u2),
                     b * np.sin(2 * np.pi * u3)], axis=-1)  # fmt: skip


def uniform_unit_vector(u: Array) -> Array:
    """A unit vector uniform on the sphere from ``u (..., 2)``: ``z = 2 u1 - 1``, azimuth ``2 pi u2``."""
    z = 2.0 * u[..., 0] - 1.0
    phi = 2.0 * np.pi * u[..., 1]
    s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)


def draw_values(spec: DispersionSpec, nominal: Array, u: Array) -> Array:
    """The dispersed values ``(B, *shape)`` of one key from its unit coordinates ``u (B, d)``."""
    shape = nominal.shape
    B = u.shape[0]
    if spec.dist == "uniform_rotation":
        d = uniform_quaternion(u)
    elif spec.dist == "uniform_direction":
        m = spec.magnitude
        mag = _scalar_ppf(m, u[:, 2], ()) if isinstance(m, MagnitudeSpec) and m.dist != "choice" else (
            _choice(m, u[:, 2], ()) if isinstance(m, MagnitudeSpec) else np.full(B, float(m)))  # fmt: skip
        d = uniform_unit_vector(u[:, :2]) * mag[:, None]
    elif spec.dist == "choice":
        d = _choice(spec, u[:, 0], shape)
    else:
        d = _scalar_ppf(spec, u.reshape((B,) + shape), shape)
    mode = mode_of(spec)
    if spec.dist == "uniform_rotation":
        q = d if mode == "replace" else qt.multiply(d, nominal)  # add: the drawn rotation on top of the nominal
        return qt.normalize(q)
    if mode == "add":
        return nominal + d
    if mode == "scale":
        return nominal * d
    return np.asarray(d, float)


def unit_plan(scn: Scenario, trials: Array, dims: int) -> Array:
    """The unit-cube points ``(B, dims)`` of the given trials (see the module's docstring)."""
    trials = np.asarray(trials, dtype=np.int64)
    sampling = scn.dispersions.sampling if scn.dispersions is not None else "random"
    if sampling == "random":
        u = np.array([dispersion_rng(scn.seed, int(j)).random(dims) for j in trials]).reshape(trials.size, dims)
    elif sampling == "lhs":
        from scipy.stats import qmc

        u = qmc.LatinHypercube(d=dims, seed=plan_seed(scn.seed)).random(scn.trials)[trials]
    else:
        u = saltelli_design(scn.seed, scn.trials, dims)[trials]
    return np.clip(u, _EPS, 1.0 - _EPS)


def noise_streams(scn: Scenario, trials) -> Array:
    """The noise / initial-error stream of each trial: its own index, except in ``sobol`` campaigns.

    Saltelli's estimators need the output to be a function of the factors; the trials'
    noise makes it random. In a ``sobol`` campaign the rows of Saltelli block ``b``
    (``A_b, AB_b^1 .. AB_b^D, B_b``: trials ``b (D + 2)`` to ``b (D + 2) + D + 1``) therefore
    share their noise: ``A_b`` and every ``AB_b^i`` use stream ``2 b``, ``B_b`` stream
    ``2 b + 1``. The noise then acts as one more independent input of the design (part of
    ``A`` and ``B``), and the indices of the dispersed factors stay unbiased.
    """
    trials = np.asarray(trials, dtype=np.int64)
    if scn.dispersions is None or scn.dispersions.sampling != "sobol":
        return trials
    D = layout_of(scn).dims
    b, r = np.divmod(trials, D + 2)
    return 2 * b + (r == D + 1)


def saltelli_blocks(trials: int, dims: int) -> int:
    """``N``: base points of the Saltelli design covering ``trials`` rows."""
    return max(1, -(-trials // (dims + 2)))


def saltelli_design(seed: int, trials: int, dims: int) -> Array:
    """SALib's Saltelli design on the unit cube (first-order and total indices), ``(N (D+2), D)``."""
    from SALib.sample import sobol as sobol_sample

    problem = {"num_vars": dims, "names": [f"u{i}" for i in range(dims)], "bounds": [[0.0, 1.0]] * dims}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # SALib warns when N is not a power of 2
        return sobol_sample.sample(problem, saltelli_blocks(trials, dims), calc_second_order=False,
                                   scramble=True, seed=plan_seed(seed))  # fmt: skip


@dataclass
class Layout:
    """The dispersions of a scenario, resolved against its nominal values."""

    paths: list[str]
    specs: list[DispersionSpec]
    nominal: list[Array]
    offsets: list[int]  # first unit coordinate of each dispersion
    dims: int


def layout_of(scn: Scenario) -> Layout:
    nominal_d = scn.model_dump(mode="python")
    paths, specs, noms, offs = [], [], [], []
    D = 0
    for path, spec in (scn.dispersions.specs.items() if scn.dispersions is not None else []):
        nom = np.asarray(get_path(nominal_d, path), dtype=float)
        paths.append(path), specs.append(spec), noms.append(nom), offs.append(D)
        D += unit_dims(spec, nom.shape)
    return Layout(paths, specs, noms, offs, D)


@dataclass
class TrialDispersions:
    """The dispersed values of a batch of trials."""

    trials: Array  # (B,)
    values: dict[str, Array]  # key path -> (B, *shape), scenario units
    columns: dict[str, Array] = field(default_factory=dict)  # column name -> (B,)
    truth: list[Scenario | None] = field(default_factory=list)  # None: invalid draw
    filter_model: list[Scenario | None] = field(default_factory=list)  # what the filter's model sees
    invalid: list[str] = field(default_factory=list)  # '' or the reason
    model_key: list[tuple] = field(default_factory=list)  # trials with equal keys share the filter's model


def draw(scn: Scenario, trials) -> TrialDispersions:
    """Draw, apply and validate the dispersions of ``trials``."""
    lay = layout_of(scn)
    trials = np.asarray(trials, dtype=np.int64)
    u = unit_plan(scn, trials, lay.dims)
    values, columns = {}, {}
    for path, spec, nom, off in zip(lay.paths, lay.specs, lay.nominal, lay.offsets):
        v = draw_values(spec, nom, u[:, off : off + unit_dims(spec, nom.shape)])
        values[path] = v
        flat = v.reshape(trials.size, -1)
        for i, name in enumerate(component_names(path, nom.shape)):
            columns[name] = flat[:, i].copy()
        if spec.dist == "uniform_direction":
            columns[f"|{path}|"] = np.linalg.norm(v, axis=-1)
    base = scn.model_dump(mode="python")
    out = TrialDispersions(trials, values, columns)
    both = [p for p, s in zip(lay.paths, lay.specs) if s.applies_to == "both"]
    for b in range(trials.size):
        tv = {p: values[p][b] for p in lay.paths}
        truth_d = apply_values(base, tv)
        reason = invalid_reason(truth_d)
        fv = {p: values[p][b] for p in both}
        out.invalid.append(reason)
        out.truth.append(None if reason else Scenario.model_validate(truth_d))
        out.filter_model.append(None if reason else Scenario.model_validate(apply_values(base, fv)))
        out.model_key.append(tuple(np.asarray(fv[p]).tobytes() for p in both if p.startswith(MODEL_PREFIXES)))
    return out


# ------------------------------------------------- per-trial truth and measurements


def truth_of(setups: list[Setup], t: np.ndarray, rtol: float) -> Truth:
    """The batched truth of trials with the given (dispersed) setups."""
    return simulate_truth_batch(np.stack([s.x0 for s in setups]), [s.orbit for s in setups], t, rtol)


def exact_measurements(setups: list[Setup], truth: Truth) -> meas.Measurements:
    """Noise-free measurements ``y (B, K+1, N, C)`` with each trial's camera; visibility ``(B, K+1, N)``."""
    base = np.array([s.baseline for s in setups])[:, None, None]
    focal = np.array([s.focal for s in setups])[:, None, None, None]
    y = camera.h_features(truth.x, base, setups[0].disparity) * focal
    vis = np.stack([visibility.visible(s, truth.x[i]) for i, s in enumerate(setups)])
    return meas.Measurements(y=y, alpha=truth.alpha.copy(), visible=vis)


def noisy_measurements(setups: list[Setup], exact: meas.Measurements, draws: meas.TrialDraws) -> meas.Measurements:
    """Exact measurements plus each trial's noise at its own (possibly dispersed) noise levels."""
    sig = np.stack([meas.channel_sigmas(s) for s in setups])  # (B, C)
    C = sig.shape[-1]
    y = exact.y + draws.image[..., :C] * sig[:, None, None, :]
    alpha = exact.alpha + np.array([s.sigma_alpha for s in setups])[:, None, None] * draws.alpha
    return meas.Measurements(y=y, alpha=alpha, visible=exact.visible)


def factor_names(scn: Scenario) -> list[str]:
    """Names of the unit-cube coordinates (the input factors of a Sobol analysis), in plan order.

    A per-component distribution's factor is its column (``path[i]``); a rotation's are
    ``path:u1..u3`` (Shoemake), a direction's ``path:direction_u1/u2`` and ``|path|``, a choice's ``path``.
    """
    lay = layout_of(scn)
    out: list[str] = []
    for path, spec, nom in zip(lay.paths, lay.specs, lay.nominal):
        if spec.dist == "uniform_rotation":
            out += [f"{path}:u{i}" for i in (1, 2, 3)]
        elif spec.dist == "uniform_direction":
            out += [f"{path}:direction_u1", f"{path}:direction_u2"]
            out += [f"|{path}|"] * _magnitude_dims(spec.magnitude)
        elif spec.dist == "choice":
            out.append(path)
        else:
            out += component_names(path, nom.shape)
    return out
