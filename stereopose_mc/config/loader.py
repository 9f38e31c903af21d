"""Load scenario YAML files with errors that name the file, the line and the key path.

Every problem is reported as one line ``FILE:LINE: key.path: message`` (see
docs/scenarios.md, "Error messages"). The line is the 1-based line of the offending
key in the YAML text (of the sequence item, for list entries); for a missing key it is
the line of the parent key (1 at top level). Problems that concern the whole file (a
YAML syntax error, an empty or non-mapping file) have no key path: ``FILE:LINE: message``;
a file that cannot be read has no line either: ``FILE: message``.

All problems of a file are collected: YAML duplicate keys (found while walking the
composed node tree, since PyYAML silently keeps the last), every pydantic validation
error, and the cross-key checks of ``_semantic_checks`` (run on whatever parts of the
file validate on their own).
"""

from __future__ import annotations

import difflib
import math
import re
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import yaml
from pydantic import BaseModel, TypeAdapter, ValidationError

from ..core import quaternion as qt
from .filters import FILTER_CONFIGS, tag
from .schema import MeasurementsConfig, Scenario, Vec3

Loc = tuple[Any, ...]


def filter_types() -> tuple[str, ...]:
    """The filter types a ``filters`` entry may name (the discriminator tags of the union, in its order)."""
    return tuple(tag(m) for m in FILTER_CONFIGS)


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a scenario file."""

    file: str
    line: int | None
    path: str
    message: str

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line is not None else self.file
        key = f" {self.path}:" if self.path else ""
        return f"{where}:{key} {self.message}"


class ScenarioError(Exception):
    """A scenario file that cannot be used; ``problems`` lists every issue found."""

    def __init__(self, problems: list[Problem]):
        self.problems = problems
        super().__init__("\n".join(str(p) for p in problems))


# --------------------------------------------------------------------------- YAML


def _walk(node: yaml.Node, path: Loc = (), seen: set[int] | None = None) -> Iterator[tuple[Loc, yaml.Node, int | None]]:
    """Every node below ``node`` with its key path and the line of its key (or list entry); duplicates included."""
    seen = set() if seen is None else seen
    if id(node) in seen:  # aliases share nodes
        return
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        for k, v in node.value:
            if isinstance(k, yaml.ScalarNode):
                sub = path + (k.value,)
                yield sub, v, k.start_mark.line + 1
                yield from _walk(v, sub, seen)
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            yield path + (i,), v, v.start_mark.line + 1
            yield from _walk(v, path + (i,), seen)


def duplicate_keys(root: yaml.Node | None) -> list[tuple[Loc, int, int]]:
    """``(key path, first line, repeated line)`` of every key repeated within one mapping."""
    if root is None:
        return []
    out: list[tuple[Loc, int, int]] = []
    for path, node in [((), root)] + [(p, n) for p, n, _ in _walk(root)]:
        if not isinstance(node, yaml.MappingNode):
            continue
        first: dict[str, int] = {}
        for k, _ in node.value:
            if not isinstance(k, yaml.ScalarNode) or k.tag == "tag:yaml.org,2002:merge":
                continue
            line = k.start_mark.line + 1
            if k.value in first:
                out.append((path + (k.value,), first[k.value], line))
            else:
                first[k.value] = line
    return out


def _compose(text: str, file: str) -> tuple[yaml.Node | None, Any, list[tuple[Loc, int, int]]]:
    """The composed node tree, the constructed data and the duplicate keys of one YAML document.

    Duplicates are looked for before construction, which rewrites mappings with merge keys (``<<``).
    """
    loader = yaml.SafeLoader(text)
    try:
        root = loader.get_single_node()
        dups = duplicate_keys(root)
        data = loader.construct_document(root) if root is not None else None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        msg = exc.problem or exc.context or "invalid YAML"
        if exc.context and exc.problem:
            cm = exc.context_mark
            msg = f"{exc.problem} ({exc.context}{f' at line {cm.line + 1}' if cm is not None else ''})"
        raise ScenarioError([Problem(file, line, "", f"YAML syntax error: {msg}")]) from None
    except yaml.YAMLError as exc:  # pragma: no cover - every PyYAML parse error is marked
        raise ScenarioError([Problem(file, None, "", f"YAML error: {exc}")]) from None
    finally:
        loader.dispose()
    return root, data, dups


def duplicate_message(first: int, again: int) -> str:
    where = f"twice on line {again}" if first == again else f"first at line {first}, again at line {again}"
    return f"duplicate key ({where}); YAML would silently keep the last"


class Locator:
    """Maps a key path (pydantic's error location) to a line of the YAML text."""

    def __init__(self, root: yaml.Node | None):
        self.root = root

    def _step(self, node: yaml.Node, key: Any) -> tuple[yaml.Node, int] | None:
        if isinstance(node, yaml.MappingNode):
            hit = None
            for k, v in node.value:  # the last of duplicate keys is the one YAML keeps
                if isinstance(k, yaml.ScalarNode) and k.value == str(key):
                    hit = (v, k.start_mark.line + 1)
            return hit
        if isinstance(node, yaml.SequenceNode) and isinstance(key, int) and 0 <= key < len(node.value):
            v = node.value[key]
            return v, v.start_mark.line + 1
        return None

    def line(self, loc: Loc) -> int:
        """Line of the key (or item) ``loc``; if it is absent, the line of its deepest present parent (1 at top)."""
        node, line = self.root, 1
        for key in loc:
            nxt = self._step(node, key) if node is not None else None
            if nxt is None:
                break
            node, line = nxt
        return line


# ----------------------------------------------------------------- pydantic errors


_UNION_MEMBER = re.compile(r"(float|int|str|bool|(list|dict|tuple)\[.*\]|[A-Z]\w*)")  # no scenario key looks so


def clean_loc(loc: Loc) -> Loc:
    """Drop the discriminator tag pydantic inserts after ``filters.K`` (``filters.0.iekf.x`` -> ``filters.0.x``)
    and the union members it names (``std.list[float]`` -> ``std``)."""
    out: list[Any] = []
    for i, p in enumerate(loc):
        if i == 2 and loc[0] == "filters" and isinstance(loc[1], int) and p in filter_types():
            continue
        if isinstance(p, str) and _UNION_MEMBER.fullmatch(p):
            continue
        out.append(p)
    return tuple(out)


def path_str(loc: Loc) -> str:
    return ".".join(str(p) for p in loc)


def _is_union(tp: Any) -> bool:
    return typing.get_origin(tp) in (typing.Union, types.UnionType)


def _unwrap(tp: Any) -> list[type[BaseModel]]:
    """The model classes reachable through ``Annotated``, ``Optional``, ``list`` and unions."""
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return _unwrap(typing.get_args(tp)[0])
    if origin is list or _is_union(tp):
        return [m for a in typing.get_args(tp) for m in _unwrap(a)]
    return [tp] if isinstance(tp, type) and issubclass(tp, BaseModel) else []


def _pick(models: list[type[BaseModel]], value: Any) -> type[BaseModel] | None:
    """The one model among ``models`` (of a discriminated union: the one whose ``type`` matches the value's)."""
    if len(models) == 1:
        return models[0]
    tag = value.get("type") if isinstance(value, dict) else None
    for m in models:
        f = m.model_fields.get("type")
        if f is not None and tag in typing.get_args(f.annotation):
            return m
    return None


def _schema_at(loc: Loc, data: Any) -> tuple[Any, Any]:
    """The schema type expected at ``loc`` (``None`` if ``loc`` is not in the schema) and the data there."""
    tp: Any = Scenario
    value = data
    for key in loc:
        while typing.get_origin(tp) is typing.Annotated:
            tp = typing.get_args(tp)[0]
        if isinstance(key, int):  # a list item has the list's element type
            args = typing.get_args(tp)
            if typing.get_origin(tp) is not list or not args:
                return None, None
            tp = args[0]
            value = value[key] if isinstance(value, list) and 0 <= key < len(value) else None
            continue
        model = _pick(_unwrap(tp), value)
        field = model.model_fields.get(str(key)) if model is not None else None
        if field is None:
            return None, None
        tp = field.annotation
        value = value.get(key) if isinstance(value, dict) else None
    return tp, value


def model_at(loc: Loc, data: Any) -> type[BaseModel] | None:
    """The schema model that the mapping at ``loc`` is validated against (``None`` if unknown)."""
    tp, value = _schema_at(loc, data)
    return _pick(_unwrap(tp), value) if tp is not None else None


def _leaf_types(tp: Any) -> set[Any]:
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return _leaf_types(typing.get_args(tp)[0])
    if _is_union(tp):
        return {t for a in typing.get_args(tp) for t in _leaf_types(a)}
    return {tp}


def booleans_as_numbers(root: yaml.Node | None, data: Any) -> list[tuple[Loc, int, str]]:
    """YAML booleans (``true``, ``yes``, ``on``) where the schema wants a number.

    pydantic's lax mode would silently read them as 1 and 0.
    """
    out = []
    if root is None:
        return out
    for loc, node, line in _walk(root):
        if isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:bool":
            leaves = _leaf_types(_schema_at(loc, data)[0])
            if leaves & {int, float} and bool not in leaves:
                out.append((loc, line or 1, f"must be a number, not a boolean (got {node.value!r})"))
    return out


def _known_keys(parent: Loc, data: Any) -> list[str]:
    """Field names allowed in the mapping at ``parent``."""
    m = model_at(parent, data)
    return list(m.model_fields) if m is not None else []


def _short(value: Any) -> str:
    s = repr(value)
    return s if len(s) <= 40 else s[:37] + "..."


def error_message(err: dict[str, Any], loc: Loc, data: Any) -> tuple[Loc, str]:
    """A one-line message (and possibly a refined location) for one pydantic error."""
    kind, msg, value = err["type"], err["msg"], err.get("input")
    tags = ", ".join(repr(t) for t in filter_types())
    if kind == "extra_forbidden":
        close = difflib.get_close_matches(str(loc[-1]), _known_keys(loc[:-1], data), n=1, cutoff=0.6)
        return loc, "unknown key" + (f" (did you mean {close[0]!r}?)" if close else "")
    if kind == "missing":
        return loc, "required key is missing"
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        # a filter entry, or another tagged mapping (target.shape): named by its key, with its own tags
        is_filter = "filters" in [k for k in loc if isinstance(k, str)]
        what = "filter" if is_filter else next((str(k) for k in reversed(loc) if isinstance(k, str)), "entry")
        expected = tags if is_filter else err.get("ctx", {}).get("expected_tags", tags)
        if kind == "union_tag_not_found":
            return loc + ("type",), f"required key is missing: every {what} needs a 'type', one of {expected}"
        tag = err.get("ctx", {}).get("tag", value)
        return loc + ("type",), f"unknown {what} type {tag!r}; expected one of {expected}"
    if kind == "finite_number":
        return loc, f"must be a finite number (got {_short(value)})"
    if kind == "value_error":
        msg = msg.removeprefix("Value error, ")
        if not loc:  # a check across keys: the message's leading key path, where the file has it
            lead = re.match(r"[a-z_]+(\.[a-z_]+)+", msg)
            key = tuple(lead.group(0).split(".")) if lead else ()
            while key and _get(data, *key) is None:
                key = key[:-1]
            if key and lead and key == tuple(lead.group(0).split(".")):
                msg = msg[lead.end():].lstrip()  # the key is the location: "measurements.occlusion: needs ..."
            return key, msg
        return loc, msg
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return loc, f"must be a mapping of keys to values (got {_short(value)})"
    if isinstance(value, (dict, list)):
        return loc, msg
    return loc, f"{msg} (got {_short(value)})"


# ------------------------------------------------------------------ semantic checks


_VEC3 = TypeAdapter(Vec3)


def _ok(adapter: TypeAdapter, value: Any) -> Any:
    """``value`` validated by ``adapter``, or ``None`` if it does not validate (pydantic reports that)."""
    try:
        return adapter.validate_python(value)
    except ValidationError:
        return None


def _get(data: Any, *keys: str) -> Any:
    for k in keys:
        if not isinstance(data, dict) or k not in data:
            return None
        data = data[k]
    return data


def _truth_sigma(data: Any, key: str) -> float | None:
    """A truth noise sigma of ``measurements`` (its default if absent), or ``None`` if invalid."""
    m = _get(data, "measurements")
    m = {} if m is None else m
    if not isinstance(m, dict):
        return None
    value = m.get(key)
    if value is None:
        default = MeasurementsConfig.model_fields[key].default
        return None if default is None else float(default)
    ok = _ok(TypeAdapter(float), value)
    return float(ok) if ok is not None and math.isfinite(ok) and ok >= 0 else None


def _points_behind(data: Any) -> list[tuple[Loc, str]]:
    """Feature points with ``y <= 0`` at t = 0: ``rho_i = rho_0 + D(q0) P_i`` (docs/model.md)."""
    rho = _ok(_VEC3, _get(data, "truth_initial_state", "rho_m"))
    q = _ok(TypeAdapter(list[float]), _get(data, "truth_initial_state", "q"))
    points = _get(data, "target", "feature_points_m")
    if rho is None or q is None or len(q) != 4 or not isinstance(points, list):
        return []
    qv = np.asarray(q, dtype=float)
    n = float(np.linalg.norm(qv))
    if not np.isfinite(n) or n < 1e-12 or not np.all(np.isfinite(rho)):
        return []
    D = qt.dcm(qv / n)
    out = []
    for i, p in enumerate(points):
        pv = _ok(_VEC3, p)
        if pv is None or not np.all(np.isfinite(pv)):
            continue
        y = float((np.asarray(rho) + D @ np.asarray(pv))[1])
        if y <= 0.0:
            out.append(
                (("target", "feature_points_m", i), f"feature point {i} {list(pv)} is behind the cameras at t=0 "
                 f"(y = {y:.3g} m <= 0)")  # fmt: skip
            )
    return out


def _points_inside(data: Any) -> list[tuple[Loc, str]]:
    """With occlusion, a feature point strictly inside a box or ellipsoid target is never visible (the body
    blocks every ray to it): an impossible feature. (A mesh's interior: :func:`_points_inside_mesh`.)"""
    shape, points = _get(data, "target", "shape"), _get(data, "target", "feature_points_m")
    if _get(data, "measurements", "occlusion") is not True or not isinstance(shape, dict) or not isinstance(points, list):
        return []
    size = _ok(_VEC3, shape.get("size_m") if shape.get("type") == "box" else shape.get("semi_axes_m"))
    if shape.get("type") not in ("box", "ellipsoid") or size is None or not all(v > 0 for v in size):
        return []
    a = np.asarray(size, float) / (2.0 if shape["type"] == "box" else 1.0)  # half edges or semi-axes
    out = []
    for i, p in enumerate(points):
        pv = _ok(_VEC3, p)
        if pv is None or not np.all(np.isfinite(pv)):
            continue
        u = np.abs(np.asarray(pv, float)) / a
        depth = 1.0 - (u.max() if shape["type"] == "box" else float(np.sqrt(np.sum(u**2))))
        if depth > 1e-6:  # inside by more than round-off: a point on the surface is fine
            out.append((("target", "feature_points_m", i), f"feature point {i} {list(pv)} lies inside the target's "
                        f"{shape['type']} (target.shape): with measurements.occlusion it is never visible"))  # fmt: skip
    return out


def _filter_R_positive(data: Any) -> list[tuple[Loc, str]]:
    """A filter whose R would default to a zero truth noise (a singular innovation covariance)."""
    sig = {k: _truth_sigma(data, k) for k in ("image_sigma", "flow_sigma")}
    m = _get(data, "measurements")
    if isinstance(m, dict) and m.get("disparity") is True:
        d = _truth_sigma(data, "disparity_sigma")
        if m.get("disparity_sigma") is None and sig["image_sigma"] is not None:
            d = math.sqrt(2.0) * sig["image_sigma"]
        sig["disparity_sigma"] = d
    filters = data.get("filters", [{"type": "iekf"}]) if isinstance(data, dict) else None
    if not isinstance(filters, list):
        return []
    out = []
    for k, f in enumerate(filters):
        if not isinstance(f, dict):
            continue
        own = f.get("measurement_noise")
        own = {} if own is None else own
        if not isinstance(own, dict):
            continue
        for key, s in sig.items():
            if s == 0.0 and own.get(key) is None:
                out.append(
                    (("filters", k, "measurement_noise", key),
                     f"the filter's R must be positive: set it when the truth noise is 0 (measurements.{key} = 0)")
                )  # fmt: skip
    return out


def _duplicate_points(data: Any) -> list[tuple[Loc, str]]:
    """Feature points given twice (within 1 nm): the same feature measured twice, a singular model."""
    points = _get(data, "target", "feature_points_m")
    if not isinstance(points, list):
        return []
    out, seen = [], []
    for i, p in enumerate(points):
        pv = _ok(_VEC3, p)
        if pv is None:
            continue
        same = [j for j, q in seen if np.allclose(pv, q, rtol=0.0, atol=1e-9)]
        if same:
            out.append((("target", "feature_points_m", i), f"feature point {i} {list(pv)} duplicates point {same[0]}"))
        seen.append((i, np.asarray(pv, dtype=float)))
    return out


def _fits_in_memory(data: Any) -> list[tuple[Loc, str]]:
    """A trial count whose merged tables cannot fit in this machine's memory (``config.budget``)."""
    from .budget import memory_problem

    trials = _ok(TypeAdapter(int), data.get("trials"))
    filters = data.get("filters", [{}])
    if trials is None or trials < 1:
        return []
    msg = memory_problem(trials, len(filters) if isinstance(filters, list) else 1)
    return [(("trials",), msg)] if msg else []


def _semantic_checks(data: Any) -> list[tuple[Loc, str]]:
    """Checks across keys that pydantic's field validators cannot see; run on the raw data."""
    if not isinstance(data, dict):
        return []
    from .dispersions import check as dispersion_checks

    return (_points_behind(data) + _points_inside(data) + _filter_R_positive(data) + _duplicate_points(data) + _fits_in_memory(data)
            + dispersion_checks(data))


# ----------------------------------------------------------------------- loading


def problems_of(text: str, file: str, overrides: dict[str, Any] | None = None) -> tuple[list[Problem], Scenario | None]:
    """Every problem of a scenario text, and the scenario if there are none."""
    root, data, dups = _compose(text, file)
    if root is None:
        return [Problem(file, 1, "", "the file is empty; a scenario is a YAML mapping of keys to values")], None
    if not isinstance(data, dict):
        kind = "list" if isinstance(data, list) else type(data).__name__
        msg = f"a scenario must be a YAML mapping of keys to values, not a {kind}"
        return [Problem(file, root.start_mark.line + 1, "", msg)], None
    if overrides:
        data = {**data, **overrides}
    where = Locator(root)
    problems = [Problem(file, l2, path_str(loc), duplicate_message(l1, l2)) for loc, l1, l2 in dups]
    bools = [Problem(file, line, path_str(loc), msg) for loc, line, msg in booleans_as_numbers(root, data)]
    problems += bools
    flagged = {p.path for p in bools}
    scenario = None
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as exc:
        for err in exc.errors():
            loc, msg = error_message(err, clean_loc(tuple(err["loc"])), data)
            if path_str(loc) in flagged:
                continue
            flagged.add(path_str(loc))  # a union's members fail together: the first says it
            problems.append(Problem(file, where.line(loc), path_str(loc), msg))
    problems += [Problem(file, where.line(loc), path_str(loc), msg) for loc, msg in _semantic_checks(data)]
    if scenario is not None and scenario.target.shape is not None and scenario.target.shape.type == "mesh":
        scenario, msg = _mesh_file(scenario, file)
        if msg:
            loc = ("target", "shape", "file")
            problems.append(Problem(file, where.line(loc), path_str(loc), msg))
        else:
            problems += [Problem(file, where.line(loc), path_str(loc), m) for loc, m in _points_inside_mesh(scenario)]
    if scenario is not None and scenario.measurements.tracks is not None:
        scenario, found = _tracks_files(scenario, file)
        problems += [Problem(file, where.line(loc), path_str(loc), msg) for loc, msg in found]
    if scenario is not None and scenario.measurements.images.texture is not None:
        scenario, msg = _texture_file(scenario, file)
        if msg:
            loc = ("measurements", "images", "texture", "file")
            problems.append(Problem(file, where.line(loc), path_str(loc), msg))
    problems.sort(key=lambda p: p.line or 0)
    return problems, (scenario if not problems else None)


def _resolved(path: str, file: str) -> Path:
    """``path`` made absolute: a relative path is taken from the scenario file's folder (the working directory
    for a scenario given as text)."""
    p = Path(path).expanduser()
    if p.is_absolute():
        return p
    base = Path(file).parent if not file.startswith("<") else Path.cwd()
    return (base / p).resolve()


def _tracks_files(scenario: Scenario, file: str) -> tuple[Scenario, list[tuple[Loc, str]]]:
    """The scenario with ``measurements.tracks.file`` / ``truth_file`` made absolute, and the problems (a file
    that is missing or not Parquet/CSV; its columns are checked when it is read, sim/tracks_file.py)."""
    t = scenario.measurements.tracks
    update, out = {}, []
    for key in ("file", "truth_file"):
        value = getattr(t, key)
        if value is None:
            continue
        p = _resolved(value, file)
        loc = ("measurements", "tracks", key)
        if not p.is_file():
            out.append((loc, f"{p}: {'is a directory, not a file' if p.is_dir() else 'file not found'}"))
        elif p.suffix.lower() not in (".parquet", ".csv"):
            out.append((loc, f"{p}: expected a .parquet or .csv file"))
        update[key] = str(p)
    m = scenario.measurements.model_copy(update={"tracks": t.model_copy(update=update)})
    return scenario.model_copy(update={"measurements": m}), out


def _texture_file(scenario: Scenario, file: str) -> tuple[Scenario, str]:
    """The scenario with ``measurements.images.texture.file`` made absolute, and the problem ("" if none): a
    missing file or one OpenCV cannot read as an image."""
    from .texturefile import TextureFileError, read_albedo

    images = scenario.measurements.images
    p = _resolved(images.texture.file, file)
    if not p.is_file():
        return scenario, f"{p}: {'is a directory, not a file' if p.is_dir() else 'file not found'}"
    try:
        read_albedo(p)
    except TextureFileError as exc:
        return scenario, str(exc)
    texture = images.texture.model_copy(update={"file": str(p)})
    m = scenario.measurements.model_copy(update={"images": images.model_copy(update={"texture": texture})})
    return scenario.model_copy(update={"measurements": m}), ""


# ray directions of the inside test: two generic directions and their opposites (a point on the surface has one
# ray of each pair leaving the body, so it never counts as inside)
_PARITY_RAYS = np.array([[0.5773, 0.5775, 0.5771], [-0.2673, 0.5347, 0.8017]])


def _points_inside_mesh(scenario: Scenario) -> list[tuple[Loc, str]]:
    """With occlusion, a feature point strictly inside the closed mesh target is never visible: a point is
    inside when every ray of :data:`_PARITY_RAYS` (both ways) crosses the surface an odd number of times."""
    from ..core.shapes import ray_triangles
    from .meshfiles import read_mesh

    points = scenario.target.feature_points_m
    if not scenario.measurements.occlusion or not points:
        return []
    m = read_mesh(Path(scenario.target.shape.file))
    tri = np.asarray(m.vertices, float)[np.asarray(m.faces)]
    p = np.asarray(points, float)
    inside = np.ones(len(p), bool)
    for d in np.concatenate([_PARITY_RAYS, -_PARITY_RAYS]):
        t = ray_triangles(p, np.broadcast_to(d / np.linalg.norm(d), p.shape), tri)
        inside &= np.sum(t > 1e-9, axis=-1) % 2 == 1
    return [(("target", "feature_points_m", int(i)), f"feature point {int(i)} {list(points[i])} lies inside the "
             "target's mesh (target.shape.file): with measurements.occlusion it is never visible")
            for i in np.flatnonzero(inside)]  # fmt: skip


def _mesh_file(scenario: Scenario, file: str) -> tuple[Scenario, str]:
    """The scenario with ``target.shape.file`` made absolute (from the scenario file's folder), or a problem."""
    from .meshfiles import MeshFileError, read_mesh

    shape = scenario.target.shape
    p = _resolved(shape.file, file)
    try:
        m = read_mesh(p)
    except MeshFileError as exc:
        return scenario, str(exc)
    if len(m.faces) < 4:
        return scenario, f"mesh {p} has {len(m.faces)} triangles; a closed body needs at least 4"
    target = scenario.target.model_copy(update={"shape": shape.model_copy(update={"file": str(p)})})
    return scenario.model_copy(update={"target": target}), ""


def load_scenario_text(text: str, file: str = "<string>", overrides: dict[str, Any] | None = None) -> Scenario:
    """Parse and validate scenario YAML text; raise ``ScenarioError`` listing all problems."""
    problems, scenario = problems_of(text, file, overrides)
    if problems or scenario is None:
        raise ScenarioError(problems)
    return scenario


MAX_SCENARIO_BYTES = 4 << 20  # a scenario (or sweep) file is a few kB; meshes live in their own files


def read_limited(path: Path, limit: int = MAX_SCENARIO_BYTES) -> bytes:
    """The bytes of ``path``, at most ``limit`` (``/dev/zero`` or a huge file: ``ValueError``, nothing more read)."""
    with open(path, "rb") as fh:
        raw = fh.read(limit + 1)
    if len(raw) > limit:
        raise ValueError(f"larger than {limit >> 20} MiB: not a scenario file")
    return raw


def load_scenario(path: str | Path, overrides: dict[str, Any] | None = None) -> Scenario:
    """Load and validate a scenario YAML file (at most ``MAX_SCENARIO_BYTES``)."""
    path = Path(path)
    try:
        raw = read_limited(path)
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        col = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        msg = (f"not UTF-8 text: byte 0x{raw[exc.start]:02x} at column {col} (file offset {exc.start}); "
               "save the file as UTF-8")
        raise ScenarioError([Problem(str(path), line, "", msg)]) from None
    except FileNotFoundError:
        raise ScenarioError([Problem(str(path), None, "", "file not found")]) from None
    except IsADirectoryError:
        raise ScenarioError([Problem(str(path), None, "", "is a directory, not a scenario file")]) from None
    except OSError as exc:
        raise ScenarioError([Problem(str(path), None, "", f"cannot read: {exc.strerror or exc}")]) from None
    except ValueError as exc:
        raise ScenarioError([Problem(str(path), None, "", str(exc))]) from None
    return load_scenario_text(text, str(path), overrides)
