"""Mass properties of a closed triangle mesh (``spmc inertia``, thesis ch. 7.4), as JSON-ready dicts.

Numerics in ``core/mesh.py``, file formats in ``config/meshfiles.py``; this module reads,
checks, optionally repairs, computes in SI and can write a scenario whose
``target.inertia_kgm2`` holds the principal moments.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .jsonfmt import fmt_vec, mat, num, vec

UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}


def mesh_mass_properties(
    path: Path, density: float = 1000.0, units: str = "m", repair: bool = False
) -> tuple[dict[str, Any], list[str]]:
    """Read, check (optionally repair) a mesh and compute its mass properties in SI.

    Returns the JSON-ready dict and a list of problems (non-empty: the mesh cannot be used;
    the dict then holds only what was read and repaired).
    """
    from ..core import mesh as M
    from ..config.meshfiles import MeshFileError, read_mesh

    try:
        data = read_mesh(path)
    except MeshFileError as exc:
        return {}, [str(exc)]
    V = data.vertices * UNITS[units]
    F = data.faces
    changes: list[str] = []
    if repair:
        V, F, changes = M.repair_mesh(V, F)
    out: dict[str, Any] = {
        "mesh": str(path),
        "format": data.format,
        "units_in_file": units,
        "density": num(density),
        "vertices": int(len(V)),
        "triangles": int(len(F)),
        "notes": list(data.notes),
        "repairs": changes,
    }
    chk = M.check_mesh(V, F)
    if chk.problems:
        prefix = f"{path}: "
        probs = [prefix + p for p in chk.problems]
        if repair and changes:
            probs.append(prefix + "after --repair, which " + "; ".join(changes))
        return out, probs
    mp = M.mass_properties(V, F, density)
    equal = M.equal_moment_pairs(mp.principal_moments)
    if equal:
        out["notes"].append(
            "equal principal moments "
            + ", ".join(f"{i + 1} and {j + 1}" for i, j in equal)
            + ": their axes are any orthonormal pair in their plane"
        )
    out.update(
        shells=len(chk.shells),
        volume=num(mp.volume),
        mass=num(mp.mass),
        centroid=vec(mp.centroid),
        inertia=mat(mp.inertia),
        principal_moments=vec(mp.principal_moments),
        principal_axes=mat(mp.principal_axes),
        k1=num(mp.k1),
        k2=num(mp.k2),
    )
    return out, []


def scenario_with_inertia(text: str, moments, comment: str | None = None) -> str:
    """``text`` (a scenario's YAML) with ``target.inertia_kgm2`` replaced by ``moments``.

    Only the characters of that value change (plus an optional comment line above the key
    when ``target`` is a block mapping): comments, order and formatting elsewhere are kept.
    """
    import yaml

    root = yaml.compose(text, Loader=yaml.SafeLoader)
    if not isinstance(root, yaml.MappingNode):
        raise ValueError("the scenario is not a YAML mapping")

    def child(node: yaml.Node, key: str) -> tuple[yaml.Node, yaml.Node]:
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == key:
                    return k, v
        raise ValueError(f"the scenario has no '{key}' mapping key")

    _, target = child(root, "target")
    key, value = child(target, "inertia_kgm2")
    start, end = value.start_mark.index, value.end_mark.index
    span = text[start:end]
    trailing = span[len(span.rstrip()) :]
    flow = "[" + ", ".join(repr(float(m)) for m in moments) + "]"
    new = text[:start] + flow + trailing + text[end:]
    if comment and isinstance(target, yaml.MappingNode) and not target.flow_style:
        line_start = new.rfind("\n", 0, key.start_mark.index) + 1
        indent = new[line_start : key.start_mark.index]
        if indent.strip() == "":
            new = new[:line_start] + f"{indent}# {comment}\n" + new[line_start:]
    return new


def write_target_config(scenario: Path, out: Path, moments, comment: str) -> list[str]:
    """Write ``scenario`` with new ``target.inertia_kgm2`` to ``out``, validated before and after."""
    from ..config import ScenarioError, load_scenario, load_scenario_text

    try:
        text = scenario.read_text(encoding="utf-8")
        new = scenario_with_inertia(text, moments, comment)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        return [f"{scenario}: cannot update target.inertia_kgm2: {exc}"]
    try:
        load_scenario_text(new, str(out))
    except ScenarioError as exc:
        return [f"the updated scenario would be invalid: {p}" for p in exc.problems]
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(new, encoding="utf-8")
        load_scenario(out)
    except OSError as exc:
        return [f"{out}: cannot write: {exc}"]
    except ScenarioError as exc:  # pragma: no cover - the text was validated above
        out.unlink(missing_ok=True)
        return [str(p) for p in exc.problems]
    return []



def inertia_lines(r: dict[str, Any]) -> list[str]:
    """Text form of the :func:`mesh_mass_properties` dict."""
    out: list[str] = []
    out.append(
        f"mesh: {r['mesh']} ({r['format']}, {r['vertices']} vertices, {r['triangles']} triangles, "
        f"{r['shells']} shell(s)); coordinates in {r['units_in_file']}, density {r['density']:g} kg/m^3"
    )
    for note in r["notes"]:
        out.append(f"note: {note}")
    for change in r["repairs"]:
        out.append(f"repair: {change}")
    out.append("all outputs in SI units (m, kg, kg m^2)")
    out.append(f"volume    {r['volume']:.9g} m^3")
    out.append(f"mass      {r['mass']:.9g} kg")
    out.append(f"centroid  {fmt_vec(r['centroid'], '.9g')} m")
    out.append("inertia about the centroid, mesh axes (kg m^2):")
    for row in r["inertia"]:
        out.append("  " + fmt_vec(row, "15.9g"))
    out.append("principal moments, ascending (kg m^2): " + fmt_vec(r["principal_moments"], ".9g"))
    out.append("principal axes (columns, mesh axes):")
    for row in r["principal_axes"]:
        out.append("  " + fmt_vec(row, "10.6f"))
    out.append(f"k1 = ln(I1/I2) = {r['k1']:.9g}    k2 = ln(I2/I3) = {r['k2']:.9g}")
    return out
