"""Sensor models: stereo projection and noise, visibility masks, rig pointing."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tumblenav.sensors import (
    Camera,
    angular_noise_to_px,
    chang2021_rig,
    convergent_rig,
    disparity,
    fixed_R_LC,
    loss_from_mask,
    measure,
    parallel_rig,
    project,
    scheduled_mask,
    self_occlusion_mask,
    target_pointing_R_LC,
)

F, B = 1000.0, 0.5
RES = (1000, 800)
PP = (500.0, 400.0)


@pytest.fixture
def rig():
    return parallel_rig(F, B, RES, PP)


# --------------------------------------------------------------------------- stereo geometry


def test_parallel_projection_by_hand(rig):
    p = np.array([[1.0, 10.0, -2.0], [0.0, 4.0, 0.5]])
    uv, ok = project(rig, p)
    assert uv.shape == (2, 2, 2) and ok.shape == (2, 2)
    # left camera at the origin: u = cu + f x/y, v = cv + f z/y
    assert np.allclose(uv[0, 0], [500.0 + 1000.0 * 1.0 / 10.0, 400.0 - 1000.0 * 2.0 / 10.0])
    assert np.allclose(uv[0, 1], [500.0, 400.0 + 1000.0 * 0.5 / 4.0])
    # right camera at [b, 0, 0]
    assert np.allclose(uv[1, 0], [500.0 + 1000.0 * 0.5 / 10.0, 200.0])
    assert np.allclose(uv[1, 1], [500.0 - 1000.0 * 0.5 / 4.0, 525.0])
    # Hu 2024 eq. 1 (corrected: depth along y): u_l - u_r = f b / y
    assert np.allclose(disparity(uv), F * B / p[:, 1])
    assert ok.all()


def test_defaults_and_baseline():
    r = parallel_rig(F, 0.3, (640, 480))
    assert r.left.principal_point_px == (320.0, 240.0)
    assert r.baseline_m == pytest.approx(0.3)
    assert r.kind == "parallel"
    assert np.allclose(r.centres_inC, [[0, 0, 0], [0.3, 0, 0]])
    h, v = r.left.fov_rad
    assert h == pytest.approx(2 * np.arctan(320 / F))
    assert v == pytest.approx(2 * np.arctan(240 / F))
    with pytest.raises(ValueError):
        Camera(F, PP, RES, np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError):
        parallel_rig(F, -1.0, RES)


def test_behind_and_out_of_image_not_in_view(rig):
    p = np.array(
        [
            [0.0, -5.0, 0.0],  # behind both cameras
            [0.0, 0.0, 1.0],  # in the plane y = 0
            [100.0, 10.0, 0.0],  # far right of both images
            [0.0, 10.0, 5.0],  # above both images (v > height)
            [-4.8, 10.0, 0.0],  # left image only: u_l = 20, u_r = -30
            [0.25, 10.0, 0.0],  # centred between the cameras: seen by both
        ]
    )
    uv, ok = project(rig, p)
    assert np.all(np.isnan(uv[:, :2]))
    assert ok[:, :4].sum() == 0
    assert np.allclose(uv[:, 4, 0], [20.0, -30.0])
    assert ok[:, 4].tolist() == [True, False]
    assert ok[:, 5].tolist() == [True, True]


def test_vectorised_over_time(rig):
    rng = np.random.default_rng(1)
    p = rng.uniform([-1, 5, -1], [1, 20, 1], size=(7, 5, 3))
    uv, ok = project(rig, p)
    assert uv.shape == (7, 2, 5, 2) and ok.shape == (7, 2, 5)
    uv3, _ = project(rig, p[3])
    assert np.allclose(uv[3], uv3)


def test_convergent_rig_axes_intersect():
    b, a = 0.92, np.deg2rad(10.0)
    r = convergent_rig(F, b, a, RES, PP)
    assert r.kind == "convergent"
    assert np.allclose(r.left.boresight_inC, [np.sin(a), np.cos(a), 0.0])
    assert np.allclose(r.right.boresight_inC, [-np.sin(a), np.cos(a), 0.0])
    for cam in r.cameras:
        R = cam.R_CkC
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(R[2], [0, 0, 1])  # turned about the rig z axis only
    # The optical axes cross at y = (b/2)/tan(toe_in), which images at both principal points.
    y_x = 0.5 * b / np.tan(a)
    c_l, c_r = r.centres_inC
    t_l, t_r = y_x / np.cos(a), y_x / np.cos(a)
    assert np.allclose(c_l + t_l * r.left.boresight_inC, [b / 2, y_x, 0.0])
    assert np.allclose(c_r + t_r * r.right.boresight_inC, [b / 2, y_x, 0.0])
    uv, ok = project(r, np.array([[b / 2, y_x, 0.0]]))
    assert np.allclose(uv[:, 0], [PP, PP]) and ok.all()
    # A point on the rig's y axis beyond the crossing is seen left of centre in the left image.
    uv, _ = project(r, np.array([[0.0, 2 * y_x, 0.0]]))
    assert uv[0, 0, 0] < PP[0]
    # Zero toe-in is the parallel rig.
    r0 = convergent_rig(F, b, 0.0, RES, PP)
    p = np.array([[0.3, 6.0, -0.2]])
    assert np.allclose(project(r0, p)[0], project(parallel_rig(F, b, RES, PP), p)[0])


def _chang_eq31_corrected(uv, f, b, a, pp):
    """Chang 2021 eq. 31 with the sign of sin(alpha) corrected (see stereo module notes)."""
    ul, vl, ur = uv[0, :, 0], uv[0, :, 1], uv[1, :, 0]
    T = np.tan(2 * a + np.arctan((pp[0] - ur) / f) - np.pi / 2)
    Z = f * b * (T * np.cos(a) - np.sin(a)) / (T * (ul - pp[0]) - f)
    return np.stack([Z * (ul - pp[0]) / f, Z, Z * (vl - pp[1]) / f], axis=-1)


def test_chang2021_rig_and_eq31():
    r = chang2021_rig()
    a = np.deg2rad(10.0)
    assert r.baseline_m == pytest.approx(0.92)
    # 35 deg field of view with f = 2029.8 px needs a 1280 px image, not 1024 px.
    assert np.rad2deg(r.left.fov_rad[0]) == pytest.approx(35.0, abs=0.01)
    assert r.left.resolution_px == (1280, 1280)
    rng = np.random.default_rng(3)
    p = np.column_stack(
        [rng.uniform(0.0, 0.9, 20), rng.uniform(3, 10, 20), rng.uniform(-0.4, 0.4, 20)]
    )
    uv, ok = project(r, p)
    assert ok.all()
    # Triangulated point in the left camera frame C0 (x right, y = left optical axis).
    p_C0 = _chang_eq31_corrected(uv, 2029.8, 0.92, a, (640.0, 640.0))
    assert np.allclose(p_C0 @ r.left.R_CkC, p, atol=1e-9)  # back into C


@st.composite
def points_in_front(draw):
    n = draw(st.integers(1, 6))
    y = draw(arrays(np.float64, n, elements=st.floats(0.5, 50.0)))
    xz = draw(arrays(np.float64, (n, 2), elements=st.floats(-1.0, 1.0)))
    return np.column_stack([xz[:, 0] * y, y, xz[:, 1] * y])


@given(points_in_front())
def test_parallel_depth_recovery_roundtrip(p):
    rig = parallel_rig(F, B, RES, PP)
    uv, _ = project(rig, p)
    cu, cv = PP
    y = F * B / disparity(uv)  # Hu 2024 eq. 1, corrected
    x = y * (uv[0, :, 0] - cu) / F
    z = y * (uv[0, :, 1] - cv) / F
    assert np.allclose(np.column_stack([x, y, z]), p, rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------------- measurements


def test_noise_statistics(rig):
    rng = np.random.default_rng(12345)
    p = np.tile([[0.1, 8.0, 0.05], [-0.2, 12.0, -0.1]], (20000, 1, 1))  # (20000, 2, 3)
    truth, _ = project(rig, p)
    m = measure(rig, p, rng, noise_px=0.7)
    err = m.uv - truth
    assert m.observed.all() and m.noise_px == 0.7
    assert np.std(err) == pytest.approx(0.7, rel=0.03)
    for axis in range(2):  # u and v separately, and per camera
        for cam in range(2):
            assert np.std(err[:, cam, :, axis]) == pytest.approx(0.7, rel=0.03)
    assert abs(np.mean(err)) < 0.01
    # i.i.d.: left and right noise uncorrelated
    assert abs(np.corrcoef(err[:, 0, 0, 0], err[:, 1, 0, 0])[0, 1]) < 0.03
    # seeded: reproducible
    m2 = measure(rig, p[:5], np.random.default_rng(7), 0.7)
    m3 = measure(rig, p[:5], np.random.default_rng(7), 0.7)
    assert np.array_equal(m2.uv, m3.uv)


def test_unobserved_are_nan_not_dropped(rig):
    rng = np.random.default_rng(0)
    p = np.array(
        [
            [[0.25, 10.0, 0.0], [0.0, -3.0, 0.0], [-4.8, 10.0, 0.0]],
            [[0.25, 10.0, 0.0], [0.1, 6.0, 0.0], [0.0, 9.0, 0.1]],
        ]
    )  # (2 epochs, 3 features, 3)
    visible = np.ones((2, 2, 3), dtype=bool)
    visible[1, 1, 2] = False  # occluded from the right camera only
    m = measure(rig, p, rng, 0.5, visible=visible)
    assert m.uv.shape == (2, 2, 3, 2) and m.observed.shape == (2, 2, 3)
    expected = np.array([[[1, 0, 1], [1, 0, 0]], [[1, 1, 1], [1, 1, 0]]], dtype=bool)
    assert np.array_equal(m.observed, expected)
    assert np.all(np.isnan(m.uv[~m.observed]))
    assert np.all(np.isfinite(m.uv[m.observed]))
    assert np.array_equal(m.stereo_observed, [[True, False, False], [True, True, False]])
    assert np.isnan(disparity(m.uv)[0, 2])
    # an epoch mask (n,) must be expanded explicitly to (n, 1, 1)
    epoch = np.array([True, False])
    m = measure(rig, p, rng, 0.5, visible=epoch[:, None, None])
    assert not m.observed[1].any() and np.all(np.isnan(m.uv[1]))
    with pytest.raises(ValueError):
        measure(rig, p, rng, 0.5, visible=epoch)


def test_angular_noise_to_px():
    assert angular_noise_to_px(1e-4, 2029.8) == pytest.approx(0.20298)
    assert np.allclose(angular_noise_to_px([1e-4, 2e-4], 1000.0), [0.1, 0.2])


# --------------------------------------------------------------------------- occlusion


def test_scheduled_mask():
    t = np.arange(0.0, 100.0, 0.1)
    vis = scheduled_mask(t, [(30.0, 50.0)])  # Hu 2024 Sec. 5: 20 s of complete loss
    assert vis.shape == t.shape
    assert np.sum(~vis) * 0.1 == pytest.approx(20.0)
    assert vis[t < 30.0 - 1e-9].all() and not vis[(t >= 30.0) & (t < 50.0 - 1e-9)].any()
    assert vis[t >= 50.0 - 1e-9].all()
    two = scheduled_mask(t, [(10.0, 20.0), (15.0, 25.0), (90.0, 200.0)])
    assert np.sum(~two) == pytest.approx(150 + 100, abs=1)  # overlapping windows merge
    assert scheduled_mask(t, []).all()
    with pytest.raises(ValueError):
        scheduled_mask(t, [(5.0, 1.0)])


def test_loss_from_mask():
    t = np.linspace(0.0, 3000.0, 3001)
    vis = loss_from_mask(t, 1500.0)  # Kabir 2025: occluded from 1500 s on
    assert vis[:1500].all() and not vis[1500:].any()
    assert loss_from_mask(t, None).all()


def test_self_occlusion_mask():
    centres = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    p = np.array([[0.5, 5.0, 0.0], [0.5, 5.0, 0.0], [0.5, 5.0, 0.0], [0.5, 5.0, 0.0]])
    n = np.array(
        [
            [0.0, -1.0, 0.0],  # faces the rig: seen by both
            [0.0, 1.0, 0.0],  # faces away: hidden from both
            [-1.0, 0.0, 0.0],  # faces -x: only the left camera (at x = 0 < 0.5) sees it
            [0.0, 0.0, 2.0],  # edge-on (dot = 0): hidden
        ]
    )
    m = self_occlusion_mask(p, n, centres)
    assert m.shape == (2, 4)
    assert m.tolist() == [[True, False, True, False], [True, False, False, False]]
    # vectorised over time, consistent with the per-epoch call
    pt = np.stack([p, p + [0.0, 1.0, 0.0]])
    nt = np.stack([n, -n])
    mt = self_occlusion_mask(pt, nt, centres)
    assert mt.shape == (2, 2, 4)
    assert np.array_equal(mt[0], m)
    assert mt[1].tolist() == [[False, True, False, False], [False, True, True, False]]


# --------------------------------------------------------------------------- pointing


def _check_rotation(R):
    eye = np.broadcast_to(np.eye(3), R.shape)
    assert np.allclose(np.swapaxes(R, -1, -2) @ R, eye, atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)


vec3 = arrays(np.float64, 3, elements=st.floats(-100.0, 100.0)).filter(
    lambda v: np.linalg.norm(v) > 1e-3
)


@given(vec3)
def test_target_pointing_boresight_hits_target(r):
    R_LC = target_pointing_R_LC(r)
    _check_rotation(R_LC)
    # the target seen from the rig lies on C's +y axis
    assert np.allclose(R_LC.T @ r, [0.0, np.linalg.norm(r), 0.0], atol=1e-9 * np.linalg.norm(r))
    # z_C is the unit vector perpendicular to y_C closest to the hint (zenith = -z_L)
    y, z = R_LC[:, 1], R_LC[:, 2]
    hint = np.array([0.0, 0.0, -1.0])
    perp = hint - (hint @ y) * y
    if np.linalg.norm(perp) > 1e-6:
        assert np.allclose(z, perp / np.linalg.norm(perp), atol=1e-9)
    # x = y cross z
    assert np.allclose(R_LC[:, 0], np.cross(y, z))


def test_target_pointing_examples_and_fallback():
    # Target ahead along-track with the default (zenith) hint, by hand:
    R = target_pointing_R_LC([10.0, 0.0, 0.0])
    assert np.allclose(R[:, 1], [1, 0, 0]) and np.allclose(R[:, 2], [0, 0, -1])
    assert np.allclose(R[:, 0], [0, 1, 0])  # y_C x z_C = x_L x (-z_L) = y_L
    # Boresight along the hint (target straight above / below): fall back, stay valid.
    for r in ([0.0, 0.0, -7.0], [0.0, 0.0, 3.0]):
        R = target_pointing_R_LC(r)
        _check_rotation(R)
        assert np.allclose(R[:, 1], np.asarray(r) / np.linalg.norm(r))
    # Vectorised over time with a custom hint.
    rs = np.array([[1.0, 2.0, 3.0], [0.0, 5.0, 0.0], [-4.0, 0.0, 1.0]])
    Rs = target_pointing_R_LC(rs, up_hint_L=(0.0, 1.0, 0.0))
    assert Rs.shape == (3, 3, 3)
    _check_rotation(Rs)
    assert np.allclose(Rs[:, :, 1], rs / np.linalg.norm(rs, axis=-1, keepdims=True))
    assert np.allclose(Rs[1], target_pointing_R_LC(rs[1], (0.0, 1.0, 0.0)))


def test_fixed_R_LC():
    R_BC = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # boresight along y_B
    assert np.allclose(fixed_R_LC(R_BC), R_BC)
    c, s = np.cos(0.3), np.sin(0.3)
    R_LB = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R_LC = fixed_R_LC(R_BC, R_LB)
    _check_rotation(R_LC)
    assert np.allclose(R_LC, R_LB @ R_BC)
    assert fixed_R_LC(np.stack([R_BC] * 4), np.stack([R_LB] * 4)).shape == (4, 3, 3)
