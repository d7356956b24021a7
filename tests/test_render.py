"""Stereo image renderer (tumblenav.sensors.render) and its noise chain (sensors.image_noise).

Small images (about 100 x 80 px) keep the file fast; the geometry checks use independent
oracles: tumblenav.sensors.project for pixels, trimesh's ray caster (the depth sensor's) for
the silhouette, trimesh's closest-point query for hit points.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy.spatial.transform import Rotation

from tumblenav.errors import InputError
from tumblenav.sensors.image_noise import ImageNoise, apply_noise, defect_pattern
from tumblenav.sensors.render import RenderSettings, StereoRenderer
from tumblenav.sensors.stereo import Camera, StereoRig, convergent_rig, parallel_rig, project
from tumblenav.sensors.texture import METAL, MLI, SOLAR, face_materials, surface_textures
from tumblenav.target_model import TargetModel, procedural_satellite

RIGS = {
    "parallel": parallel_rig(110.0, 0.3, (100, 80), (51.3, 38.7)),
    "convergent": convergent_rig(110.0, 0.6, np.deg2rad(10.0), (100, 80)),
}
NO_NOISE = RenderSettings(noise=None, threads=1)


def _white_model(mesh: trimesh.Trimesh) -> TargetModel:
    """``mesh`` with a UV texture that is white everywhere (albedo 1)."""
    image = Image.new("RGB", (4, 4), (255, 255, 255))
    mesh.visual = trimesh.visual.TextureVisuals(
        uv=np.full((len(mesh.vertices), 2), 0.5), image=image
    )
    return TargetModel(mesh=mesh, rectangles=())


def _boxes(
    *specs: tuple[tuple[float, float, float], tuple[float, float, float]],
) -> trimesh.Trimesh:
    """One mesh of axis-aligned boxes given as (extents, centre)."""
    verts, faces = [], []
    for ext, centre in specs:
        b = trimesh.creation.box(extents=ext)
        faces.append(np.asarray(b.faces) + sum(len(v) for v in verts))
        verts.append(np.asarray(b.vertices) + np.asarray(centre))
    return trimesh.Trimesh(np.vstack(verts), np.vstack(faces), process=False)


def _pose(rig: StereoRig, range_m: float) -> np.ndarray:
    """A point between the two boresights at ``range_m`` (C)."""
    return np.array([0.5 * rig.baseline_m, range_m, 0.0])


# -------------------------------------------------------------------------------------------
# geometry


@pytest.mark.parametrize("kind", ["parallel", "convergent"])
def test_a_known_point_renders_at_its_projected_pixel(kind):
    """A small white cube: its image centroid (8 x 8 supersampled, uniform light) is the
    projection of its centre within 0.04 px (measured <= 0.016), with pixel centres at (i + 0.5, j + 0.5); the
    pixel holding that projection is on target, with the cube's depth and hit point."""
    rig = RIGS[kind]
    side = 0.04  # about 2 px at 2.2 m
    model = _white_model(_boxes(((side, side, side), (0.0, 0.0, 0.0))))
    R_CM = Rotation.from_euler("xyz", [20, -35, 10], degrees=True).as_matrix()
    p_MinC = _pose(rig, 2.2) + np.array([0.07, 0.1, -0.05])
    soft = RenderSettings(ambient=1.0, exposure=0.9, supersample=8, texture="mesh", noise=None)
    img = StereoRenderer(model, rig, soft).render(R_CM, p_MinC, np.array([0, -1.0, 0]), None)
    hard = StereoRenderer(model, rig, NO_NOISE).render(R_CM, p_MinC, [0, -1.0, 0], None)
    uv, in_view = project(rig, p_MinC[None, :])
    for k in (0, 1):
        assert in_view[k, 0]
        im = img.images[k].astype(float)
        jj, ii = np.mgrid[0 : im.shape[0], 0 : im.shape[1]]
        centroid = np.array([np.sum((ii + 0.5) * im), np.sum((jj + 0.5) * im)]) / im.sum()
        assert np.allclose(centroid, uv[k, 0], atol=0.04), (k, centroid, uv[k, 0])
        i, j = np.floor(uv[k, 0]).astype(int)
        assert hard.mask[k, j, i]
        cam = rig.cameras[k]
        centre_k = cam.R_CkC @ (p_MinC - cam.p_CkinC)
        assert abs(hard.depth_m[k, j, i] - centre_k[1]) < side
        assert np.all(np.abs(hard.hit_M[k, j, i]) <= side / 2 + 1e-6)
        # and the far background pixel is empty
        assert not hard.mask[k, 0, 0] and np.isnan(hard.depth_m[k, 0, 0])


def _trimesh_silhouette(model: TargetModel, cam: Camera, R_CM, p_MinC) -> np.ndarray:
    """Pixel-centre rays cast with trimesh (as sensors/depth.py does): hit mask (H, W)."""
    w, h = cam.resolution_px
    (cu, cv), f = cam.principal_point_px, cam.focal_px
    jj, ii = np.mgrid[0:h, 0:w]
    d_k = np.stack([(ii + 0.5 - cu) / f, np.ones_like(ii, float), (jj + 0.5 - cv) / f], -1)
    R_kM = cam.R_CkC @ R_CM
    d_M = d_k.reshape(-1, 3) @ R_kM  # R_kM^T d
    o_M = R_CM.T @ (cam.p_CkinC - p_MinC)
    _, idx, _ = model.mesh.ray.intersects_location(
        np.tile(o_M, (len(d_M), 1)), d_M, multiple_hits=False
    )
    hit = np.zeros(h * w, bool)
    hit[idx] = True
    return hit.reshape(h, w)


@pytest.mark.parametrize("kind", ["parallel", "convergent"])
def test_silhouette_matches_the_depth_sensors_ray_cast(kind):
    rig = RIGS[kind]
    model = procedural_satellite()
    R_CM = Rotation.from_euler("zyx", [40, 25, -30], degrees=True).as_matrix()
    p_MinC = _pose(rig, 9.0)
    out = StereoRenderer(model, rig, NO_NOISE).render(R_CM, p_MinC, [0.3, -0.8, -0.5], None)
    for k in (0, 1):
        ref = _trimesh_silhouette(model, rig.cameras[k], R_CM, p_MinC)
        mask = out.mask[k]
        assert ref.sum() > 300
        iou = np.sum(mask & ref) / np.sum(mask | ref)
        assert iou >= 0.99, iou
        assert np.all(out.images[k][~mask] == 0)  # black space


@pytest.mark.parametrize("kind", ["parallel", "convergent"])
def test_depth_is_the_camera_axis_coordinate_of_the_hit_point_on_the_mesh(kind):
    rig = RIGS[kind]
    model = procedural_satellite()
    R_CM = Rotation.from_euler("xyz", [-50, 15, 70], degrees=True).as_matrix()
    p_MinC = _pose(rig, 6.0)
    out = StereoRenderer(model, rig, NO_NOISE).render(R_CM, p_MinC, [0, -1.0, 0], None)
    rng = np.random.default_rng(3)
    for k in (0, 1):
        cam = rig.cameras[k]
        m = out.mask[k]
        assert np.array_equal(m, np.isfinite(out.depth_m[k]))
        assert np.array_equal(m, np.all(np.isfinite(out.hit_M[k]), axis=-1))
        hit = out.hit_M[k][m].astype(float)
        p_k = (hit @ R_CM.T + p_MinC - cam.p_CkinC) @ cam.R_CkC.T
        assert np.allclose(out.depth_m[k][m], p_k[:, 1], atol=2e-5)
        # the hit point projects back into its own pixel
        jj, ii = np.nonzero(m)
        u = cam.principal_point_px[0] + cam.focal_px * p_k[:, 0] / p_k[:, 1]
        v = cam.principal_point_px[1] + cam.focal_px * p_k[:, 2] / p_k[:, 1]
        assert np.allclose(u, ii + 0.5, atol=1e-3) and np.allclose(v, jj + 0.5, atol=1e-3)
        # on the surface: distance to the closest triangle (a sample, brute force)
        pick = rng.choice(len(hit), size=min(150, len(hit)), replace=False)
        tri = model.mesh.triangles
        pts = np.repeat(hit[pick], len(tri), axis=0)
        closest = trimesh.triangles.closest_point(np.tile(tri, (len(pick), 1, 1)), pts)
        dist = np.linalg.norm(closest - pts, axis=1).reshape(len(pick), len(tri)).min(axis=1)
        assert dist.max() < 1e-5


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1),
    range_m=st.floats(4.0, 30.0),
)
def test_truth_maps_are_consistent_for_any_pose(q, range_m):
    """For any attitude and range: mask <=> finite depth <=> finite hit; depth > 0; images
    are black off target."""
    rig = RIGS["convergent"]
    R_CM = Rotation.from_quat(q).as_matrix()
    out = _SAT_RENDERER.render(R_CM, _pose(rig, range_m), [0.2, -0.9, 0.3], None)
    for k in (0, 1):
        m = out.mask[k]
        assert np.array_equal(m, np.isfinite(out.depth_m[k]))
        assert np.array_equal(m, np.all(np.isfinite(out.hit_M[k]), axis=-1))
        assert np.all(out.depth_m[k][m] > 0)
        assert np.all(out.images[k][~m] == 0)


_SAT_RENDERER = StereoRenderer(procedural_satellite(), RIGS["convergent"], NO_NOISE)


def test_cameras_of_different_sizes_give_tuples_and_truth_false_skips_maps():
    left = Camera(90.0, (40.0, 30.0), (80, 60))
    right = Camera(120.0, (50.0, 45.0), (100, 90), np.eye(3), np.array([0.4, 0.0, 0.0]))
    rig = StereoRig(left, right)
    r = StereoRenderer(procedural_satellite(), rig, NO_NOISE)
    out = r.render(np.eye(3), [0.2, 8.0, 0.0], [0, -1.0, 0], None)
    assert isinstance(out.images, tuple)
    assert out.images[0].shape == (60, 80) and out.images[1].shape == (90, 100)
    assert out.depth_m[1].shape == (90, 100) and out.hit_M[1].shape == (90, 100, 3)
    lean = r.render(np.eye(3), [0.2, 8.0, 0.0], [0, -1.0, 0], None, truth=False)
    assert lean.depth_m is None and lean.hit_M is None and lean.mask is None
    assert np.array_equal(lean.images[0], out.images[0])


# -------------------------------------------------------------------------------------------
# light


def _plate_scene():
    """A 2 x 2 m white plate facing the camera at 3 m and a 0.3 m cube between it and a sun
    at 45 deg (x+, towards the camera): the cube's shadow falls around (-0.5, 3, 0)."""
    sun = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    blocker = np.array([-0.5, 2.95, 0.0]) + 0.9 * sun
    mesh = _boxes(((2.0, 0.1, 2.0), (0.0, 3.05, 0.0)), ((0.3, 0.3, 0.3), tuple(blocker)))
    return _white_model(mesh), sun


def _pixel(rig: StereoRig, p_C) -> tuple[int, int]:
    uv, ok = project(rig, np.asarray(p_C, float)[None, :])
    assert ok[0, 0]
    i, j = np.floor(uv[0, 0]).astype(int)
    return j, i


def test_lit_shadowed_and_averted_faces_read_the_lambert_ambient_levels():
    rig = parallel_rig(120.0, 0.3, (120, 120))
    model, sun = _plate_scene()
    s = RenderSettings(exposure=0.8, ambient=0.05, texture="mesh", noise=None)
    r = StereoRenderer(model, rig, s)
    assert r.texture_source == "mesh"
    out = r.render(np.eye(3), np.zeros(3), sun, None)
    left = out.images[0].astype(int)
    lit = 255 * 0.8 * (0.05 + 0.95 * np.cos(np.pi / 4))
    dark = 255 * 0.8 * 0.05
    shadow_px = _pixel(rig, [-0.5, 3.0, 0.0])
    lit_px = _pixel(rig, [-0.5, 3.0, 0.7])
    assert abs(left[shadow_px] - dark) <= 1
    assert abs(left[lit_px] - lit) <= 1
    # the sun behind the plate: its visible face gets the ambient term only
    back = r.render(np.eye(3), np.zeros(3), [0.0, 1.0, 0.0], None).images[0].astype(int)
    assert abs(back[lit_px] - dark) <= 1 and abs(back[shadow_px] - dark) <= 1
    # eclipse: a dark frame, noise only
    noisy = StereoRenderer(model, rig, RenderSettings(noise=ImageNoise(read_noise_e=30.0)))
    ecl = noisy.render(np.eye(3), np.zeros(3), None, np.random.default_rng(0))
    assert ecl.images.mean() < 2.0 and ecl.mask.sum() > 1000


def test_procedural_target_has_texture_and_corners():
    """The procedural satellite at 5 m: textured (spread of grey levels), FAST finds corners."""
    import cv2

    rig = convergent_rig(300.0, 0.92, np.deg2rad(10.0), (256, 256))
    r = StereoRenderer(procedural_satellite(), rig, RenderSettings(threads=1))
    R_CM = Rotation.from_euler("xyz", [-60, 10, 25], degrees=True).as_matrix()
    out = r.render(R_CM, [0.46, 5.0, 0.0], [0.5, -0.6, -0.6], np.random.default_rng(0))
    for k in (0, 1):
        on = out.images[k][out.mask[k]]
        assert np.std(on.astype(float)) > 10
        assert len(cv2.FastFeatureDetector_create(20).detect(out.images[k])) > 50


def test_face_materials_of_the_procedural_satellite():
    sat = procedural_satellite()
    mat, labels = face_materials(sat.mesh)
    centres = sat.mesh.triangles_center
    bus = np.all(np.abs(centres) <= np.array([0.45, 0.6, 0.75]) + 1e-9, axis=1)
    panel = np.abs(centres[:, 0]) > 0.5
    assert np.all(mat[panel] == SOLAR)
    assert np.all(mat[bus & (labels == labels[0])] == MLI)
    assert set(np.unique(mat)) == {MLI, SOLAR, METAL}  # ring and nozzle are metal
    with pytest.warns(UserWarning, match="no UV texture"):
        assert surface_textures(sat.mesh, "mesh").source == "procedural"


def test_a_users_obj_with_its_own_texture_is_rendered_with_it(tmp_path):
    """A 1 x 1 m plate at 3 m, facing the camera, with an image whose top half is white and
    bottom half black, exported as OBJ + MTL + PNG and read back through load_mesh: the
    plate's upper half renders bright, its lower half dark (UV v up = image up)."""
    from tumblenav.target_model import load_mesh

    verts = np.array([[-0.5, 0, 0.5], [0.5, 0, 0.5], [0.5, 0, -0.5], [-0.5, 0, -0.5]], float)
    plate = trimesh.Trimesh(verts, [[0, 1, 2], [0, 2, 3]], process=False)
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[:32] = 255  # top rows of the image
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # z = -0.5 (up) at v = 1
    plate.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(tex))
    plate.export(tmp_path / "plate.obj")
    model = load_mesh(tmp_path / "plate.obj")
    rig = parallel_rig(100.0, 0.3, (100, 100))
    s = RenderSettings(texture="mesh", noise=None, ambient=1.0, exposure=1.0)
    r = StereoRenderer(model, rig, s)
    assert r.texture_source == "mesh"
    img = r.render(np.eye(3), [0.0, 3.0, 0.0], [0, -1.0, 0], None).images[0]
    upper = img[_pixel(rig, [0.0, 3.0, -0.3])]
    lower = img[_pixel(rig, [0.0, 3.0, 0.3])]
    assert upper > 240 and lower < 15
    assert StereoRenderer(model, rig, NO_NOISE).texture_source == "procedural"


def test_supersampling_softens_edges_but_keeps_the_silhouette_truth():
    rig = RIGS["parallel"]
    model = _white_model(_boxes(((0.5, 0.5, 0.5), (0.0, 0.0, 0.0))))
    args = (Rotation.from_euler("z", 20, degrees=True).as_matrix(), _pose(rig, 3.0), [0, -1.0, 0])
    base = RenderSettings(texture="mesh", noise=None, ambient=1.0, exposure=1.0)
    one = StereoRenderer(model, rig, base).render(*args, None)
    four = StereoRenderer(model, rig, RenderSettings(**{**base.__dict__, "supersample": 4}))
    ss = four.render(*args, None)
    assert np.array_equal(one.mask, ss.mask)
    assert set(np.unique(one.images)) <= {0, 255}
    mid = (ss.images > 20) & (ss.images < 235)
    assert mid.sum() > 20  # edge pixels are partly covered
    assert abs(float(ss.images.mean()) - float(one.images.mean())) < 2.0


# -------------------------------------------------------------------------------------------
# noise and determinism


def test_same_seed_same_pixels_different_seed_different_noise_off_uses_no_rng():
    rig = RIGS["convergent"]
    model = procedural_satellite()
    pose = (np.eye(3), _pose(rig, 8.0), [0.3, -0.9, 0.1])
    noisy = StereoRenderer(model, rig, RenderSettings(noise=ImageNoise(read_noise_e=40.0)))
    a = noisy.render(*pose, np.random.default_rng(7))
    b = noisy.render(*pose, np.random.default_rng(7))
    c = noisy.render(*pose, np.random.default_rng(8))
    assert np.array_equal(a.images, b.images)
    assert not np.array_equal(a.images, c.images)
    # left and right noise independent: their difference from the clean image is uncorrelated
    clean = StereoRenderer(model, rig, NO_NOISE).render(*pose, None)
    n0 = a.images[0].astype(float) - clean.images[0]
    n1 = a.images[1].astype(float) - clean.images[1]
    assert abs(np.corrcoef(n0.ravel(), n1.ravel())[0, 1]) < 0.05
    # noise off: deterministic and the generator is not touched
    quiet = StereoRenderer(model, rig, RenderSettings(noise=ImageNoise(shot=False)))
    rng = np.random.default_rng(1)
    state = rng.bit_generator.state
    q1 = quiet.render(*pose, rng)
    assert rng.bit_generator.state == state
    assert np.array_equal(q1.images, quiet.render(*pose, None).images)
    assert np.array_equal(q1.images, clean.images)
    # a pickled renderer (sent to a worker process) renders the same pixels
    import pickle

    again = pickle.loads(pickle.dumps(noisy))
    assert np.array_equal(again.render(*pose, np.random.default_rng(7)).images, a.images)
    # threads do not change the pixels
    seq = StereoRenderer(model, rig, RenderSettings(noise=ImageNoise(read_noise_e=40.0), threads=1))
    assert np.array_equal(seq.render(*pose, np.random.default_rng(7)).images, a.images)


@pytest.mark.parametrize("level_e", [10.0, 8000.0])  # exact Poisson / its Gaussian limit
def test_shot_noise_variance_is_the_signal_in_electrons(level_e):
    full = 255.0 if level_e < 50 else 20000.0
    noise = ImageNoise(full_well_e=full)
    flat = np.full((200, 200), level_e / full, np.float32)
    dn = apply_noise(flat, noise, np.random.default_rng(2)).astype(float)
    e = dn * full / 255.0
    quant = (full / 255.0) ** 2 / 12.0 if level_e >= 50 else 0.0  # integer e- = DN below
    assert e.mean() == pytest.approx(level_e, rel=0.01)
    assert e.var() == pytest.approx(level_e + quant, rel=0.04)


def test_read_and_dark_noise_levels():
    noise = ImageNoise(full_well_e=255.0, shot=False, read_noise_e=3.0, dark_current_e=40.0)
    dn = apply_noise(np.zeros((200, 200), np.float32), noise, np.random.default_rng(5))
    e = dn.astype(float)  # 1 DN = 1 e- here
    assert e.mean() == pytest.approx(40.0, abs=0.1)
    # var = 40 (dark, Poisson) + 9 (read) + 1/12 (rounding); no clipping 5 sigma above 0
    assert e.var() == pytest.approx(49.08, rel=0.04)


def test_dead_pixels_stay_dark_hot_pixels_saturate_and_the_pattern_is_fixed():
    noise = ImageNoise(dead_pixel_fraction=0.01, hot_pixel_fraction=0.005, read_noise_e=50.0)
    shape = (100, 120)
    pat = defect_pattern(noise, shape, 0)
    assert len(pat.dead) == 120 and len(pat.hot) == 60
    assert not set(pat.dead) & set(pat.hot)
    assert np.array_equal(pat.dead, defect_pattern(noise, shape, 0).dead)
    assert not np.array_equal(pat.dead, defect_pattern(noise, shape, 1).dead)
    bright = apply_noise(np.full(shape, 0.9, np.float32), noise, np.random.default_rng(1), pat)
    dark = apply_noise(np.zeros(shape, np.float32), noise, np.random.default_rng(2), pat)
    assert np.all(bright.ravel()[pat.dead] == 0) and np.all(dark.ravel()[pat.hot] == 255)
    others = np.setdiff1d(np.arange(bright.size), np.concatenate([pat.dead, pat.hot]))
    assert np.all(bright.ravel()[others] > 200) and np.all(dark.ravel()[others] < 10)
    # through the renderer: the same pixels in every frame, whatever the generator
    rig = RIGS["parallel"]
    r = StereoRenderer(procedural_satellite(), rig, RenderSettings(noise=noise))
    f1 = r.render(np.eye(3), _pose(rig, 8.0), [0, -1.0, 0], np.random.default_rng(1))
    f2 = r.render(np.eye(3), _pose(rig, 8.0), [0, -1.0, 0], np.random.default_rng(9))
    hot = np.flatnonzero(f1.images[0] == 255)
    assert len(hot) >= 80 * 100 * 0.005 and np.all(f2.images[0].ravel()[hot] == 255)


def test_blur_conserves_the_mean():
    rng = np.random.default_rng(4)
    img = rng.uniform(0.0, 0.9, (120, 90)).astype(np.float32)
    img[40:60, 30:50] = 0.95
    sharp = apply_noise(img, ImageNoise(shot=False), None).astype(float)
    soft = apply_noise(img, ImageNoise(shot=False, blur_sigma_px=1.5), None).astype(float)
    assert soft.mean() == pytest.approx(sharp.mean(), abs=0.3)
    assert soft.std() < 0.5 * sharp.std()  # and it does blur


def test_bad_input_is_an_input_error():
    rig = RIGS["parallel"]
    r = StereoRenderer(procedural_satellite(), rig, NO_NOISE)
    with pytest.raises(InputError):
        r.render(np.ones((3, 3)), [0, 5, 0], [0, -1, 0], None)
    with pytest.raises(InputError):
        r.render(np.eye(3), [0, np.nan, 0], [0, -1, 0], None)
    with pytest.raises(InputError):
        r.render(np.eye(3), [0, 5, 0], [0, 0, 0], None)
    with pytest.raises(InputError):
        StereoRenderer(procedural_satellite(), rig, RenderSettings()).render(
            np.eye(3), [0, 5, 0], [0, -1, 0], None
        )
    for bad in ({"supersample": 0}, {"texture": "png"}, {"ambient": 2.0}, {"threads": 3}):
        with pytest.raises(InputError):
            RenderSettings(**bad)
    with pytest.raises(InputError):
        ImageNoise(dead_pixel_fraction=-0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        StereoRenderer(procedural_satellite(), rig, NO_NOISE)  # no warning by default


# -------------------------------------------------------------------------------------------
# speed paths: the same pixels and statistics as the plain computation


@pytest.mark.parametrize("supersample", [1, 2])
def test_rays_only_where_triangles_project_give_the_pixels_and_truth_of_the_whole_roi(
    supersample, monkeypatch
):
    """The renderer casts only the ROI pixels that a projected triangle (grown by 1/2 px) can
    cover; with the margin so large that every ROI pixel is cast, images and truth maps are
    bit-identical, and the culling does skip most of the ROI for a tumbling satellite."""
    from tumblenav.sensors import render

    rig = convergent_rig(500.0, 0.6, np.deg2rad(10.0), (320, 300))
    r = StereoRenderer(
        procedural_satellite(), rig, RenderSettings(noise=None, supersample=supersample)
    )
    poses = [
        (Rotation.from_quat(q).as_matrix(), np.array([0.3, rng_m, 0.1]))
        for q, rng_m in zip(
            Rotation.random(4, random_state=11).as_quat(), (1.5, 3.0, 6.0, 12.0), strict=True
        )
    ]
    sun = [0.3, -0.8, 0.5]
    culled = [r.render(R, p, sun, None) for R, p in poses]
    cam = rig.cameras[0]
    R_kM = cam.R_CkC @ poses[2][0]
    p_k = cam.R_CkC @ (poses[2][1] - cam.p_CkinC)
    roi = r._roi(cam, R_kM, p_k)
    cast = r._covered(cam, R_kM, p_k, roi)[0].size
    assert cast < 0.7 * (roi[1] - roi[0]) * (roi[3] - roi[2])
    monkeypatch.setattr(render, "_COVER_MARGIN_PX", 1e6)
    assert r._covered(cam, R_kM, p_k, roi)[0].size == (roi[1] - roi[0]) * (roi[3] - roi[2])
    for (R, p), a in zip(poses, culled, strict=True):
        b = r.render(R, p, sun, None)
        assert a.mask.sum() > 500
        assert np.array_equal(a.images, b.images)
        assert np.array_equal(a.mask, b.mask)
        assert np.array_equal(a.depth_m, b.depth_m, equal_nan=True)
        assert np.array_equal(a.hit_M, b.hit_M, equal_nan=True)


_NOISES = [
    ImageNoise(read_noise_e=10.0, dark_current_e=5.0),  # chang2021_close: Poisson dark + read
    ImageNoise(full_well_e=255.0, shot=False, read_noise_e=3.0, dark_current_e=40.0),
    ImageNoise(full_well_e=2000.0, dark_current_e=60.0),  # dark in the Gaussian limit, no read
    ImageNoise(full_well_e=500.0, dark_current_e=7.0),  # exact Poisson, no read: discrete DN
    ImageNoise(full_well_e=255.0, read_noise_e=0.7),  # read noise only
]


@pytest.mark.parametrize("noise", _NOISES)
def test_background_pmf_is_the_per_pixel_chains_distribution(noise):
    """A pixel without signal: its DN probabilities (background_pmf) against 2e6 draws of the
    per-pixel chain (Poisson dark, exact below 50 e- with shot noise on, Gaussian limit
    above; + read noise; quantised and clipped): every DN within 5 sigma of its binomial
    count, and a dark 1024 x 256 frame from apply_noise has the pmf's mean and spread."""
    from tumblenav.sensors.image_noise import background_pmf

    pmf = background_pmf(noise)
    assert pmf.shape == (256,) and pmf.sum() == pytest.approx(1.0) and np.all(pmf >= 0)
    rng = np.random.default_rng(42)
    n = 2_000_000
    lam = noise.dark_current_e
    if noise.shot and lam >= 50.0:
        e = (lam + np.sqrt(lam) * rng.standard_normal(n)).astype(np.float32)
    else:
        e = rng.poisson(lam, n).astype(np.float32)
    e = e + np.float32(noise.read_noise_e) * rng.standard_normal(n, dtype=np.float32)
    dn = np.clip(np.rint(e * np.float32(255.0 / noise.full_well_e)), 0, 255).astype(int)
    count = np.bincount(dn, minlength=256)
    sigma = np.sqrt(n * pmf * (1 - pmf))
    assert np.all(np.abs(count - n * pmf) <= 5.0 * sigma + 2.0)
    frame = apply_noise(np.zeros((256, 1024), np.float32), noise, rng).astype(float)
    mean = float(np.arange(256) @ pmf)
    sd = float(np.sqrt((np.arange(256) - mean) ** 2 @ pmf))
    assert abs(frame.mean() - mean) <= 5.0 * sd / 512.0 + 1e-9
    if sd > 0.1:
        assert frame.std() == pytest.approx(sd, rel=0.02)


def test_dark_pixels_draw_only_their_rare_non_zero_outcomes_independently():
    """chang2021_close's noise: a dark pixel reads 1 DN with probability ~4.3e-4 (39 e-
    above a 5 e- dark level with 10 e- read noise).  Over 8 dark 1024^2 frames the count of
    1-DN pixels is the binomial one (5 sigma), their positions change from frame to frame,
    and a lit square keeps the shot + read variance."""
    from tumblenav.sensors.image_noise import background_pmf

    noise = ImageNoise(read_noise_e=10.0, dark_current_e=5.0)
    p1 = background_pmf(noise)[1]
    assert 3e-4 < p1 < 6e-4 and background_pmf(noise)[2:].sum() < 1e-20
    rng = np.random.default_rng(3)
    s = np.zeros((1024, 1024), np.float32)
    s[400:600, 300:700] = 0.5  # 10000 e-
    frames = [apply_noise(s, noise, rng) for _ in range(8)]
    dark = np.ones(s.shape, bool)
    dark[400:600, 300:700] = False
    ones = np.array([f[dark] for f in frames])
    n = dark.sum() * 8
    assert abs((ones == 1).sum() - n * p1) <= 5.0 * np.sqrt(n * p1) and ones.max() == 1
    assert not np.array_equal(frames[0][dark] == 1, frames[1][dark] == 1)
    lit = np.array([f[~dark] for f in frames]).astype(float) * 20000.0 / 255.0
    assert lit.mean() == pytest.approx(10005.0, rel=2e-3)
    assert lit.var() == pytest.approx(10005.0 + 100.0 + (20000.0 / 255.0) ** 2 / 12.0, rel=0.03)


def test_noise_on_the_signal_box_only_equals_the_whole_frame_computation():
    """``support`` (a box outside which the signal is zero) and the blur computed on that box
    grown by its kernel give the pixels of the whole-frame computation, near an image edge
    too."""
    import cv2

    from tumblenav.sensors.image_noise import _blur

    s = np.zeros((120, 160), np.float32)
    s[2:30, 100:158] = np.random.default_rng(1).uniform(0.1, 0.9, (28, 58))
    noise = ImageNoise(read_noise_e=20.0, dark_current_e=3.0)
    a = apply_noise(s, noise, np.random.default_rng(5))
    b = apply_noise(s, noise, np.random.default_rng(5), support=(0, 60, 90, 160))
    assert np.array_equal(a, b)
    for sigma in (0.8, 2.3):
        full = cv2.GaussianBlur(s, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        win, box = _blur(s, sigma, (2, 30, 100, 158))
        assert np.allclose(win, full, rtol=0, atol=1e-7)
        outside = np.ones(s.shape, bool)
        outside[box[0] : box[1], box[2] : box[3]] = False
        assert np.all(full[outside] == 0)
