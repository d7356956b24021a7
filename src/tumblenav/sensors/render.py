"""Stereo image renderer: 8-bit grey stereo pairs of a textured target lit by the sun, with the
per-pixel truth a front end is judged by (Chang 2021 Sec. 3.2 renders in Unity; this is
tumblenav's headless CPU stand-in).

Engine
------
Ray casting with Embree (``embreex``, already a dependency through trimesh) and a compiled
(numba) shader, chosen over Mitsuba 3 (needs a system libLLVM 19) and pyrender (broken on
numpy 2), see ``shared/papers/chang2021-notes.md`` sec. 2.  Per camera and frame:

1. primary rays through the pixel centres ``(i + 0.5, j + 0.5)`` (``supersample = n``: an
   n x n grid of sub-pixel rays averaged), only inside the projection of the target's
   bounding box (ROI), and there only from the pixels that a projected triangle (grown by
   ``_COVER_MARGIN_PX``) can cover: the rays of the others would miss (the same pixels and
   truth maps as casting the whole ROI; a third of the rays at close range);
2. the shader: hit point in M from Embree's barycentrics, the face normal turned towards the
   camera (two-sided surfaces), the albedo sampled trilinearly from the mip-mapped texture
   (:mod:`tumblenav.sensors.texture`) at the level of the pixel footprint;
3. shadow rays towards the sun only from target points whose normal faces it (hard shadows:
   the sun is a directional light);
4. image level (fraction of full scale), Lambert with an ambient term::

       s = exposure * albedo * (ambient + (1 - ambient) * max(0, n.sun) * lit)

   so a white surface facing the sun reads ``exposure`` and a shadowed one
   ``exposure * ambient``.  Black space behind.  ``sun_C = None`` (eclipse): ``s = 0``
   everywhere (no sunlit Earth in view either), the frame holds only noise;
5. the sensor chain of :mod:`tumblenav.sensors.image_noise` and 8-bit quantisation, told
   the box of pixels with signal (the per-pixel chain runs there, the dark rest of the frame
   is drawn from its exact DN distribution).

The two cameras of a pair use the same model pose; they are rendered in two threads (Embree
and the compiled shader release the GIL), each camera's noise from its own generator seeded
from the caller's ``rng``, so that the same ``rng`` state gives the same pixels.

Frames: ``R_CM`` maps the model frame M into the rig frame C, ``p_MinC`` is M's origin in C;
camera k sees ``p_Ck = R_CkC (p_C - p_CkinC)`` and projects ``u = cu + f x/y``,
``v = cv + f z/y`` (:func:`tumblenav.sensors.stereo.project`); depth is ``y`` in ``C_k``.

All lighting and texture choices are ``# tumblenav default (Chang 2021 silent)``: the paper
uses a Unity point light as the sun and textures it does not describe.
"""

from __future__ import annotations

import threading
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from embreex import rtcore_scene  # type: ignore[import-untyped]
from embreex.mesh_construction import TriangleMesh  # type: ignore[import-untyped]
from numba import njit
from numpy.typing import ArrayLike, NDArray

from tumblenav.errors import InputError
from tumblenav.sensors.image_noise import DefectPattern, ImageNoise, apply_noise, defect_pattern
from tumblenav.sensors.stereo import Camera, StereoRig
from tumblenav.sensors.texture import SurfaceTextures, surface_textures
from tumblenav.target_model import TargetModel

__all__ = ["ImageNoise", "RenderSettings", "RenderedPair", "StereoRenderer"]

Array = NDArray[np.float64]
F32 = NDArray[np.float32]
_TEXTURES = ("procedural", "mesh")
# tumblenav default: a pixel is cast if its square grown by this much meets a projected
# triangle (float rounding in Embree's float32 test is far below it)
_COVER_MARGIN_PX = 0.5


@dataclass(frozen=True)
class RenderSettings:
    """How frames are rendered.

    Attributes
    ----------
    exposure : float
        Image level (fraction of full scale) of a white surface facing the sun.
    ambient : float
        Ambient fraction (Earth shine) in ``[0, 1]``: a shadowed or sun-averted white surface
        reads ``exposure * ambient``.
    supersample : int
        n x n rays per pixel, averaged (1 = one ray through the pixel centre).
    texture : str
        ``'procedural'`` (MLI, solar cells, metal) or ``'mesh'`` (the mesh's own UV texture;
        falls back to procedural with a warning when it has none).
    noise : ImageNoise or None
        The sensor noise chain; None quantises the ideal image.
    threads : int
        1 or 2: render the two cameras one after the other or in two threads.
    """

    exposure: float = 0.8  # tumblenav default (Chang 2021 silent)
    ambient: float = 0.02  # tumblenav default (Chang 2021 silent)
    supersample: int = 1
    texture: str = "procedural"
    noise: ImageNoise | None = field(default_factory=ImageNoise)
    threads: int = 2

    def __post_init__(self) -> None:
        if not self.exposure > 0:
            raise InputError(f"exposure must be positive, got {self.exposure}")
        if not 0 <= self.ambient <= 1:
            raise InputError(f"ambient must be in [0, 1], got {self.ambient}")
        if int(self.supersample) != self.supersample or not 1 <= self.supersample <= 8:
            raise InputError(f"supersample must be an integer in 1..8, got {self.supersample}")
        if self.texture not in _TEXTURES:
            raise InputError(f"texture must be one of {_TEXTURES}, got {self.texture!r}")
        if self.threads not in (1, 2):
            raise InputError(f"threads must be 1 or 2, got {self.threads}")


ImageStack = NDArray[Any] | tuple[NDArray[Any], NDArray[Any]]


@dataclass(frozen=True, eq=False)
class RenderedPair:
    """One stereo frame and its truth (index 0 = left, 1 = right).

    When the two cameras have the same resolution every field is one array with a leading
    axis of 2; when they differ, a tuple ``(left, right)`` of arrays.  ``depth_m``, ``hit_M``
    and ``mask`` are None when rendered with ``truth=False``.

    Attributes
    ----------
    images : (2, H, W) uint8
        Grey images (DN).
    depth_m : (2, H, W) float32
        Coordinate of the surface point along each camera's optical axis ``y_k`` (m) at the
        pixel centre; NaN off target.
    hit_M : (2, H, W, 3) float32
        The surface point seen at the pixel centre, in the model frame M (m); NaN off target.
    mask : (2, H, W) bool
        True where the pixel-centre ray hits the target.
    """

    images: ImageStack
    depth_m: ImageStack | None
    hit_M: ImageStack | None
    mask: ImageStack | None


# ---------------------------------------------------------------------------------------------
# compiled shader


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _bilinear(atlas, off, w, h, x, y):
    """Bilinear sample of one level (texel centres at +0.5), wrap-around addressing."""
    x = x - 0.5
    y = y - 0.5
    x = x - w * np.floor(x / w)
    y = y - h * np.floor(y / h)
    ix = min(int(x), w - 1)
    iy = min(int(y), h - 1)
    fx = x - ix
    fy = y - iy
    ix1 = ix + 1 if ix + 1 < w else 0
    iy1 = iy + 1 if iy + 1 < h else 0
    a = atlas[off + iy * w + ix]
    b = atlas[off + iy * w + ix1]
    c = atlas[off + iy1 * w + ix]
    d = atlas[off + iy1 * w + ix1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _trilinear(atlas, loff, lw, lh, lcnt, m, s, t, lod):
    """Trilinear (mip-mapped) sample of material ``m`` at level-0 texel ``(s, t)``."""
    top = lcnt[m] - 1
    if lod < 0.0:
        lod = 0.0
    if lod > top:
        lod = float(top)
    l0 = int(lod)
    fl = lod - l0
    w0 = lw[m, 0]
    h0 = lh[m, 0]
    a = _bilinear(atlas, loff[m, l0], lw[m, l0], lh[m, l0], s * lw[m, l0] / w0, t * lh[m, l0] / h0)
    if fl <= 0.0 or l0 >= top:
        return a
    l1 = l0 + 1
    b = _bilinear(atlas, loff[m, l1], lw[m, l1], lh[m, l1], s * lw[m, l1] / w0, t * lh[m, l1] / h0)
    return a * (1 - fl) + b * fl


@njit(cache=True, nogil=True, error_model="numpy")
def _shade(
    prim,
    bu,
    bv,
    dirs,
    origin,
    tri,
    normals,
    ftex,
    fmat,
    ftpm,
    atlas,
    loff,
    lw,
    lh,
    lcnt,
    R_kM,
    p_MinCk,
    pix_rad,
    sun,
    has_sun,
    eps,
    truth,
    hit_out,
    depth_out,
    albedo_out,
    cos_out,
    shadow_origin,
    shadow_dir,
    shadow_ray,
):
    """Per ray: point in M (float32), depth along the camera axis, albedo and cos(sun); misses
    get NaN point and depth, zero albedo and cos(sun); ``truth`` False leaves ``hit_out`` and
    ``depth_out`` untouched (they may be of length 1).  The rays whose point faces the sun get
    a shadow ray, packed into the first rows of ``shadow_origin``/``shadow_dir``
    (``shadow_ray`` holds their ray index); returns their number."""
    nan = np.nan
    n_lit = 0
    for i in range(prim.shape[0]):
        f = prim[i]
        if f < 0:
            if truth:
                hit_out[i, 0] = nan
                hit_out[i, 1] = nan
                hit_out[i, 2] = nan
                depth_out[i] = nan
            albedo_out[i] = 0.0
            cos_out[i] = 0.0
            continue
        b1 = np.float64(bu[i])
        b2 = np.float64(bv[i])
        b0 = 1.0 - b1 - b2
        # Embree barycentrics: p = (1 - u - v) v0 + u v1 + v v2
        hx = b0 * tri[f, 0, 0] + b1 * tri[f, 1, 0] + b2 * tri[f, 2, 0]
        hy = b0 * tri[f, 0, 1] + b1 * tri[f, 1, 1] + b2 * tri[f, 2, 1]
        hz = b0 * tri[f, 0, 2] + b1 * tri[f, 1, 2] + b2 * tri[f, 2, 2]
        if truth:
            hit_out[i, 0] = hx
            hit_out[i, 1] = hy
            hit_out[i, 2] = hz
            depth_out[i] = R_kM[1, 0] * hx + R_kM[1, 1] * hy + R_kM[1, 2] * hz + p_MinCk[1]
        dx = np.float64(dirs[i, 0])
        dy = np.float64(dirs[i, 1])
        dz = np.float64(dirs[i, 2])
        dn = np.sqrt(dx * dx + dy * dy + dz * dz)
        nx = normals[f, 0]
        ny = normals[f, 1]
        nz = normals[f, 2]
        c = (nx * dx + ny * dy + nz * dz) / dn
        if c > 0.0:  # back face: turn the normal towards the camera (two-sided surfaces)
            nx, ny, nz, c = -nx, -ny, -nz, -c
        ex = hx - origin[0]
        ey = hy - origin[1]
        ez = hz - origin[2]
        dist = np.sqrt(ex * ex + ey * ey + ez * ez)
        # pixel footprint on the surface (m), stretched by the incidence: sets the mip level
        foot = dist * pix_rad / np.sqrt(max(-c, 0.05))
        lod = np.log2(max(foot * ftpm[f], 1e-12))
        s = b0 * ftex[f, 0, 0] + b1 * ftex[f, 1, 0] + b2 * ftex[f, 2, 0]
        t = b0 * ftex[f, 0, 1] + b1 * ftex[f, 1, 1] + b2 * ftex[f, 2, 1]
        albedo_out[i] = _trilinear(atlas, loff, lw, lh, lcnt, fmat[f], s, t, lod)
        cs = 0.0
        if has_sun:
            cs = nx * sun[0] + ny * sun[1] + nz * sun[2]
            if cs < 0.0:
                cs = 0.0
        cos_out[i] = cs
        if cs > 0.0:
            shadow_origin[n_lit, 0] = hx + eps * nx
            shadow_origin[n_lit, 1] = hy + eps * ny
            shadow_origin[n_lit, 2] = hz + eps * nz
            shadow_dir[n_lit, 0] = sun[0]
            shadow_dir[n_lit, 1] = sun[1]
            shadow_dir[n_lit, 2] = sun[2]
            shadow_ray[n_lit] = i
            n_lit += 1
    return n_lit


@njit(cache=True, nogil=True, error_model="numpy")
def _coverage(tri_uv, rh, rw, margin, cover):
    """Mark in ``cover`` (rh, rw) the pixels of the ROI whose square, grown by ``margin`` px,
    meets a projected triangle (``tri_uv`` (F, 3, 2): vertex pixel coordinates relative to the
    ROI corner, every vertex in front of the camera): per triangle and pixel row, the exact
    column extent of the triangle within the row's strip (the strip's polygon has its
    vertices on the clipped edges)."""
    for f in range(tri_uv.shape[0]):
        vmin = min(tri_uv[f, 0, 1], tri_uv[f, 1, 1], tri_uv[f, 2, 1])
        vmax = max(tri_uv[f, 0, 1], tri_uv[f, 1, 1], tri_uv[f, 2, 1])
        r0 = max(int(np.floor(vmin - margin)), 0)
        r1 = min(int(np.floor(vmax + margin)) + 1, rh)
        for j in range(r0, r1):
            ylo = j - margin
            yhi = j + 1.0 + margin
            xmin = np.inf
            xmax = -np.inf
            for e in range(3):
                ua = tri_uv[f, e, 0]
                va = tri_uv[f, e, 1]
                ub = tri_uv[f, (e + 1) % 3, 0]
                vb = tri_uv[f, (e + 1) % 3, 1]
                if max(va, vb) < ylo or min(va, vb) > yhi:
                    continue
                if va == vb:
                    xa = ua
                    xb = ub
                else:  # the edge's part inside the strip
                    ta = min(max((ylo - va) / (vb - va), 0.0), 1.0)
                    tb = min(max((yhi - va) / (vb - va), 0.0), 1.0)
                    xa = ua + ta * (ub - ua)
                    xb = ua + tb * (ub - ua)
                xmin = min(xmin, xa, xb)
                xmax = max(xmax, xa, xb)
            if xmax < xmin:
                continue
            c0 = max(int(np.floor(xmin - margin)), 0)
            c1 = min(int(np.floor(xmax + margin)) + 1, rw)
            for i in range(c0, c1):
                cover[j, i] = True


@njit(cache=True, nogil=True, error_model="numpy")
def _covered_pixels(cover, i0, j0, w):
    """The marked ROI pixels of ``cover``: their flat ROI indices, their flat indices in a
    frame ``w`` wide (ROI corner at pixel ``(i0, j0)``) and the box (rows ``[r0, r1)``,
    columns ``[c0, c1)``, frame pixels) that holds them."""
    rh, rw = cover.shape
    n = 0
    for j in range(rh):
        for i in range(rw):
            if cover[j, i]:
                n += 1
    pix = np.empty(n, np.int64)
    at = np.empty(n, np.int64)
    r0, r1, c0, c1 = rh, 0, rw, 0
    m = 0
    for j in range(rh):
        for i in range(rw):
            if cover[j, i]:
                pix[m] = j * rw + i
                at[m] = (j + j0) * w + i + i0
                m += 1
                r0 = min(r0, j)
                r1 = max(r1, j + 1)
                c0 = min(c0, i)
                c1 = max(c1, i + 1)
    return pix, at, r0 + j0, r1 + j0, c0 + i0, c1 + i0


@njit(cache=True, nogil=True, error_model="numpy")
def _scatter(at, values, out):
    """``out[at[i]] = values[i]`` (flat arrays; rows of ``values`` and ``out`` when 2-D)."""
    if values.ndim == 1:
        for i in range(at.size):
            out[at[i]] = values[i]
    else:
        for i in range(at.size):
            for c in range(values.shape[1]):
                out[at[i], c] = values[i, c]


@njit(cache=True, nogil=True, error_model="numpy")
def _primary_rays(pix, rw, n, i0, j0, cu, cv, f, R_kM, origin, dirs, origins):
    """Rays of the ROI pixels ``pix`` (flat, row-major in a ROI ``rw`` wide whose corner is
    pixel ``(i0, j0)``), an n x n grid each at sub-pixel ``(a + 0.5) / n``, ordered (pixel,
    sub-row, sub-column): ``(x, 1, z)`` in camera k (so Embree's t is the depth) turned into
    M, ``x r0 + r1 + z r2`` with ``r_i`` the rows of ``R_kM``."""
    r = 0
    for p in pix:
        row = j0 + p // rw
        col = i0 + p % rw
        for a in range(n):
            z = (row + (a + 0.5) / n - cv) / f
            for b in range(n):
                x = (col + (b + 0.5) / n - cu) / f
                for c in range(3):
                    dirs[r, c] = x * R_kM[0, c] + R_kM[1, c] + z * R_kM[2, c]
                    origins[r, c] = origin[c]
                r += 1


@njit(cache=True, nogil=True, error_model="numpy")
def _light(albedo, cos_sun, lit, occluded, exposure, ambient, level_out):
    """Image level ``exposure * albedo * (ambient + (1 - ambient) cos_sun visible)``; the rays
    ``lit[j]`` with ``occluded[j] >= 0`` are in shadow."""
    for j in range(lit.shape[0]):
        if occluded[j] >= 0:
            cos_sun[lit[j]] = 0.0
    for i in range(albedo.shape[0]):
        level_out[i] = exposure * albedo[i] * (ambient + (1.0 - ambient) * cos_sun[i])


# ---------------------------------------------------------------------------------------------
# scene (built once per target mesh and texture mode)


@dataclass(frozen=True, eq=False)
class _Scene:
    embree: Any
    tri: Array  # (F, 3, 3) vertices of each face in M (m)
    normals: Array  # (F, 3) unit face normals in M
    corners_M: Array  # (8, 3) bounding-box corners in M
    vertices: Array  # (V, 3) mesh vertices in M (m)
    faces: NDArray[np.int64]  # (F, 3) vertex indices of each face
    eps_m: float  # shadow-ray offset
    tex: SurfaceTextures


_SCENES: dict[tuple[int, str], tuple[weakref.ref, _Scene]] = {}
_SCENES_LOCK = threading.Lock()


def _scene_for(model: TargetModel, texture: str) -> _Scene:
    """The Embree scene and textures of ``model.mesh``, cached while the mesh lives."""
    mesh = model.mesh
    key = (id(mesh), texture)
    with _SCENES_LOCK:
        hit = _SCENES.get(key)
        if hit is not None and hit[0]() is mesh:
            return hit[1]
    vertices = np.asarray(mesh.vertices, dtype=float)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(faces) == 0:
        raise InputError("the target mesh has no triangles")
    if not np.all(np.isfinite(vertices)):
        raise InputError("the target mesh has non-finite vertices")
    embree = rtcore_scene.EmbreeScene()
    TriangleMesh(embree, vertices.astype(np.float32), faces.astype(np.int32))
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    scale = float(np.linalg.norm(hi - lo))
    scene = _Scene(
        embree=embree,
        tri=np.ascontiguousarray(tri),
        normals=np.ascontiguousarray(n),
        corners_M=corners,
        vertices=np.ascontiguousarray(vertices),
        faces=np.ascontiguousarray(faces),
        eps_m=max(1e-5 * scale, 1e-6) * 10.0,
        tex=surface_textures(mesh, texture),
    )
    with _SCENES_LOCK:
        for k in [k for k, (ref, _) in _SCENES.items() if ref() is None]:
            del _SCENES[k]
        _SCENES[key] = (weakref.ref(mesh), scene)
    return scene


# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _CameraFrame:
    signal: F32  # (H, W) image level, fraction of full scale
    support: tuple[int, int, int, int]  # rows [j0, j1), columns [i0, i1): signal 0 outside
    depth: F32 | None
    hit: F32 | None
    mask: NDArray[np.bool_] | None


def _as_matrix(a: ArrayLike, shape: tuple[int, ...], name: str) -> Array:
    out = np.asarray(a, dtype=float)
    if out.shape != shape or not np.all(np.isfinite(out)):
        raise InputError(f"{name} must be a finite array of shape {shape}, got {out.shape}")
    return out


class StereoRenderer:
    """Renders stereo pairs of one target model seen by one rig (scene built once, cached).

    Parameters
    ----------
    model : TargetModel
        The target geometry (mesh in the model frame M, metres).
    rig : StereoRig
        Any parallel or convergent rig (each camera its own intrinsics, size and pose).
    settings : RenderSettings
    """

    def __init__(
        self, model: TargetModel, rig: StereoRig, settings: RenderSettings = RenderSettings()
    ) -> None:
        self.model = model
        self.rig = rig
        self.settings = settings
        self._scene = _scene_for(model, settings.texture)
        noise = settings.noise
        self._defects: tuple[DefectPattern | None, ...] = tuple(
            defect_pattern(noise, (c.resolution_px[1], c.resolution_px[0]), k)
            if noise is not None
            else None
            for k, c in enumerate(rig.cameras)
        )

    def __getstate__(self) -> dict[str, Any]:
        # the Embree scene cannot be pickled: rebuilt (or found in the cache) on unpickling
        return {"model": self.model, "rig": self.rig, "settings": self.settings}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["model"], state["rig"], state["settings"])  # type: ignore[misc]

    @property
    def texture_source(self) -> str:
        """The texture actually used: 'procedural' or 'mesh'."""
        return self._scene.tex.source

    def render(
        self,
        R_CM: ArrayLike,
        p_MinC: ArrayLike,
        sun_C: ArrayLike | None,
        rng: np.random.Generator | None,
        truth: bool = True,
    ) -> RenderedPair:
        """Render both cameras at one model pose.

        Parameters
        ----------
        R_CM : (3, 3) array
            Rotation mapping model-frame M coordinates into the rig frame C.
        p_MinC : (3,) array
            Origin of M in C (m).
        sun_C : (3,) array or None
            Direction from the target towards the sun, in C (normalised here); None: eclipse.
        rng : numpy.random.Generator
            Source of the image noise; not used (may be None) when the noise draws nothing.
        truth : bool
            Also return depth, hit-point and mask maps (False skips them).
        """
        R = _as_matrix(R_CM, (3, 3), "R_CM")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            raise InputError("R_CM must be a rotation matrix")
        p = _as_matrix(p_MinC, (3,), "p_MinC")
        sun_M = None
        if sun_C is not None:
            s = _as_matrix(sun_C, (3,), "sun_C")
            norm = float(np.linalg.norm(s))
            if norm == 0.0:
                raise InputError("sun_C must be a non-zero vector (None for eclipse)")
            sun_M = R.T @ (s / norm)
        noise = self.settings.noise
        seeds: list[int | None] = [None, None]
        if noise is not None and noise.random:
            if rng is None:
                raise InputError("render needs a random generator for this image noise")
            seeds = [int(x) for x in rng.integers(0, 2**63 - 1, size=2)]

        def job(k: int) -> tuple[NDArray[np.uint8], _CameraFrame]:
            frame = self._render_camera(k, R, p, sun_M, truth)
            gen = np.random.default_rng(seeds[k]) if seeds[k] is not None else None
            img = apply_noise(frame.signal, noise, gen, self._defects[k], frame.support)
            return img, frame

        if self.settings.threads == 2:
            with ThreadPoolExecutor(max_workers=2) as pool:
                out = list(pool.map(job, (0, 1)))
        else:
            out = [job(0), job(1)]
        (img0, f0), (img1, f1) = out
        same = img0.shape == img1.shape

        def stack(a: Any, b: Any) -> Any:
            if a is None:
                return None
            return np.stack([a, b]) if same else (a, b)

        return RenderedPair(
            images=stack(img0, img1),
            depth_m=stack(f0.depth, f1.depth),
            hit_M=stack(f0.hit, f1.hit),
            mask=stack(f0.mask, f1.mask),
        )

    # -----------------------------------------------------------------------------------------

    def _roi(self, cam: Camera, R_kM: Array, p_MinCk: Array) -> tuple[int, int, int, int]:
        """Pixel columns [i0, i1) and rows [j0, j1) that can see the target's bounding box."""
        w, h = cam.resolution_px
        pts = self._scene.corners_M @ R_kM.T + p_MinCk
        y = pts[:, 1]
        if np.all(y <= 0.0):
            return 0, 0, 0, 0
        if np.any(y <= 1e-9):  # the box straddles the camera plane: the whole image
            return 0, w, 0, h
        f, (cu, cv) = cam.focal_px, cam.principal_point_px
        u = cu + f * pts[:, 0] / y
        v = cv + f * pts[:, 2] / y
        i0 = int(np.clip(np.floor(u.min()) - 1, 0, w))
        i1 = int(np.clip(np.ceil(u.max()) + 1, 0, w))
        j0 = int(np.clip(np.floor(v.min()) - 1, 0, h))
        j1 = int(np.clip(np.ceil(v.max()) + 1, 0, h))
        return i0, i1, j0, j1

    def _covered(
        self, cam: Camera, R_kM: Array, p_MinCk: Array, roi: tuple[int, int, int, int]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], tuple[int, int, int, int]]:
        """The ROI pixels that the target's triangles may cover (their projections grown by
        ``_COVER_MARGIN_PX``; every pixel when a vertex is not in front of the camera): flat
        indices in the ROI and in the frame, and the box (rows, columns) holding them.  The
        other pixels' rays would miss: they are not cast."""
        sc = self._scene
        i0, i1, j0, j1 = roi
        rh, rw = j1 - j0, i1 - i0
        w = cam.resolution_px[0]
        cover = np.zeros((rh, rw), np.bool_)
        pts = sc.vertices @ R_kM.T + p_MinCk
        y = pts[:, 1]
        if np.any(y <= 1e-9):
            cover[:] = True
        else:
            f, (cu, cv) = cam.focal_px, cam.principal_point_px
            uv = np.empty((len(pts), 2))
            uv[:, 0] = cu + f * pts[:, 0] / y - i0
            uv[:, 1] = cv + f * pts[:, 2] / y - j0
            _coverage(uv[sc.faces], rh, rw, _COVER_MARGIN_PX, cover)
        pix, at, r0, r1, c0, c1 = _covered_pixels(cover, i0, j0, w)
        return pix, at, (int(r0), int(r1), int(c0), int(c1))

    def _cast(
        self,
        cam: Camera,
        R_kM: Array,
        p_MinCk: Array,
        sun_M: Array | None,
        roi: tuple[int, int, int, int],
        pix: NDArray[np.int64],
        n: int,
        shade: bool,
        truth: bool,
    ) -> tuple[NDArray[np.int32], F32, F32, F32]:
        """Cast an n x n grid of rays per ROI pixel ``pix``; returns per pixel (prim, hit,
        depth, level), prim, hit and depth of the pixel's first ray (``truth`` False: hit and
        depth are not filled), the level averaged over its n x n rays."""
        sc = self._scene
        i0, i1, j0, j1 = roi
        f, (cu, cv) = cam.focal_px, cam.principal_point_px
        nr = pix.size * n * n
        origin = -R_kM.T @ p_MinCk  # the camera centre in M
        dirs = np.empty((nr, 3), np.float32)
        orig = np.empty((nr, 3), np.float32)
        _primary_rays(pix, i1 - i0, n, i0, j0, cu, cv, f, R_kM, origin, dirs, orig)
        res = sc.embree.run(orig, dirs, output=1)
        prim = res["primID"]
        m = nr if truth else 1
        hit = np.empty((m, 3), np.float32)
        depth = np.empty(m, np.float32)
        albedo = np.empty(nr, np.float32)
        cos_s = np.empty(nr, np.float32)
        s_orig = orig  # reused: rewritten for the rays that need a shadow ray
        s_dir = np.empty((nr, 3), np.float32)
        s_ray = np.empty(nr, np.int64)
        sun = np.zeros(3) if sun_M is None else sun_M
        tex = sc.tex
        n_lit = _shade(
            prim,
            res["u"],
            res["v"],
            dirs,
            origin,
            sc.tri,
            sc.normals,
            tex.face_texel,
            tex.face_material,
            tex.face_texel_per_m,
            tex.atlas,
            tex.level_offset,
            tex.level_width,
            tex.level_height,
            tex.level_count,
            R_kM,
            p_MinCk,
            1.0 / (f * n),
            sun,
            shade and sun_M is not None,
            sc.eps_m,
            truth,
            hit,
            depth,
            albedo,
            cos_s,
            s_orig,
            s_dir,
            s_ray,
        )
        level = np.zeros(nr, np.float32)
        if shade and sun_M is not None:
            st = self.settings
            occluded = np.zeros(0, np.int32)
            if n_lit:
                occluded = sc.embree.run(s_orig[:n_lit], s_dir[:n_lit], query="OCCLUDED")
            _light(albedo, cos_s, s_ray[:n_lit], occluded, st.exposure, st.ambient, level)
        if n > 1:
            level = level.reshape(pix.size, n * n).mean(axis=1)
            prim, hit, depth = prim[:: n * n], hit[:: n * n], depth[:: n * n]
        return prim, hit, depth, level

    def _render_camera(
        self, k: int, R_CM: Array, p_MinC: Array, sun_M: Array | None, truth: bool
    ) -> _CameraFrame:
        cam = self.rig.cameras[k]
        w, h = cam.resolution_px
        R_kM = cam.R_CkC @ R_CM
        p_MinCk = cam.R_CkC @ (p_MinC - cam.p_CkinC)
        i0, i1, j0, j1 = roi = self._roi(cam, R_kM, p_MinCk)
        signal = np.zeros((h, w), np.float32)
        depth = hit_map = mask = None
        if truth:
            depth = np.full((h, w), np.nan, np.float32)
            hit_map = np.full((h, w, 3), np.nan, np.float32)
            mask = np.zeros((h, w), bool)
        empty = (0, 0, 0, 0)
        if i1 <= i0 or j1 <= j0:
            return _CameraFrame(signal, empty, depth, hit_map, mask)
        n = self.settings.supersample
        shade_centre = n == 1 and sun_M is not None
        if not (truth or sun_M is not None):
            return _CameraFrame(signal, empty, depth, hit_map, mask)
        pix, at, support = self._covered(cam, R_kM, p_MinCk, roi)
        if pix.size == 0:
            return _CameraFrame(signal, empty, depth, hit_map, mask)
        if truth or shade_centre:
            prim, hit, dep, level = self._cast(
                cam, R_kM, p_MinCk, sun_M, roi, pix, 1, shade_centre, truth
            )
            if shade_centre:
                _scatter(at, level, signal.reshape(-1))
            if truth:
                assert depth is not None and hit_map is not None and mask is not None
                _scatter(at, prim >= 0, mask.reshape(-1))
                _scatter(at, dep, depth.reshape(-1))
                _scatter(at, hit, hit_map.reshape(-1, 3))
        if n > 1 and sun_M is not None:
            level = self._cast(cam, R_kM, p_MinCk, sun_M, roi, pix, n, True, False)[3]
            _scatter(at, level, signal.reshape(-1))
        return _CameraFrame(signal, support, depth, hit_map, mask)
