"""``spmc inertia``: mass properties of a closed triangle mesh (thesis ch. 7.4).

Parses options and calls :mod:`stereopose_mc.studies.mass_properties`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Optional

import typer

from .app import app, emit, fail, load_or_exit

INERTIA_HELP = (
    "Mass properties of a closed triangle mesh at constant density (divergence theorem, thesis ch. 7.4).\n\n"
    "Prints volume, mass, centroid, the inertia tensor about the centroid (mesh axes), principal moments "
    "(ascending) and axes (columns), and k1 = ln(I1/I2), k2 = ln(I2/I3).\n\n"
    "--units is the unit of the mesh file's coordinates; all outputs are SI (m, m^3, kg, kg m^2).\n\n"
    "A mesh that is open, non-manifold, inconsistently oriented, inward-facing or degenerate is an error "
    "(exit 2) unless --repair can fix it.\n\n"
    "With --target-config S --write-config OUT, OUT is a copy of S whose target.inertia_kgm2 holds the "
    "principal moments in ascending order (the target's x, y, z are the principal axes in that order)."
)


@app.command(help=INERTIA_HELP)
def inertia(
    mesh: Path = typer.Argument(..., help="closed triangle mesh: .obj, .stl (ASCII or binary), .ply (ASCII or binary)"),
    density: float = typer.Option(
        1000.0, "--density", help="constant density in kg/m^3 (default 1000 = 1 g/cm^3, as in the thesis)"
    ),
    units: str = typer.Option(
        "m", "--units", help="unit of the mesh file's coordinates: m, cm or mm. Outputs are always SI (m, kg, kg m^2)."
    ),
    repair: bool = typer.Option(
        False,
        "--repair",
        help="fix what can be fixed and say what changed: merge duplicate vertices, drop degenerate/duplicate "
        "triangles, flip faces to a consistent orientation, flip inward-facing shells (holes are not filled)",
    ),
    as_json: bool = typer.Option(False, "--json", help="print one JSON object (SI units)"),
    target_config: Optional[Path] = typer.Option(
        None,
        "--target-config",
        help="scenario whose target.inertia_kgm2 gets the principal moments (needs --write-config)",
    ),
    write_config: Optional[Path] = typer.Option(
        None, "--write-config", help="new scenario file to write (never the --target-config file itself)"
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="allow --write-config to replace an existing file"),
) -> None:
    """Mass properties of a closed triangle mesh (see INERTIA_HELP)."""
    problems: list[str] = []
    from ..studies.mass_properties import UNITS, inertia_lines, mesh_mass_properties, write_target_config

    if units not in UNITS:
        problems.append(f"--units must be m, cm or mm (got {units!r})")
    if not (math.isfinite(density) and density > 0):
        problems.append(f"--density must be a positive number of kg/m^3 (got {density})")
    if (target_config is None) != (write_config is None):
        problems.append("--target-config and --write-config go together (the scenario is never edited in place)")
    if target_config is not None and write_config is not None:
        load_or_exit(target_config)
        if write_config.exists() and os.path.samefile(write_config, target_config):
            problems.append(f"--write-config {write_config} is the --target-config file: write to a new file")
        elif write_config.exists() and not overwrite:
            problems.append(f"{write_config} exists (use --overwrite to replace it)")
        elif write_config.is_dir():
            problems.append(f"{write_config} is a directory")
    if problems:
        fail(problems)

    r, problems = mesh_mass_properties(mesh, density, units, repair)
    if problems:
        fail(problems)
    if target_config is not None and write_config is not None:
        comment = (
            f"inertia_kgm2 written by 'spmc inertia {mesh.name}' ({density:g} kg/m^3, mesh in {units}): "
            "principal moments, ascending"
        )
        problems = write_target_config(target_config, write_config, r["principal_moments"], comment)
        if problems:
            fail(problems)
        r["written_config"] = str(write_config)
    emit(r, inertia_lines, as_json)
    if not as_json and "written_config" in r:
        from ..studies.jsonfmt import fmt_vec

        typer.echo(f"wrote {write_config}: target.inertia_kgm2 = {fmt_vec(r['principal_moments'], '.9g')}")
