"""Surface albedo for the stereo renderer: procedural spacecraft materials and mesh textures.

Chang 2021 renders its target in Unity with textures it does not describe (Sec. 3.2, Fig. 13:
gold multi-layer insulation on the bus, solar cells on the panels).  tumblenav's stand-in, all
``# tumblenav default (Chang 2021 silent)``:

* three procedural grey-level albedo tiles (1024 x 1024 texels, ``TEXEL_M`` = 2 mm a texel,
  drawn once from a fixed seed, so every run sees the same target):

  - ``MLI``: gold foil blankets cut into rectangular blocks with seams, crinkled (ridged
    multi-scale noise) and with dark fasteners at the block corners;
  - ``SOLAR``: a grid of 64 x 128 mm cells with chamfered corners, silver gaps and busbars;
  - ``METAL``: brushed grey metal (docking ring, nozzle);

* a material per connected part of the mesh: a thin flat part (its smallest bounding-box side
  below 8 % of its largest) is a solar panel; a part whose area lies mostly on faces that are
  not square to an axis of M is metal; everything else is MLI;
* planar mapping of the procedural tiles: each face takes the two M coordinates across its
  dominant normal axis, offset per (part, axis, side) so the faces of a box do not repeat;
* a user's mesh with UV coordinates and an image (``texture="mesh"``) uses that image's
  luminance as albedo instead.

Every material is stored with its mip-map pyramid (2 x 2 box filter) in one flat ``float32``
atlas that the compiled shader samples trilinearly with wrap-around addressing.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy import ndimage

__all__ = [
    "METAL",
    "MLI",
    "SOLAR",
    "TEXEL_M",
    "SurfaceTextures",
    "face_materials",
    "mesh_image_texture",
    "procedural_tile",
    "surface_textures",
]

Array = NDArray[np.float64]
F32 = NDArray[np.float32]

MLI, SOLAR, METAL = 0, 1, 2
TEXEL_M = 0.002  # tumblenav default (Chang 2021 silent): 2 mm a texel, 1 px at 3 m for f = 1624 px
_TILE = 1024
_SEED = 20210230  # fixed: the procedural target looks the same in every run


def _unit_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float | tuple) -> F32:
    """Band-limited Gaussian noise with zero mean and unit standard deviation (wraps around)."""
    n = ndimage.gaussian_filter(rng.standard_normal(shape), sigma, mode="wrap")
    return ((n - n.mean()) / (n.std() + 1e-12)).astype(np.float32)


def _split_blocks(rng: np.random.Generator, x0: int, y0: int, w: int, h: int, out: list) -> None:
    """Guillotine cuts into blocks of about 75-250 texels (15-50 cm): MLI blanket pieces."""
    if max(w, h) > 250 or (max(w, h) > 150 and rng.random() < 0.5):
        if w >= h:
            c = int(rng.uniform(0.3, 0.7) * w)
            _split_blocks(rng, x0, y0, c, h, out)
            _split_blocks(rng, x0 + c, y0, w - c, h, out)
        else:
            c = int(rng.uniform(0.3, 0.7) * h)
            _split_blocks(rng, x0, y0, w, c, out)
            _split_blocks(rng, x0, y0 + c, w, h - c, out)
    else:
        out.append((x0, y0, w, h))


def _mli_tile(rng: np.random.Generator) -> F32:
    n = _TILE
    blocks: list[tuple[int, int, int, int]] = []
    _split_blocks(rng, 0, 0, n, n, blocks)
    albedo = np.empty((n, n), np.float32)
    crease = np.zeros((n, n), np.float32)
    for x0, y0, w, h in blocks:
        # each blanket has its own sheen and its own crease direction (anisotropic noise)
        albedo[y0 : y0 + h, x0 : x0 + w] = rng.uniform(0.42, 0.68)
        sig = (rng.uniform(2.0, 9.0), rng.uniform(2.0, 9.0))
        crease[y0 : y0 + h, x0 : x0 + w] = _unit_noise(rng, (h, w), sig)
    # crinkles: ridged noise (bright/dark creases) at three scales
    crinkle = (
        0.55 * (1.0 - 1.6 * np.abs(crease))
        + 0.30 * (1.0 - 1.6 * np.abs(_unit_noise(rng, (n, n), 3.0)))
        + 0.15 * _unit_noise(rng, (n, n), 1.0)
    )
    img = albedo * (1.0 + 0.45 * crinkle)
    for x0, y0, w, h in blocks:
        # seams (3 texels, dark) on the block's upper and left edges: the tile wraps around
        img[y0 : y0 + 3, x0 : x0 + w] = 0.12
        img[y0 : y0 + h, x0 : x0 + 3] = 0.12
        # aluminium tape over some seams
        if rng.random() < 0.35:
            img[y0 + 3 : y0 + 12, x0 : x0 + w] = 0.85
        # fasteners (dark squares with a bright centre) near the corners
        for cx, cy in ((x0 + 10, y0 + 10), (x0 + w - 16, y0 + 10), (x0 + 10, y0 + h - 16)):
            if 0 <= cx < n - 6 and 0 <= cy < n - 6:
                img[cy : cy + 6, cx : cx + 6] = 0.08
                img[cy + 2 : cy + 4, cx + 2 : cx + 4] = 0.7
    return np.clip(img, 0.03, 1.0).astype(np.float32)


def _solar_tile(rng: np.random.Generator) -> F32:
    n = _TILE
    cw, ch, gap, chamfer = 32, 64, 2, 4
    img = np.full((n, n), 0.72, np.float32)  # silver interconnects between the cells
    fine = 0.015 * _unit_noise(rng, (n, n), 0.7)
    yy, xx = np.mgrid[0:ch, 0:cw]
    inner = (xx >= gap) & (yy >= gap)
    # chamfered corners of mono-crystalline cells
    lx, ly = xx - gap, yy - gap
    wx, wy = cw - gap - 1, ch - gap - 1
    for cx, cy in ((0, 0), (wx, 0), (0, wy), (wx, wy)):
        inner &= np.abs(lx - cx) + np.abs(ly - cy) >= chamfer
    busbar = inner & ((np.abs(xx - (gap + cw // 3)) < 1) | (np.abs(xx - (gap + 2 * cw // 3)) < 1))
    for j in range(0, n, ch):
        for i in range(0, n, cw):
            cell = img[j : j + ch, i : i + cw]
            level = rng.uniform(0.10, 0.17)
            cell[inner] = level
            cell[busbar] = 0.42
    return np.clip(img + fine, 0.02, 1.0).astype(np.float32)


def _metal_tile(rng: np.random.Generator) -> F32:
    n = _TILE
    brushed = _unit_noise(rng, (n, n), (0.6, 25.0))  # streaks along the tile's u axis
    spots = _unit_noise(rng, (n, n), 12.0)
    return np.clip(0.36 + 0.05 * brushed + 0.04 * spots, 0.05, 1.0).astype(np.float32)


@cache
def procedural_tile(material: int) -> F32:
    """The procedural albedo tile (1024 x 1024, values in ``(0, 1]``) of MLI, SOLAR or METAL.

    Drawn from a fixed seed: identical in every process (cached)."""
    rng = np.random.default_rng([_SEED, material])
    makers = {MLI: _mli_tile, SOLAR: _solar_tile, METAL: _metal_tile}
    tile = makers[material](rng)
    tile.setflags(write=False)
    return tile


def _mip_levels(img: F32) -> list[F32]:
    """Mip-map pyramid by 2 x 2 box filtering down to one texel."""
    levels = [np.ascontiguousarray(img, dtype=np.float32)]
    while max(levels[-1].shape) > 1:
        h, w = levels[-1].shape
        size = (max(1, w // 2), max(1, h // 2))
        levels.append(
            np.asarray(cv2.resize(levels[-1], size, interpolation=cv2.INTER_AREA), np.float32)
        )
    return levels


@dataclass(frozen=True, eq=False)
class SurfaceTextures:
    """Per-face texture mapping and the packed mip-mapped atlas the shader samples.

    Attributes
    ----------
    face_texel : (F, 3, 2) float64
        Texel coordinates (level 0 of the face's material) at the face's three vertices.
    face_material : (F,) int32
        Row of ``level_offset`` used by the face.
    face_texel_per_m : (F,) float64
        Texels per metre on the face (sets the mip level from the pixel footprint).
    atlas : (N,) float32
        All levels of all materials, row-major, one after another.
    level_offset, level_width, level_height : (n_materials, n_levels) int64
        Where each level starts in ``atlas`` and its size; ``n_levels`` per material in
        ``level_count``.
    source : str
        ``'procedural'`` or ``'mesh'`` (what was used, after any fallback).
    """

    face_texel: Array
    face_material: NDArray[np.int32]
    face_texel_per_m: Array
    atlas: F32
    level_offset: NDArray[np.int64]
    level_width: NDArray[np.int64]
    level_height: NDArray[np.int64]
    level_count: NDArray[np.int64]
    source: str


I64 = NDArray[np.int64]


def _pack(images: list[F32]) -> tuple[F32, I64, I64, I64, I64]:
    pyramids = [_mip_levels(im) for im in images]
    n_lev = max(len(p) for p in pyramids)
    off = np.zeros((len(images), n_lev), np.int64)
    wid = np.ones((len(images), n_lev), np.int64)
    hei = np.ones((len(images), n_lev), np.int64)
    cnt = np.array([len(p) for p in pyramids], np.int64)
    chunks, pos = [], 0
    for m, pyr in enumerate(pyramids):
        for lev, im in enumerate(pyr):
            off[m, lev], hei[m, lev], wid[m, lev] = pos, im.shape[0], im.shape[1]
            chunks.append(im.ravel())
            pos += im.size
    return np.concatenate(chunks).astype(np.float32), off, wid, hei, cnt


def face_materials(mesh: trimesh.Trimesh) -> tuple[NDArray[np.int32], NDArray[np.int64]]:
    """Procedural material of each face (MLI, SOLAR or METAL) and its connected part's label.

    A part is a set of faces connected through shared edges.  Thin flat parts (smallest
    bounding-box side < 8 % of the largest) are solar panels; parts with more than half of
    their area on faces whose normal is more than 5 deg from every axis of M are metal
    (rings, cones, cylinders); the rest is MLI.  # tumblenav default (Chang 2021 silent)
    """
    n_faces = len(mesh.faces)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=n_faces)
    normals = np.asarray(mesh.face_normals)
    area = np.asarray(mesh.area_faces)
    square = np.max(np.abs(normals), axis=1) > np.cos(np.radians(5.0))
    mat = np.full(n_faces, MLI, np.int32)
    verts = np.asarray(mesh.vertices)
    for lab in np.unique(labels):
        sel = labels == lab
        pts = verts[np.asarray(mesh.faces)[sel].ravel()]
        ext = pts.max(axis=0) - pts.min(axis=0)
        a = area[sel]
        if ext.max() > 0 and ext.min() < 0.08 * ext.max():
            mat[sel] = SOLAR
        elif a.sum() > 0 and a[~square[sel]].sum() > 0.5 * a.sum():
            mat[sel] = METAL
    return mat, labels.astype(np.int64)


def _planar_texels(mesh: trimesh.Trimesh, labels: NDArray[np.int64]) -> Array:
    """Level-0 texel coordinates of each face's vertices by planar projection across the
    dominant normal axis, offset per (part, axis, side)."""
    normals = np.asarray(mesh.face_normals)
    axis = np.argmax(np.abs(normals), axis=1)
    side = normals[np.arange(len(axis)), axis] >= 0
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]  # (F, 3, 3)
    # the two other axes, ordered so that (a, b, normal axis) is a cyclic permutation
    a_ax = (axis + 1) % 3
    b_ax = (axis + 2) % 3
    idx = np.arange(len(axis))
    uv = np.stack([tri[idx, :, a_ax[idx]], tri[idx, :, b_ax[idx]]], axis=-1) / TEXEL_M
    key = (labels * 6 + axis * 2 + side).astype(np.uint64)
    # a fixed hash of the key: offsets in [0, tile) texels
    h = (key * np.uint64(2654435761) + np.uint64(12345)) % np.uint64(2**32)
    off = np.stack([(h % np.uint64(_TILE)), ((h // np.uint64(_TILE)) % np.uint64(_TILE))], -1)
    return uv + off.astype(float)[:, None, :]


def mesh_image_texture(mesh: trimesh.Trimesh) -> tuple[F32, Array] | None:
    """The mesh's own texture as (grey albedo image, per-vertex UV), or None without one.

    The image's luminance (PIL ``'L'``, 0-255) divided by 255 is taken as albedo."""
    visual = getattr(mesh, "visual", None)
    uv = getattr(visual, "uv", None)
    material = getattr(visual, "material", None)
    if uv is None or material is None or len(uv) != len(mesh.vertices):
        return None
    image = getattr(material, "image", None)
    if image is None:
        image = getattr(material, "baseColorTexture", None)
    if image is None:
        return None
    grey = np.asarray(image.convert("L"), dtype=np.float32) / 255.0
    if grey.ndim != 2 or grey.size == 0:
        return None
    return grey, np.asarray(uv, dtype=float)


def surface_textures(mesh: trimesh.Trimesh, texture: str = "procedural") -> SurfaceTextures:
    """Build the per-face mapping and the atlas for ``mesh`` (``texture``: 'procedural' or
    'mesh'; 'mesh' falls back to the procedural materials, with a warning, when the mesh has
    no UV coordinates with an image)."""
    tiles = [procedural_tile(m) for m in (MLI, SOLAR, METAL)]
    own = mesh_image_texture(mesh) if texture == "mesh" else None
    if texture == "mesh" and own is None:
        warnings.warn(
            "the target mesh has no UV texture image: using the procedural texture",
            stacklevel=3,
        )
    faces = np.asarray(mesh.faces)
    if own is not None:
        image, uv = own
        h, w = image.shape
        # UV origin at the image's bottom-left (OpenGL/trimesh): row = (1 - v) h
        texel = np.stack([uv[faces][..., 0] * w, (1.0 - uv[faces][..., 1]) * h], axis=-1)
        material = np.zeros(len(faces), np.int32)
        atlas, off, wid, hei, cnt = _pack([image])
        source = "mesh"
    else:
        material, labels = face_materials(mesh)
        texel = _planar_texels(mesh, labels)
        atlas, off, wid, hei, cnt = _pack(tiles)
        source = "procedural"
    # texels per metre on each face: sqrt(texel area / surface area)
    tri = np.asarray(mesh.vertices)[faces]
    area_m = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    e1, e2 = texel[:, 1] - texel[:, 0], texel[:, 2] - texel[:, 0]
    area_t = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    tpm = np.sqrt(area_t / np.maximum(area_m, 1e-300))
    tpm = np.where(np.isfinite(tpm) & (tpm > 0), tpm, 1.0 / TEXEL_M)
    return SurfaceTextures(
        face_texel=np.ascontiguousarray(texel, dtype=float),
        face_material=material,
        face_texel_per_m=tpm,
        atlas=atlas,
        level_offset=off,
        level_width=wid,
        level_height=hei,
        level_count=cnt,
        source=source,
    )
