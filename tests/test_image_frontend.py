"""Image front end (Chang 2021 Sec. 2.3-2.4): FAST + LK + epipolar NCC + feature management.

The scenes are exact: a textured plane at a known pose is rendered into each camera by casting
the ray of every pixel centre ``(i + 0.5, j + 0.5)`` (tumblenav pixels) to the plane, so the 3D
point, the right-image correspondence and the motion of every pixel are known.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tumblenav.errors import InputError
from tumblenav.frontends.stereo_images import (
    EpipolarGeometry,
    ImageFrontEndTuning,
    ImageTracker,
    MatchStatus,
    StereoMatcher,
    most_tracked_to_remove,
    track_images,
)
from tumblenav.frontends.stereo_images.detection import (
    FAST_CIRCLE,
    CornerDetector,
    feature_mask,
    sad_response,
)
from tumblenav.frontends.stereo_images.ecc_kernel import ECC_OK, ecc_affine
from tumblenav.frontends.stereo_images.matching import parabola_peak, sample_patches
from tumblenav.frontends.stereo_images.refine import refine_affine, template_at
from tumblenav.frontends.stereo_images.tuning import REFINED_TRACK_NOISE_PX
from tumblenav.frontends.triangulation import triangulate_two_ray
from tumblenav.measurements.stereo import StereoMeasurements
from tumblenav.sensors.stereo import convergent_rig, parallel_rig, project

W, H = 320, 240
F_PX = 300.0
B_M = 0.4


def _rigs():
    return {
        "parallel": parallel_rig(F_PX, B_M, (W, H)),
        "convergent": convergent_rig(F_PX, B_M, np.radians(4.0), (W, H)),
    }


def _texture(seed: int, size: int = 768) -> np.ndarray:
    """Smoothed noise plus flat rectangles (corners for FAST), grey levels in [1, 255]."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (size, size)).astype(np.float32), (0, 0), 3.0)
    tex = 128.0 + 40.0 * tex / tex.std()
    for _ in range(250):
        x, y = rng.integers(0, size, 2)
        w, h = rng.integers(8, 40, 2)
        tex[y : y + h, x : x + w] = rng.uniform(20.0, 235.0)
    tex = cv2.GaussianBlur(tex, (0, 0), 1.0)
    return np.clip(tex, 1.0, 255.0).astype(np.float32)


class Plane:
    """A textured plane: centre ``o`` (C, m), in-plane unit axes ``e1``, ``e2`` (C)."""

    def __init__(self, tex, texel_m, o, e1, e2):
        self.tex, self.texel = tex, texel_m
        self.o, self.e1, self.e2 = (np.asarray(x, float) for x in (o, e1, e2))
        self.n = np.cross(self.e1, self.e2)

    def moved(self, rotvec, t) -> Plane:
        R = Rotation.from_rotvec(rotvec).as_matrix()
        return Plane(self.tex, self.texel, self.o + np.asarray(t), R @ self.e1, R @ self.e2)

    def hit(self, origin, d):
        s = ((self.o - origin) @ self.n) / (d @ self.n)
        return origin + s[..., None] * d, s

    def texel_coords(self, P):
        c = self.tex.shape[0] / 2 - 0.5
        return (P - self.o) @ self.e1 / self.texel + c, (P - self.o) @ self.e2 / self.texel + c

    def point(self, a, b):
        c = self.tex.shape[0] / 2 - 0.5
        return (
            self.o
            + ((a - c) * self.texel)[:, None] * self.e1
            + ((b - c) * self.texel)[:, None] * self.e2
        )


def _plane(seed: int = 1, yaw_deg: float = 20.0) -> Plane:
    e1 = Rotation.from_euler("z", yaw_deg, degrees=True).apply([1.0, 0.0, 0.0])
    return Plane(_texture(seed), 0.006, [0.2, 3.0, 0.0], e1, [0.0, 0.0, 1.0])


def _render(rig, plane: Plane, k: int) -> np.ndarray:
    cam = rig.cameras[k]
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)  # pixel centres, tumblenav
    cu, cv = cam.principal_point_px
    d_cam = np.stack([(u - cu) / cam.focal_px, np.ones_like(u), (v - cv) / cam.focal_px], -1)
    P, s = plane.hit(cam.p_CkinC, d_cam @ cam.R_CkC)
    a, b = plane.texel_coords(P)
    a[s <= 0], b[s <= 0] = -10.0, -10.0
    img = cv2.remap(
        plane.tex, a.astype(np.float32), b.astype(np.float32), cv2.INTER_LINEAR, borderValue=0
    )
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _pair(rig, plane):
    return _render(rig, plane, 0), _render(rig, plane, 1)


def _truth(rig, plane, uv_l):
    """3D points seen at the left pixels and their true right pixels (and whether inside)."""
    geo = EpipolarGeometry(rig)
    P, _ = plane.hit(geo.c[0], geo.left_rays(uv_l))
    uv, inside = project(rig, P)
    return P, uv[1], inside[1]


# ----------------------------------------------------------------------------- geometry


@pytest.mark.parametrize("kind", ["parallel", "convergent"])
def test_fundamental_matrix_and_segments(kind):
    rig = _rigs()[kind]
    geo = EpipolarGeometry(rig)
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(1.5, 30, 50), rng.uniform(-1, 1, 50)])
    uv, _ = project(rig, p)
    x_l = np.column_stack([uv[0], np.ones(50)])
    x_r = np.column_stack([uv[1], np.ones(50)])
    assert np.abs(np.einsum("ni,ij,nj->n", x_r, geo.F, x_l)).max() < 1e-9
    assert geo.epipolar_distance(uv[0], uv[1]).max() < 1e-9
    lam = geo.left_depth(p)
    assert np.allclose(geo.right_of_depth(uv[0], lam), uv[1], atol=1e-9)
    assert np.allclose(geo.triangulate(uv[0], uv[1]), p, atol=1e-9)
    near, far = geo.right_segments(uv[0], 1.0, None)
    assert geo.epipolar_distance(uv[0], near).max() < 1e-9
    assert geo.epipolar_distance(uv[0], far).max() < 1e-9
    # the true right pixel lies between the near (1 m) and far (vanishing point) ends
    t = np.sum((uv[1] - near) * (far - near), axis=1) / np.sum((far - near) ** 2, axis=1)
    assert ((t > 0) & (t < 1)).all()
    d_l, d_r = geo.directions(uv[0], lam)
    if kind == "parallel":
        assert np.allclose(d_l, [1.0, 0.0]) and np.allclose(d_r, [1.0, 0.0])


def test_sampling_uses_tumblenav_pixel_centres():
    img = np.arange(H * W, dtype=np.uint32).reshape(H, W) % 251
    img = img.astype(np.uint8)
    i, j = np.array([10, 100, 200]), np.array([20, 50, 230])
    c = np.column_stack([i + 0.5, j + 0.5])  # tumblenav centres of pixels (i, j)
    patches = sample_patches(img, c, np.tile([1.0, 0.0], (3, 1)), 1)
    assert np.array_equal(patches[:, 1, 1], img[j, i])
    assert np.array_equal(patches[:, 1, 2], img[j, i + 1])  # columns along +u
    assert np.array_equal(patches[:, 2, 1], img[j + 1, i])  # rows along +v


def test_parabola_peak():
    x0 = 0.3
    s = 1.0 - (np.array([-1.0, 0.0, 1.0]) - x0) ** 2
    assert parabola_peak(s[:1], s[1:2], s[2:])[0] == pytest.approx(x0)


# ----------------------------------------------------------------------------- detection


def test_sad_response_is_chang_definition():
    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, (20, 20)).astype(np.uint8)
    r, c = 9, 11
    expected = sum(abs(int(img[r, c]) - int(img[r + dy, c + dx])) for dx, dy in FAST_CIRCLE)
    assert sad_response(img, np.array([c]), np.array([r]))[0] == expected
    assert len({tuple(o) for o in FAST_CIRCLE}) == 16
    assert np.allclose(np.hypot(*FAST_CIRCLE.T), 3.0, atol=0.2)


@pytest.mark.parametrize("response", ["sad", "opencv"])
def test_detection_respects_mask_and_ranks(response):
    rig = _rigs()["parallel"]
    left, _ = _pair(rig, _plane())
    tu = ImageFrontEndTuning(response=response)
    existing = np.array([[100.5, 100.5], [200.2, 50.7]])
    mask = feature_mask((H, W), existing, 5, 8)
    assert mask[100, 98:103].max() == 0 and mask[100, 103] == 255 and mask[100, 97] == 255
    uv, resp = CornerDetector(tu).detect(left, mask)
    assert len(uv) > 100
    assert np.all(np.diff(resp) <= 0)
    assert np.allclose(uv % 1.0, 0.5)  # pixel centres in tumblenav pixels
    cheb = np.abs(np.floor(uv)[:, None, :] - np.floor(existing)[None]).max(axis=2)
    assert cheb.min() >= 3  # nothing in the 5 x 5 squares
    assert (uv >= 8).all() and (uv[:, 0] <= W - 8).all() and (uv[:, 1] <= H - 8).all()


# ----------------------------------------------------------------------------- matching


@pytest.mark.parametrize("kind", ["parallel", "convergent"])
def test_epipolar_match_and_triangulation_accuracy(kind):
    rig = _rigs()[kind]
    plane = _plane()
    left, right = _pair(rig, plane)
    tu = ImageFrontEndTuning()
    uv_l, _ = CornerDetector(tu).detect(left, feature_mask((H, W), np.zeros((0, 2)), 5, 8))
    uv_l = uv_l[:300]
    res = StereoMatcher(EpipolarGeometry(rig), tu).match(left, right, uv_l)
    P, uv_true, inside = _truth(rig, plane, uv_l)
    ok = res.ok
    assert ok.mean() > 0.8
    err = np.hypot(*(res.uv_r - uv_true).T)
    well_inside = inside & (uv_true[:, 0] > 10) & (uv_true[:, 0] < W - 10)
    e = err[ok & well_inside]
    assert np.mean(e < 0.5) >= 0.98 and e.max() < 1.0 and np.median(e) < 0.2
    assert np.isnan(res.uv_r[~ok]).all()
    # triangulation: depth error within what the pixel error explains
    geo = EpipolarGeometry(rig)
    p = geo.triangulate(uv_l[ok], res.uv_r[ok])
    depth = geo.left_depth(P[ok])
    dz = np.abs(geo.left_depth(p) - depth)
    sel = well_inside[ok]
    assert np.all(dz[sel] <= depth[sel] ** 2 / (F_PX * B_M) * 1.2 * err[ok][sel] + 1e-6)


def _chang_eq31(uv_l, uv_r, f, b, a, pp):
    """Chang 2021 eq. 31, corrected (stereo module notes: cos a - sin a; arctan^-1 = arctan),
    in the left camera frame (x right, y = optical axis = the paper's Z, z down)."""
    ul, vl, ur = uv_l[:, 0], uv_l[:, 1], uv_r[:, 0]
    T = np.tan(2 * a + np.arctan((pp[0] - ur) / f) - np.pi / 2)
    Z = f * b * (T * np.cos(a) - np.sin(a)) / (T * (ul - pp[0]) - f)
    return np.stack([Z * (ul - pp[0]) / f, Z, Z * (vl - pp[1]) / f], axis=-1)


def test_chang_eq31_agrees_with_two_ray_triangulation():
    a = np.radians(10.0)
    rig = convergent_rig(F_PX, B_M, a, (W, H))
    pp = rig.left.principal_point_px
    args = (F_PX, pp, rig.left.R_CkC, rig.left.p_CkinC, rig.right.R_CkC, rig.right.p_CkinC)
    # exact projections: identical up to rounding
    rng = np.random.default_rng(4)
    p = np.column_stack([rng.uniform(-0.5, 1.0, 40), rng.uniform(2, 8, 40), rng.uniform(-1, 1, 40)])
    uv, _ = project(rig, p)
    two_ray = triangulate_two_ray(uv[0], uv[1], *args)
    eq31 = _chang_eq31(uv[0], uv[1], F_PX, B_M, a, pp) @ rig.left.R_CkC  # C0 -> C
    assert np.allclose(two_ray, p, atol=1e-9) and np.allclose(eq31, p, atol=1e-9)
    # the front end's matches (v_r ignored by eq. 31): agree within the match noise
    plane = _plane(yaw_deg=0.0)
    fr = ImageTracker(rig, ImageFrontEndTuning(n_min=60, n_max=60)).step(*_pair(rig, plane))
    assert len(fr.ids) == 60
    eq31 = _chang_eq31(fr.uv[0], fr.uv[1], F_PX, B_M, a, pp) @ rig.left.R_CkC
    assert np.allclose(fr.p_inC, triangulate_two_ray(fr.uv[0], fr.uv[1], *args))
    depth = fr.p_inC @ rig.left.R_CkC[1]
    sigma_depth = depth**2 / (F_PX * B_M)  # m per px of disparity
    assert np.all(np.linalg.norm(eq31 - fr.p_inC, axis=1) < 0.5 * sigma_depth)


def test_flat_patches_are_not_matched():
    rig = _rigs()["parallel"]
    flat = np.full((H, W), 90, np.uint8)
    res = StereoMatcher(EpipolarGeometry(rig), ImageFrontEndTuning()).match(
        flat, flat, np.array([[100.5, 100.5], [150.5, 60.5]])
    )
    assert (res.status == MatchStatus.NO_TEXTURE).all() and np.isnan(res.uv_r).all()


# ----------------------------------------------------------------------------- tracking


def _material_points(rig, plane, uv_l):
    """Texture coordinates of the surface seen at the left pixels."""
    geo = EpipolarGeometry(rig)
    P, _ = plane.hit(geo.c[0], geo.left_rays(uv_l))
    return plane.texel_coords(P)


@pytest.mark.parametrize("kind", ["parallel", "convergent"])
def test_lk_tracks_a_known_motion(kind):
    rig = _rigs()[kind]
    plane = _plane()
    tracker = ImageTracker(rig, ImageFrontEndTuning(n_min=80, n_max=80))
    fr0 = tracker.step(*_pair(rig, plane))
    a, b = _material_points(rig, plane, fr0.uv[0])
    moved = plane.moved([0.0, 0.02, 0.01], [0.03, -0.05, 0.02])
    fr1 = tracker.step(*_pair(rig, moved))
    assert fr1.stats.tracked >= 75
    kept = np.searchsorted(fr0.ids, fr1.ids[fr1.age == 2])
    uv_true, inside = project(rig, moved.point(a[kept], b[kept]))
    err = np.hypot(*(fr1.uv[0, fr1.age == 2] - uv_true[0]).T)
    assert np.median(err) < 0.1 and err.max() < 0.5
    # right pixels of the tracked features still within 0.5 px of their correspondence
    _, uv_r, _ = _truth(rig, moved, fr1.uv[0])
    assert np.mean(np.hypot(*(fr1.uv[1] - uv_r).T) < 0.5) >= 0.97


def test_forward_backward_rejects_a_corrupted_track():
    rig = _rigs()["parallel"]
    plane = _plane()
    tracker = ImageTracker(rig, ImageFrontEndTuning(n_min=40, n_max=40))
    fr0 = tracker.step(*_pair(rig, plane))
    left, right = _pair(rig, plane.moved([0, 0, 0], [0.01, 0.0, 0.0]))
    u, v = np.floor(fr0.uv[0, 5]).astype(int)
    left[v - 6 : v + 7, u - 6 : u + 7] = left[v - 6 : v + 7, u - 6 : u + 7][::-1, ::-1].copy()
    fr1 = tracker.step(left, right)
    assert fr0.ids[5] not in fr1.ids
    assert fr1.stats.fb_rejected >= 1 and fr1.stats.lost == 0
    # an uncorrupted run keeps every track
    t2 = ImageTracker(rig, ImageFrontEndTuning(n_min=40, n_max=40))
    t2.step(*_pair(rig, plane))
    ok = t2.step(*_pair(rig, plane.moved([0, 0, 0], [0.01, 0.0, 0.0])))
    assert ok.stats.fb_rejected == 0 and ok.stats.matched == 40


def _aged_errors(template_refine: bool, affine_match_refine: bool, n: int = 40):
    """Left pixels of the tracks alive from the first frame after ``n`` frames of a slanted
    plane turning 0.7 deg per frame (mostly about the line of sight), against the projection
    of the surface point each started on; and every right pixel against its correspondence."""
    rig = _rigs()["convergent"]
    plane = _plane()
    tu = ImageFrontEndTuning(
        n_min=60, n_max=60, max_age_frames=100, template_refine=template_refine,
        affine_match_refine=affine_match_refine,
    )  # fmt: skip
    tracker = ImageTracker(rig, tu)
    fr = tracker.step(*_pair(rig, plane))
    a, b = _material_points(rig, plane, fr.uv[0])
    ids0 = fr.ids
    for _ in range(n):
        plane = plane.moved([0.0, 0.012, 0.006], [0.004, 0.0, 0.002])
        fr = tracker.step(*_pair(rig, plane))
    alive = np.isin(fr.ids, ids0)
    uv_true, _ = project(
        rig, plane.point(*(c[np.searchsorted(ids0, fr.ids[alive])] for c in (a, b)))
    )
    _, uv_r, _ = _truth(rig, plane, fr.uv[0])
    return np.hypot(*(fr.uv[0, alive] - uv_true[0]).T), np.hypot(*(fr.uv[1] - uv_r).T)


def test_template_refinement_keeps_a_track_on_its_surface_point():
    # LK frame to frame follows the turning patch's texture and slides (0.46 px median after
    # 40 frames here); the affine warp of the first-sighting patch stays on the point (0.02)
    slid, _ = _aged_errors(False, True)
    held, _ = _aged_errors(True, True)
    assert len(held) >= 45 and len(slid) >= 45
    assert np.median(slid) > 0.3
    assert np.median(held) < 0.05 and np.percentile(held, 90) < 0.1


def test_affine_match_refinement_removes_the_slant_bias():
    # the slanted plane's NCC match is off along the epipolar line (0.10 px median); the left
    # patch warped into the right image is not (0.02)
    _, ncc = _aged_errors(True, False)
    _, affine = _aged_errors(True, True)
    assert np.median(ncc) > 0.07
    assert np.median(affine) < 0.04 and np.percentile(affine, 90) < 0.08


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_affine_refinement_finds_a_known_warp(seed):
    # the image is a texture under a known affine map M (OpenCV pixels, dst = M src): the
    # template centred on tumblenav pixel uv0 of the texture lies at M (uv0 - 0.5) + 0.5, with
    # the linear part M[:, :2]; the search starts 0.7 px off with an identity warp. The texture
    # is smooth noise, textured in every direction (a patch holding one straight edge would
    # leave its position along the edge to the aperture problem)
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (256, 256)).astype(np.float32), (0, 0), 2.0)
    tex = 128.0 + 40.0 * tex / tex.std()
    ang, sc = rng.uniform(-0.15, 0.15), rng.uniform(0.92, 1.08)
    rot_ = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    L = sc * rot_ @ np.array([[1.0, rng.uniform(-0.05, 0.05)], [0.0, 1.0]])
    M = np.hstack([L, rng.uniform(-3, 3, (2, 1))])
    img = np.clip(np.rint(cv2.warpAffine(tex, M, (256, 256), flags=cv2.INTER_CUBIC)), 0, 255)
    src = np.clip(np.rint(tex), 0, 255).astype(np.uint8)
    uv0 = np.array([[100.5, 120.5], [150.25, 90.75]])
    true = (uv0 - 0.5) @ L.T + M[:, 2] + 0.5
    res = refine_affine(
        template_at(src, uv0, 15), img.astype(np.uint8), true + [0.7, -0.5],
        np.tile(np.eye(2), (2, 1, 1)), 0.7, 2.0,
    )  # fmt: skip
    assert res.ok.all()
    assert np.abs(res.uv - true).max() < 0.06  # measured <= 0.04 over seeds 0-7
    assert np.abs(res.lin - L).max() < 0.02


def test_affine_refinement_refuses_another_patch():
    rng = np.random.default_rng(3)
    img = _render(_rigs()["parallel"], _plane(), 0)
    uv = np.array([[100.5, 100.5], [200.5, 120.5]])
    tmpl = template_at(img, uv, 15)
    same = refine_affine(tmpl, img, uv + [0.4, -0.3], np.tile(np.eye(2), (2, 1, 1)), 0.7, 2.0)
    assert same.ok.all() and np.abs(same.uv - uv).max() < 0.05
    noise = rng.uniform(0, 255, tmpl.shape).astype(np.float32)
    other = refine_affine(noise, img, uv, np.tile(np.eye(2), (2, 1, 1)), 0.7, 2.0)
    assert not other.ok.any()
    np.testing.assert_array_equal(other.uv, uv)


def _ecc_scene(seed: int):
    """A textured image (uint8, 160 x 160) with a flat square, and 15 x 15 templates cut from
    it under known affine maps (template pixel -> image pixel, OpenCV pixels) with a little
    noise: turned, scaled and sheared ones, one on the flat square, one on a faint texture and
    two whose warps reach past the image's left and top edges. Returns the image, the
    templates, the maps and the tumblenav pixels the search starts from (0.4-0.8 px off)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (160, 160)).astype(np.float32), (0, 0), 1.8)
    tex = 128.0 + 40.0 * tex / tex.std()
    tex[100:140, 100:140] = 90.0  # flat
    tex[20:60, 100:140] = 128.0 + 0.012 * (tex[20:60, 100:140] - 128.0)  # faint: +-0.5 grey
    img = np.clip(np.rint(tex), 0, 255).astype(np.uint8)
    maps = []
    for ang, sx, sy, shear in [
        (0.0, 1.0, 1.0, 0.0),
        (0.25, 1.0, 1.0, 0.0),
        (-0.2, 1.0, 1.0, 0.0),
        (0.0, 1.15, 1.15, 0.0),
        (0.0, 0.88, 0.95, 0.0),
        (0.0, 1.0, 1.0, 0.15),
        (0.1, 1.08, 0.93, -0.1),
        *[(rng.uniform(-0.2, 0.2), *rng.uniform(0.9, 1.1, 2), rng.uniform(-0.1, 0.1))] * 1,
    ]:
        rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        maps.append(rot @ np.array([[sx, shear], [0.0, sy]]))
    centres = [[40, 40], [70, 35], [45, 80], [80, 80], [35, 120], [60, 135], [85, 55], [60, 95]]
    special = [([120, 120], np.eye(2)), ([120, 40], np.eye(2))]  # flat, faint
    special += [([5.0, 70.0], maps[1]), ([75.0, 3.0], maps[5])]  # past the left, the top edge
    lins = maps + [L for _, L in special]
    centres = np.array(centres + [c for c, _ in special], float) + rng.uniform(-0.5, 0.5, (12, 2))
    c = np.array([7.0, 7.0])
    M = np.concatenate([np.array(lins), (centres - np.array(lins) @ c)[:, :, None]], axis=2)
    src = img.astype(np.float32)
    flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
    tmpl = np.stack([cv2.warpAffine(src, Mi, (15, 15), flags=flags) for Mi in M])
    tmpl = (tmpl + rng.normal(0.0, 1.0, tmpl.shape)).astype(np.float32)
    off = rng.uniform(0.4, 0.8, (12, 2)) * rng.choice([-1.0, 1.0], (12, 2))
    return img, tmpl, M, centres + off + 0.5


def _refine_affine_opencv(templates, image, uv_pred, lin, min_cc, max_shift_px):
    """refine_affine as it was with ``cv2.findTransformECC`` called per feature: the
    reference of the compiled kernel (same crop, acceptance and return values)."""
    m, side = len(uv_pred), templates.shape[-1]
    c = (side - 1) / 2.0
    reach = c * np.abs(np.asarray(lin, float)).sum(axis=-1).max(axis=-1)
    h, w = image.shape
    uv, lin_out = np.array(uv_pred, float), np.array(lin, float)
    cc, ok = np.full(m, np.nan), np.zeros(m, bool)
    cen = np.array([c, c])
    for i in range(m):
        p = uv_pred[i] - 0.5
        half = int(np.ceil(reach[i] + max_shift_px)) + 4
        x0, y0 = max(int(round(p[0])) - half, 0), max(int(round(p[1])) - half, 0)
        x1, y1 = min(int(round(p[0])) + half + 1, w), min(int(round(p[1])) + half + 1, h)
        warp = np.empty((2, 3), np.float32)
        warp[:, :2] = lin[i]
        warp[:, 2] = p - lin[i] @ cen - (x0, y0)
        crop = image[y0:y1, x0:x1].astype(np.float32)
        try:
            score, found = cv2.findTransformECC(
                templates[i], crop, warp, cv2.MOTION_AFFINE, (3, 20, 1e-3), None, 1
            )
        except cv2.error:
            continue
        q = found[:, :2].astype(float) @ cen + found[:, 2] + (x0, y0)
        cc[i] = score
        if score >= min_cc and np.hypot(*(q - p)) <= max_shift_px:
            uv[i], lin_out[i], ok[i] = q + 0.5, found[:, :2], True
    return uv, lin_out, cc, ok


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ecc_kernel_agrees_with_opencv(seed):
    # the compiled ECC (ecc_kernel.ecc_affine, through refine_affine) against OpenCV's
    # findTransformECC per feature: the same outcome for each feature, the refined centre to
    # 2e-3 px and the score to 1e-4 (float64 against float32 sums: measured <= 1.4e-4 px and
    # <= 2.7e-5 over seeds 0-7). The starts are identity warps (0.2-0.25 rad and 15 % off for
    # the turned and scaled templates) and, for a second pass, the true linear parts.
    img, tmpl, M, uv0 = _ecc_scene(seed)
    true = M[:, :, :2] @ np.array([7.0, 7.0]) + M[:, :, 2] + 0.5
    for lin in [np.tile(np.eye(2), (12, 1, 1)), M[:, :, :2]]:
        res = refine_affine(tmpl, img, uv0, lin, 0.7, 2.0)
        uv, lin_ref, cc, ok = _refine_affine_opencv(tmpl, img, uv0, lin, 0.7, 2.0)
        np.testing.assert_array_equal(np.isnan(res.cc), np.isnan(cc))
        np.testing.assert_array_equal(res.ok, ok)
        assert np.nanmax(np.abs(res.cc - cc)) < 1e-4
        assert np.abs(res.uv - uv).max() < 2e-3
        assert np.abs(res.lin - lin_ref).max() < 1e-3
        # the textured ones are found, within 0.1 px of the truth (measured <= 0.066)
        assert res.ok[:8].all() and np.abs(res.uv[:8] - true[:8]).max() < 0.1
        # the flat square fails (OpenCV: NaN correlation); the faint texture scores low
        assert np.isnan(res.cc[8]) and not res.ok[8]
        assert res.cc[9] < 0.7 and not res.ok[9]
        # the two at the edges are refined with template pixels past the image (masked; the
        # templates are 0 there, cut with warpAffine's border, so no truth to compare with)
        assert res.ok[10:].all()
        corners = np.array([[-7.0, -7.0], [-7.0, 7.0], [7.0, -7.0], [7.0, 7.0]])
        reach = res.uv[10:, None] - 0.5 + np.einsum("mij,kj->mki", res.lin[10:], corners)
        assert reach[0, :, 0].min() < -0.5 and reach[1, :, 1].min() < -0.5


def test_ecc_kernel_matches_opencv_step_by_step():
    # ecc_affine's contract: per feature, cv2.findTransformECC(templates[i], the crop boxes[i]
    # as float32, warps[i], MOTION_AFFINE, (COUNT | EPS, max_iter, eps), None, 1). With EPS
    # off, each iteration count 1..8 on crops that cut the template (masked pixels) and that
    # hold it, the warps agree to 1e-4 px (rounding: float64 here, float32 there)
    img, tmpl, M, uv0 = _ecc_scene(4)
    boxes = np.array([[0, 55, 20, 85], [25, 25, 56, 56], [60, 0, 92, 14], [20, 60, 60, 100]])
    feats = [10, 0, 11, 2]
    warps = np.array(
        [np.hstack([M[f][:, :2], (uv0[f] - 0.5 - M[f][:, :2] @ [7.0, 7.0] - b[:2])[:, None]])
         for f, b in zip(feats, boxes, strict=True)],
        np.float32,
    )  # fmt: skip
    for n_iter in range(1, 9):
        got, rho, status = ecc_affine(tmpl[feats], img, boxes, warps, n_iter, -1.0)
        for j, (f, (x0, y0, x1, y1)) in enumerate(zip(feats, boxes, strict=True)):
            crop = img[y0:y1, x0:x1].astype(np.float32)
            r, want = cv2.findTransformECC(
                tmpl[f], crop, warps[j].copy(), cv2.MOTION_AFFINE, (1, n_iter, -1.0), None, 1
            )
            assert status[j] == ECC_OK
            assert abs(rho[j] - r) < 1e-5
            np.testing.assert_allclose(got[j], want, atol=1e-4)


def _sequence(rig, n, step=([0.0, 0.01, 0.004], [0.01, 0.0, 0.005]), plane=None):
    plane = plane or _plane()
    for _ in range(n):
        yield _pair(rig, plane)
        plane = plane.moved(*step)


def test_feature_management_over_a_sequence():
    rig = _rigs()["convergent"]
    tu = ImageFrontEndTuning(n_min=50, n_max=50, max_age_frames=4)
    tracker = ImageTracker(rig, tu)
    seen: set[int] = set()
    ages: dict[int, int] = {}
    prev_ids = np.zeros(0, dtype=np.int64)
    for left, right in _sequence(rig, 12):
        fr = tracker.step(left, right)
        assert len(fr.ids) == 50  # held at n_max
        assert fr.stats.removed == 0
        assert np.isfinite(fr.uv).all() and np.isfinite(fr.p_inC).all()
        new = np.setdiff1d(fr.ids, prev_ids)
        assert len(new) == fr.stats.new
        assert not (set(new.tolist()) & seen)  # IDs never reused
        if len(prev_ids) and len(new):
            assert new.min() > max(seen)
        old = np.isin(fr.ids, prev_ids)
        # the 5 x 5 mask: no new feature inside an existing feature's square
        if old.any() and (~old).any():
            cheb = np.abs(np.floor(fr.uv[0, ~old])[:, None, :] - np.floor(fr.uv[0, old])[None]).max(
                axis=2
            )
            assert cheb.min() >= 3
        for i, a in zip(fr.ids.tolist(), fr.age.tolist(), strict=True):
            assert a == ages.get(i, 0) + 1  # survival time counts observed frames
            ages[i] = a
        seen |= set(fr.ids.tolist())
        prev_ids = fr.ids
    assert max(ages.values()) == 4  # max age enforced, and reached
    assert tracker.next_id == len(seen)


def test_tracker_keeps_its_per_feature_arrays_in_step():
    # templates and warps follow the features through tracking, refinement drops, detection
    # and Chang's removal
    rig = _rigs()["convergent"]
    tracker = ImageTracker(rig, ImageFrontEndTuning(n_min=50, n_max=50, max_age_frames=4))
    for left, right in _sequence(rig, 8):
        fr = tracker.step(left, right)
        n = len(tracker.ids)
        assert n == len(fr.ids) and tracker.templates.shape == (n, 15, 15)
        assert tracker.lin.shape == (n, 2, 2) and len(tracker.uv_l) == n


def test_removal_takes_the_most_tracked():
    ids = np.arange(6, dtype=np.int64)
    age = np.array([3, 9, 1, 9, 4, 2], dtype=np.int64)
    assert most_tracked_to_remove(ids, age, 3).tolist() == [1, 3, 4]  # ages 9, 9, 4
    assert most_tracked_to_remove(ids, age, 5).tolist() == [1]  # tie at 9: the older ID
    assert most_tracked_to_remove(ids, age, 6).size == 0
    assert most_tracked_to_remove(ids, age, 10).size == 0


@given(
    st.lists(st.integers(1, 50), min_size=0, max_size=40),
    st.integers(1, 40),
)
def test_removal_property(ages, n_max):
    age = np.array(ages, dtype=np.int64)
    ids = np.arange(len(age), dtype=np.int64)
    drop = most_tracked_to_remove(ids, age, n_max)
    assert drop.size == max(len(age) - n_max, 0)
    keep = np.setdiff1d(ids, drop)
    if drop.size and keep.size:
        assert age[drop].min() >= age[keep].max()


def test_black_frame_gives_zero_features_and_recovers():
    rig = _rigs()["parallel"]
    tracker = ImageTracker(rig, ImageFrontEndTuning(n_min=30, n_max=30))
    black = np.zeros((H, W), np.uint8)
    fr = tracker.step(black, black)  # black first frame
    assert len(fr.ids) == 0 and fr.uv.shape == (2, 0, 2)
    frames = list(_sequence(rig, 3))
    assert len(tracker.step(*frames[0]).ids) == 30
    fr = tracker.step(black, black)
    assert len(fr.ids) == 0 and fr.stats.lost + fr.stats.fb_rejected == 30
    fr = tracker.step(*frames[2])  # detection restarts
    assert len(fr.ids) == 30 and np.isfinite(fr.uv).all()
    assert fr.ids.min() == 30  # fresh IDs


def test_few_features_are_fine():
    rig = _rigs()["parallel"]
    tracker = ImageTracker(rig, ImageFrontEndTuning(n_min=2, n_max=2))
    for left, right in _sequence(rig, 3):
        fr = tracker.step(left, right)
        assert len(fr.ids) == 2 and np.isfinite(fr.uv).all()
    # a single textured blob on black: at most a handful of features, never NaN
    img = np.zeros((H, W), np.uint8)
    cv2.rectangle(img, (150, 100), (170, 120), 200, -1)
    tracker = ImageTracker(rig)
    for _ in range(2):
        fr = tracker.step(img, np.roll(img, -40, axis=1))
        assert len(fr.ids) < 3 and np.isfinite(fr.uv).all()


def test_bad_images_are_input_errors():
    tracker = ImageTracker(_rigs()["parallel"])
    ok = np.zeros((H, W), np.uint8)
    with pytest.raises(InputError):
        tracker.step(np.zeros((H, W, 3), np.uint8), ok)
    with pytest.raises(InputError):
        tracker.step(ok, np.zeros((H, W), np.float32))
    with pytest.raises(InputError):
        tracker.step(ok, np.zeros((H + 1, W), np.uint8))
    with pytest.raises(ValueError):
        ImageFrontEndTuning(n_min=10, n_max=5)
    with pytest.raises(ValueError):
        ImageFrontEndTuning(nonsense=1)


# ----------------------------------------------------------------------------- track_images


def test_track_images_gives_stereo_measurements():
    rig = _rigs()["convergent"]
    n = 6
    t = 0.1 * np.arange(n)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    calls: list[int] = []
    black = np.zeros((H, W), np.uint8)
    frames = list(_sequence(rig, n))
    frames[3] = (black, black)
    meas, stats = track_images(
        iter(frames),
        t,
        rig,
        q,
        q,
        0.5,
        ImageFrontEndTuning(n_min=40, n_max=40, max_age_frames=3),
        progress=calls.append,
    )
    assert isinstance(meas, StereoMeasurements)
    N = meas.uv.shape[2]
    assert meas.uv.shape == (n, 2, N, 2) and meas.observed.shape == (n, 2, N)
    assert np.array_equal(meas.observed[:, 0], meas.observed[:, 1])  # both cameras or none
    assert np.isfinite(meas.uv[meas.observed]).all()
    assert np.isnan(meas.uv[~meas.observed]).all()
    assert (meas.observed[:, 0].sum(axis=1) == stats.counts["features"]).all()
    assert stats.counts["features"].tolist() == [40, 40, 40, 0, 40, 40]
    assert stats.track_length.max() <= 3 and stats.track_length.sum() == 200
    assert N == stats.totals["new"] and calls == list(range(n))
    d = stats.to_dict()
    assert d["feature_ids"] == N and d["epochs"] == n
    # each feature keeps its slot: observed epochs of an ID are contiguous
    obs = meas.observed[:, 0]
    for j in range(N):
        k = np.flatnonzero(obs[:, j])
        assert k.size and np.all(np.diff(k) == 1)
    ds = meas.to_dataset("test")  # round trip through the file format
    back = StereoMeasurements.from_dataset(ds)
    assert np.array_equal(back.observed, meas.observed)
    # the front end states its tracks' slide (none: the refinement holds them) and their noise
    # after the first sighting; the file keeps both
    assert back.slide_px2_per_frame == meas.slide_px2_per_frame == 0.0
    assert back.track_noise_px == meas.track_noise_px == REFINED_TRACK_NOISE_PX
    lk, _ = track_images(
        iter(frames), t, rig, q, q, 0.5,
        ImageFrontEndTuning(n_min=40, n_max=40, max_age_frames=3, template_refine=False),
    )  # fmt: skip
    back = StereoMeasurements.from_dataset(lk.to_dataset("test"))
    assert back.slide_px2_per_frame == 0.006 and back.track_noise_px is None
    with pytest.raises(InputError):
        track_images(iter(frames[:5]), t, rig, q, q, 0.5)
    with pytest.raises(InputError):
        track_images(iter(frames), t[:5], rig, q[:5], q[:5], 0.5)
