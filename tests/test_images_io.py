"""Stereo images as measurements: simulated lazily and deterministically, written as PNG pairs
with measurements.nc, read back pixel for pixel, and bad image files refused with one line."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from tumblenav import io, sensors
from tumblenav.campaign.store import run_seed
from tumblenav.errors import InputError
from tumblenav.measurements import STEREO_IMAGES, StereoImageMeasurements, kind_of
from tumblenav.measurements.images import read_png
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate


@dataclass(frozen=True)
class _Noise:
    """A small synthetic source: seeded noise images."""

    n: int
    shape: tuple[int, int]

    def __len__(self) -> int:
        return self.n

    def pair(self, k: int):
        rng = np.random.default_rng([7, k])
        return tuple(rng.integers(0, 256, self.shape, dtype=np.uint8) for _ in range(2))


def _small(n: int = 3, w: int = 64, h: int = 48) -> StereoImageMeasurements:
    rig = sensors.convergent_rig(50.0, 0.3, np.radians(5.0), (w, h))
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return StereoImageMeasurements(
        t=np.arange(n) * 0.2, q_CL=q, q_LI=q, rig=rig, noise_px=0.5, source=_Noise(n, (h, w))
    )


def test_png_pairs_round_trip_pixel_for_pixel(tmp_path: Path):
    m = _small()
    m.write(tmp_path, "test")
    assert sorted(p.name for p in (tmp_path / "images").iterdir())[:2] == [
        "000000_left.png",
        "000000_right.png",
    ]
    back = StereoImageMeasurements.from_dataset(
        io.read_netcdf(tmp_path / "measurements.nc"), tmp_path
    )
    assert np.array_equal(back.t, m.t) and back.noise_px == 0.5
    assert back.rig.kind == "convergent" and np.allclose(back.rig.right.R_CkC, m.rig.right.R_CkC)
    for a, b in zip(back.pairs(), m.pairs(), strict=True):
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not list(tmp_path.rglob("*.tmp"))  # atomic writes leave nothing behind


@pytest.mark.parametrize(
    "bad, words",
    [
        ("missing", "image file not found"),
        ("size", "calibration says 64 x 48 px"),
        ("colour", "3-channel colour image"),
        ("16bit", "not an 8-bit grayscale image"),
        ("text", "cannot read the image"),
    ],
)
def test_bad_image_files_are_one_line_naming_the_file(tmp_path: Path, bad, words):
    _small().write(tmp_path)
    f = tmp_path / "images" / "000001_right.png"
    if bad == "missing":
        f.unlink()
    elif bad == "size":
        cv2.imwrite(str(f), np.zeros((48, 60), np.uint8))
    elif bad == "colour":
        cv2.imwrite(str(f), np.zeros((48, 64, 3), np.uint8))
    elif bad == "16bit":
        cv2.imwrite(str(f), np.zeros((48, 64), np.uint16))
    else:
        f.write_text("not an image")
    back = StereoImageMeasurements.from_dataset(
        io.read_netcdf(tmp_path / "measurements.nc"), tmp_path
    )
    back.source.pair(0)  # the others are fine
    with pytest.raises(InputError) as ei:
        back.source.pair(1)
    assert words in str(ei.value) and "000001_right.png" in str(ei.value)
    assert "\n" not in str(ei.value)


def test_read_png_accepts_8bit_grayscale(tmp_path: Path):
    img = np.arange(12, dtype=np.uint8).reshape(3, 4)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    assert np.array_equal(read_png(tmp_path / "a.png", (3, 4)), img)


@pytest.fixture(scope="module")
def close_images():
    sc = load_scenario("chang2021_close").with_updates(duration_s=0.6, steady_state_window_s=None)
    return sc, simulate(sc, run_seed(sc.montecarlo.seed, 0))


def test_simulated_images_are_lazy_deterministic_and_seeded(close_images):
    sc, (truth, meas) = close_images
    assert kind_of(sc.sensor) == STEREO_IMAGES and isinstance(meas, StereoImageMeasurements)
    a, b = meas.source.pair(2), meas.source.pair(2)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])  # any order, same pixels
    assert a[0].shape == (1024, 1024) and a[0].dtype == np.uint8
    assert (a[0] > 30).mean() > 0.01  # the lit target is in the left view ...
    assert (a[1] > 30).mean() > 0.01  # ... and in the right one
    _, other = simulate(sc, run_seed(sc.montecarlo.seed, 1))
    c = other.source.pair(2)
    assert not np.array_equal(a[0], c[0])  # another run: other camera noise
    assert np.abs(a[0].astype(int) - c[0].astype(int)).mean() < 3  # ... of the same scene


def test_simulate_writes_png_pairs_that_read_back_identical(close_images, tmp_path: Path):
    from tumblenav import pipeline

    sc, (truth, meas) = close_images
    pipeline.run_simulate(str(_yaml(sc, tmp_path)), tmp_path / "sim", plots=False)
    ds = io.read_netcdf(tmp_path / "sim" / "measurements.nc")
    assert ds.attrs["kind"] == "stereo-images"
    back = StereoImageMeasurements.from_dataset(ds, tmp_path / "sim")
    for a, b in zip(back.pairs(), meas.pairs(), strict=True):
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert (tmp_path / "sim" / "truth.nc").is_file()


def _yaml(sc, folder: Path) -> Path:
    from tumblenav.scenario import scenario_to_yaml

    p = folder / "scenario.yaml"
    p.write_text(scenario_to_yaml(sc))
    return p


def test_track_truth_points_lie_under_the_tracked_corners(close_images):
    """For estimators of feature positions on images, each track's true point is the rendered
    surface point under its first left pixel: it must project back to that pixel and agree
    with the track's own triangulation (F's accuracy: 3 mm median depth error at 10 m)."""
    from tumblenav import rotations as rot
    from tumblenav.frontends import stages
    from tumblenav.frontends.triangulation import triangulate_two_ray
    from tumblenav.simulation import with_track_truth

    sc, (truth, meas) = close_images
    tracks, _ = stages.prepare(meas, ("stereo-tracks",), {})
    tt = with_track_truth(truth, meas, tracks)
    assert tt.features_T.shape == (tracks.uv.shape[2], 3)
    k = 0
    ids = np.flatnonzero(tracks.observed[k, 0])
    assert len(ids) >= 100
    R_CL = rot.quat_to_matrix(truth.q_CL[k])
    p_C = (tt.features_T[ids] @ truth.R_LT[k].T + truth.r_L[k]) @ R_CL.T
    uv, _ = sensors.project(meas.rig, p_C)
    assert np.nanmax(np.abs(uv[0] - tracks.uv[k, 0, ids])) < 1.0  # within the pixel
    L, R = meas.rig.left, meas.rig.right
    tri = triangulate_two_ray(
        tracks.uv[k, 0, ids],
        tracks.uv[k, 1, ids],
        (L.focal_px, R.focal_px),
        (L.principal_point_px, R.principal_point_px),
        L.R_CkC,
        L.p_CkinC,
        R.R_CkC,
        R.p_CkinC,
    )
    assert np.median(np.linalg.norm(tri - p_C, axis=1)) < 0.01


def test_estimate_reads_png_pairs_and_reports_the_front_end(tmp_path: Path, capsys):
    """`estimate --measurements DIR` on a folder of PNG pairs: the image front end runs, the
    summary says what it found; a pair whose image is missing is one line, exit 2."""
    from tumblenav import cli, pipeline

    sc = load_scenario("chang2021_close").with_updates(
        duration_s=3.0, steady_state_window_s=[2.0, 3.0], **{"estimator.tuning": {"init_frames": 8}}
    )
    y = _yaml(sc, tmp_path)
    pipeline.run_simulate(str(y), tmp_path / "sim", plots=False)

    def run(out: str) -> tuple[int, str]:
        argv = [
            "estimate",
            str(y),
            "--measurements",
            str(tmp_path / "sim"),
            "-o",
            str(tmp_path / out),
        ]
        with pytest.raises(SystemExit) as ei:
            cli.main(argv + ["--no-plots"])
        return int(ei.value.code or 0), capsys.readouterr().err

    code, err = run("est")
    assert code == 0, err
    s = io.read_json(tmp_path / "est" / "summary.json")
    assert s["frontend"]["features_mean"] > 50 and s["frontend"]["epochs"] == 16
    assert s["measurements"].endswith("measurements.nc")
    (tmp_path / "sim" / "images" / "000007_left.png").unlink()
    code, err = run("est2")
    assert code == 2 and "000007_left.png" in err and "not found" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "est2").exists()


def test_files_hold_the_scene_top_first(tmp_path: Path):
    """In memory row j holds v in [j, j+1), v growing up the scene (the camera's z); the PNG
    files hold the rows as a camera gives them, the scene's top first."""
    from tumblenav.measurements.images import read_frame, write_frame

    img = np.zeros((48, 64), np.uint8)
    img[0] = 255  # v in [0, 1): the bottom of the scene
    write_frame(tmp_path / "f.png", img)
    raw = cv2.imread(str(tmp_path / "f.png"), cv2.IMREAD_UNCHANGED)
    assert raw[-1].min() == 255 and raw[0].max() == 0  # the file's last row
    assert np.array_equal(read_frame(tmp_path / "f.png", (48, 64)), img)
    # a point above the optical axis (z > 0) projects to v > cv: the upper half of the file
    rig = sensors.parallel_rig(50.0, 0.3, (64, 48))
    uv, _ = sensors.project(rig, np.array([[0.0, 5.0, 1.0]]))
    assert uv[0, 0, 1] > 24
