"""Target geometry for depth sensing (Yu 2019): a procedural satellite or a user's mesh.

The procedural satellite is built in the model frame M (origin at the bus centre, x along the
solar-panel span, z along the docking-ring / nozzle axis): a box bus, two rectangular solar
panels (thin boxes) on +-x, a docking ring on +z and a nozzle cone on -z. Its rectangles (bus
faces and panel faces) are listed with their sides, centres and orientation, for rectangle
recognition. A user's mesh (OBJ, STL, glTF, ... anything trimesh reads) is used as given, in
metres, in its own frame.

The target's body frame T of the rest of tumblenav is the model frame M shifted by the mass
centre offset ``b`` (Yu 2019 Sec. 3.2: ``T`` is parallel to the nominal frame, with its origin at
the true mass centre). Mass properties can also be computed from the mesh (uniform density).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import NDArray

from tumblenav.errors import InputError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Rectangle:
    """A known rectangle of the model: sides (short, long) in m, centre in M, and ``R_MP``
    (columns: short side, long side, outward normal, in M)."""

    name: str
    sides_m: tuple[float, float]
    centre_M: Array
    R_MP: Array


@dataclass(frozen=True)
class TargetModel:
    mesh: trimesh.Trimesh  # in the model frame M (m)
    rectangles: tuple[Rectangle, ...]

    def mass_properties(self) -> tuple[Array, Array]:
        """Mass centre (m, in M) and principal moments per unit density (ascending), from the
        mesh (uniform density; needs a watertight mesh)."""
        if not self.mesh.is_watertight:
            raise InputError("the target mesh is not watertight: give its mass centre instead")
        return np.asarray(self.mesh.center_mass), np.asarray(self.mesh.principal_inertia_components)


def _face_rectangles(name: str, extents: Array, centre: Array) -> list[Rectangle]:
    """The six faces of an axis-aligned box as rectangles (outward normals)."""
    out = []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        s0, s1 = extents[others[0]], extents[others[1]]
        short, long_ = (others[0], others[1]) if s0 <= s1 else (others[1], others[0])
        for sign in (+1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            u = np.zeros(3)
            u[short] = 1.0
            v = np.cross(n, u)  # long-side axis with (u, v, n) right-handed
            c = centre + n * extents[axis] / 2
            out.append(
                Rectangle(
                    f"{name}{'+-'[sign < 0]}{'xyz'[axis]}",
                    (float(min(s0, s1)), float(max(s0, s1))),
                    c,
                    np.column_stack([u, v, n]),
                )
            )
    return out


def procedural_satellite(
    bus_m: tuple[float, float, float] = (0.9, 1.2, 1.5),
    panel_m: tuple[float, float] = (1.8, 0.8),
    panel_thickness_m: float = 0.03,
    ring_radius_m: float = 0.3,
    ring_height_m: float = 0.08,
    nozzle_radius_m: float = 0.15,
    nozzle_height_m: float = 0.25,
) -> TargetModel:
    """Box bus, two solar panels along x, docking ring on +z, nozzle on -z (metres)."""
    bus = np.asarray(bus_m, dtype=float)
    if np.any(bus <= 0) or min(panel_m) <= 0 or panel_thickness_m <= 0:
        raise InputError("satellite dimensions must be positive")
    parts = [trimesh.creation.box(extents=bus)]
    # the panels' roots cross the bus faces +-x, and the docking ring and the nozzle stand on
    # +-z: those faces are not clean rectangles and are not used for recognition
    blocked = {"bus+x", "bus-x"}
    if ring_radius_m > 0 and ring_height_m > 0:
        blocked.add("bus+z")
    if nozzle_radius_m > 0 and nozzle_height_m > 0:
        blocked.add("bus-z")
    rects = [r for r in _face_rectangles("bus", bus, np.zeros(3)) if r.name not in blocked]
    for sign in (+1.0, -1.0):
        ext = np.array([panel_m[0], panel_m[1], panel_thickness_m])
        centre = np.array([sign * (bus[0] / 2 + panel_m[0] / 2), 0.0, 0.0])
        parts.append(trimesh.creation.box(extents=ext, transform=_translation(centre)))
        for r in _face_rectangles(f"panel{'+-'[sign < 0]}x_", ext, centre):
            if abs(r.R_MP[2, 2]) > 0.5:  # keep the two large faces (normals along +-z)
                rects.append(r)
    if ring_radius_m > 0 and ring_height_m > 0:
        ring = trimesh.creation.annulus(
            r_min=0.8 * ring_radius_m, r_max=ring_radius_m, height=ring_height_m
        )
        ring.apply_translation([0.0, 0.0, bus[2] / 2 + ring_height_m / 2])
        parts.append(ring)
    if nozzle_radius_m > 0 and nozzle_height_m > 0:
        nozzle = trimesh.creation.cone(radius=nozzle_radius_m, height=nozzle_height_m)
        nozzle.apply_transform(_translation([0.0, 0.0, -bus[2] / 2]) @ _flip_z())
        parts.append(nozzle)
    mesh = trimesh.util.concatenate(parts)
    return TargetModel(mesh=mesh, rectangles=tuple(rects))


def load_mesh(path: str | Path) -> TargetModel:
    """A user's mesh (metres, its own frame) via trimesh; no known rectangles."""
    p = Path(path)
    if not p.is_file():
        raise InputError("mesh file not found", str(p))
    try:
        mesh = trimesh.load(p, force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"cannot read mesh ({exc.__class__.__name__}: {exc})", str(p)) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("the file holds no triangles", str(p))
    return TargetModel(mesh=mesh, rectangles=())


def _translation(t) -> Array:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def _flip_z() -> Array:
    T = np.eye(4)
    T[1, 1] = T[2, 2] = -1.0
    return T


def from_config(cfg) -> TargetModel:
    """The target's geometry from a scenario's ``target.model`` settings (procedural
    satellite or the user's mesh file): the geometry only, no motion."""
    if cfg.kind == "file":
        return load_mesh(cfg.path)
    return procedural_satellite(
        bus_m=tuple(cfg.bus_m),
        panel_m=tuple(cfg.panel_m),
        panel_thickness_m=cfg.panel_thickness_m,
        ring_radius_m=cfg.ring_radius_m,
        ring_height_m=cfg.ring_height_m,
        nozzle_radius_m=cfg.nozzle_radius_m,
        nozzle_height_m=cfg.nozzle_height_m,
    )
