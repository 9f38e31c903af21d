"""Regenerate the small example meshes in this folder: ``python configs/meshes/generate.py``.

See README.md here for what each file is and its exact mass properties.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereopose_mc.core import mesh as M
from stereopose_mc.config.meshfiles import write_obj, write_ply, write_stl

HERE = Path(__file__).resolve().parent

# Thesis ch. 7.5.2 tank: the thesis gives no dimensions, only the CAD inertia at 1 g/cm^3,
# I_SW = diag(85.3, 85.34, 26.67) kg cm^2 (eq. 7.39). A solid cylinder with
# m r^2 / 2 = 26.67 and m (3 r^2 + h^2) / 12 = 85.32 (the mean of the two transverse
# moments) has r = 5.309 cm and h = 21.366 cm; rounded to r = 5.31 cm, h = 21.37 cm.
TANK_RADIUS_CM, TANK_HEIGHT_CM, TANK_SIDES = 5.31, 21.37, 96


def main() -> None:
    v, f = M.box_mesh(1.0, 2.0, 3.0)
    write_obj(HERE / "box.obj", v, f, "box 1 x 2 x 3 m centred at the origin (metres)")
    write_stl(HERE / "box.stl", v, f, binary=True, name="box 1 x 2 x 3 m centred at the origin")
    v, f = M.prism_mesh(0.5, 2.0, 64)
    write_stl(HERE / "cylinder.stl", v, f, binary=True, name="cylinder r=0.5 m h=2 m, 64-gon prism")
    v, f = M.prism_mesh(TANK_RADIUS_CM, TANK_HEIGHT_CM, TANK_SIDES)
    write_obj(
        HERE / "tank.obj",
        v + [0.0, 0.0, TANK_HEIGHT_CM / 2],
        f,
        f"thesis ch. 7.5.2 high-pressure tank as a solid cylinder (CENTIMETRES): r = {TANK_RADIUS_CM} cm,\n"
        f"h = {TANK_HEIGHT_CM} cm, {TANK_SIDES}-gon prism standing on z = 0; dimensions fitted to the\n"
        "thesis's CAD inertia diag(85.3, 85.34, 26.67) kg cm^2 at 1 g/cm^3 (eq. 7.39).\n"
        "spmc inertia configs/meshes/tank.obj --units cm --density 1000",
    )
    v, f = M.box_mesh(1.0, 2.0, 3.0)
    write_obj(HERE / "open_box.obj", v, f[np.arange(len(f)) != 0], "box 1 x 2 x 3 m with one triangle missing (open)")
    write_ply(HERE / "inward_box.ply", v, M.flip_faces(f), binary=False)


if __name__ == "__main__":
    main()
