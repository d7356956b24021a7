"""Target mesh and the ray-cast depth sensor (Yu 2019 Sec. 4 set-up)."""

import numpy as np
import pytest

from tumblenav import rotations as rot
from tumblenav.errors import InputError
from tumblenav.frontends import planes as pl
from tumblenav.sensors.depth import DepthSensor, scan
from tumblenav.target_model import load_mesh, procedural_satellite


def test_procedural_satellite_geometry():
    m = procedural_satellite(bus_m=(1.0, 1.0, 1.2))
    assert m.mesh.bounds[1][0] == pytest.approx(0.5 + 1.8)  # bus half width + panel span
    names = {r.name for r in m.rectangles}
    assert {"bus+y", "bus-y", "panel+x_+z", "panel-x_-z"} <= names
    assert not {"bus+x", "bus-x", "bus+z", "bus-z"} & names  # panel roots, ring, nozzle
    for r in m.rectangles:
        assert np.allclose(r.R_MP.T @ r.R_MP, np.eye(3)) and np.isclose(np.linalg.det(r.R_MP), 1)
        assert r.sides_m[0] <= r.sides_m[1]
    with pytest.raises(InputError):
        procedural_satellite(bus_m=(1.0, -1.0, 1.0))


def test_mass_properties_of_a_box_bus():
    m = procedural_satellite(
        bus_m=(1.0, 1.0, 1.2), panel_m=(1e-3, 1e-3), ring_radius_m=0, nozzle_radius_m=0
    )
    c, moments = m.mass_properties()
    assert np.allclose(c, 0.0, atol=1e-3)
    # a 1 x 1 x 1.2 box of unit density: I = m (a^2 + b^2) / 12, m = 1.2
    assert moments[0] == pytest.approx(1.2 * 2 / 12, rel=1e-2)


def test_scan_of_a_face_gives_its_distance_and_plane():
    """The bus face -y seen from 5 m along +y: range 4.5 m, a plane with the bus face's sides."""
    m = procedural_satellite(
        bus_m=(1.0, 1.0, 1.2), panel_m=(1e-3, 1e-3), ring_radius_m=0, nozzle_radius_m=0
    )
    sensor = DepthSensor(fov_rad=np.radians(20), points=4000)
    pts, ok = scan(sensor, m, np.eye(3), np.array([0.0, 5.0, 0.0]), np.random.default_rng(0))
    assert ok.sum() > 100 and np.all(np.isnan(pts[~ok]))
    assert np.allclose(pts[ok, 1], 4.5, atol=1e-9)
    d = pl.distribution_matrix(pts[ok])
    b, a, _ = pl.rectangle_sides(d.eigenvalues)
    # a grid of rays over a 1 x 1.2 face: the sampled extent is the face up to one grid step
    assert b == pytest.approx(1.0, abs=0.06) and a == pytest.approx(1.2, abs=0.06)


def test_noise_outliers_and_max_range():
    m = procedural_satellite()
    R_SM = rot.exp_map([0.3, -0.2, 0.5])
    sensor = DepthSensor(np.radians(30), 2500, range_noise_m=0.01)
    clean, ok = scan(
        DepthSensor(np.radians(30), 2500), m, R_SM, [0, 8.0, 0], np.random.default_rng(1)
    )
    noisy, ok2 = scan(sensor, m, R_SM, [0, 8.0, 0], np.random.default_rng(1))
    assert np.array_equal(ok, ok2)
    dr = np.linalg.norm(noisy[ok], axis=1) - np.linalg.norm(clean[ok], axis=1)
    assert np.std(dr) == pytest.approx(0.01, rel=0.1)
    out, ok3 = scan(
        DepthSensor(np.radians(30), 2500, outlier_fraction=0.5),
        m,
        R_SM,
        [0, 8, 0],
        np.random.default_rng(2),
    )
    moved = np.abs(np.linalg.norm(out[ok3 & ok], axis=1) - np.linalg.norm(clean[ok3 & ok], axis=1))
    assert 0.3 < np.mean(moved > 0.01) < 0.7
    far, okf = scan(
        DepthSensor(np.radians(30), 2500, max_range_m=5.0),
        m,
        R_SM,
        [0, 8.0, 0],
        np.random.default_rng(3),
    )
    assert not okf.any()


def test_user_mesh_loading(tmp_path):
    p = tmp_path / "sat.stl"
    procedural_satellite().mesh.export(p)
    assert len(load_mesh(p).mesh.faces) > 0
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "absent.obj")
    bad = tmp_path / "bad.stl"
    bad.write_text("not a mesh")
    with pytest.raises(InputError):
        load_mesh(bad)


def test_simulate_yu2019_depth_measurements(tmp_path):
    """The built-in yu2019 scenario scans the procedural satellite 25 m ahead."""
    import xarray as xr

    from tumblenav.cli import main
    from tumblenav.scenario import load_scenario, scenario_to_yaml
    from tumblenav.simulation import DepthMeasurements, simulate

    s = load_scenario("yu2019").with_updates(duration_s=4.0)
    truth, meas = simulate(s, 0)
    assert isinstance(meas, DepthMeasurements)
    n = meas.observed.sum(axis=1)
    assert np.all(n > 0.5 * s.sensor.points)
    rng_m = np.linalg.norm(meas.points[meas.observed], axis=1)
    assert np.all(np.abs(rng_m - 25.0) < 4.0)  # the satellite is 25 m ahead, a few m across
    p = tmp_path / "yu.yaml"
    p.write_text(scenario_to_yaml(s))
    with pytest.raises(SystemExit) as ei:
        main(["simulate", str(p), "-o", str(tmp_path / "o"), "--no-plots"])
    assert ei.value.code == 0
    ds = xr.open_dataset(tmp_path / "o" / "measurements.nc")
    assert ds["points"].attrs["units"] == "m" and ds.sizes["time"] == 5


def test_pose_fixes_recover_the_model_pose():
    """Yu 2019 Sec. 2: planes -> recognised rectangles -> pose of M in S, symmetry resolved
    by a prediction 10 deg off."""
    from tumblenav.frontends.depth_pose import pose_fixes

    m = procedural_satellite()
    rng = np.random.default_rng(4)
    R_SM = rot.exp_map([0.4, 0.3, -0.6])
    p = np.array([0.3, 12.0, -0.2])
    sensor = DepthSensor(np.radians(40), 6000, range_noise_m=0.002)
    pts, ok = scan(sensor, m, R_SM, p, rng, on_target=True)
    R_pred = rot.exp_map(np.radians([6.0, -5.0, 6.0])) @ R_SM
    fixes, skipped = pose_fixes(pts[ok], m, 0.01, rng, sigma_m=0.002, R_SM_predicted=R_pred)
    assert fixes, skipped
    for f in fixes:
        ang = np.degrees(np.linalg.norm(rot.log_map(f.R_SM @ R_SM.T)))
        assert ang < 3.0, (f.rectangle, ang)
        assert np.linalg.norm(f.p_MinS - p) < 0.05
        assert not f.ambiguous
    # no points, no fix, and a reason
    assert pose_fixes(np.zeros((0, 3)), m, 0.01, rng) == ([], ["only 0 finite points"])


def _rectangle_cloud(rng, a: float, b: float, n: int = 2000, sigma: float = 0.002) -> np.ndarray:
    """n points uniform on an a x b rectangle 10 m ahead, facing the sensor (normal -y)."""
    u = rng.uniform(-a / 2, a / 2, n)
    w = rng.uniform(-b / 2, b / 2, n)
    return np.stack([u, 10.0 + sigma * rng.normal(size=n), w], axis=1)


def test_pose_fixes_skip_what_is_not_a_model_rectangle_and_say_why():
    """Yu 2019 Sec. 2 bad input: NaN/inf points are dropped; a plane whose sides match no
    rectangle of the model, and a model rectangle seen only in part, give no fix (never a
    wrong attitude) and a reason each; the whole face gives its fix."""
    from tumblenav.frontends.depth_pose import pose_fixes

    m = procedural_satellite()
    rng = np.random.default_rng(8)
    bus = next(r for r in m.rectangles if r.name == "bus+y")
    b, a = sorted(bus.sides_m)
    whole = _rectangle_cloud(rng, b, a)
    bad = whole.copy()
    bad[::50] = np.nan
    bad[1::50] = np.inf
    fixes, why = pose_fixes(bad, m, 0.01, rng, sigma_m=0.002)
    assert [f.rectangle for f in fixes] in (["bus+y"], ["bus-y"]), why  # faces of equal size
    # a square of another size: no fix, and the reason names the sides it saw
    fixes, why = pose_fixes(_rectangle_cloud(rng, 0.3, 0.3), m, 0.01, rng, sigma_m=0.002)
    assert fixes == [] and len(why) == 1 and "no known rectangle" in why[0]
    # the same bus face with 40% of its long side hidden: no fix
    part = whole[whole[:, 2] < whole[:, 2].min() + 0.6 * a]
    fixes, why = pose_fixes(part, m, 0.01, rng, sigma_m=0.002)
    assert fixes == [] and "seen in part" in why[0]
