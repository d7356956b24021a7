"""Yu 2019 Sec. 2.1-2.2 and Sec. 4: RANSAC planes, distribution matrix, rectangle sides."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from tumblenav import rotations as rot
from tumblenav.frontends import planes as pl
from tumblenav.papers import yu2019


def test_ransac_iterations_eq2():
    # Yu 2019 eq. 2: K = log(1 - Phi) / log(1 - (1 - tau)^3)
    assert pl.ransac_iterations(0.5, 0.99) == math.ceil(math.log(0.01) / math.log(1 - 0.125))
    assert pl.ransac_iterations(0.0, 0.99) == 1
    with pytest.raises(ValueError):
        pl.ransac_iterations(1.0)


@pytest.mark.parametrize(("outliers", "paper"), [(0, 2500), (100, 2400), (500, 2000), (1250, 1252)])
def test_table1_extracted_points_within_1_percent(outliers, paper):
    # Yu 2019 Table 1 (2500 points, threshold 0.005, 300 iterations); target: within 1%
    cloud = yu2019.with_outliers(2500, outliers, np.random.default_rng([5, outliers]))
    fit = pl.ransac_plane(cloud, yu2019.THRESHOLD_CM, np.random.default_rng(1), max_iterations=300)
    assert abs(fit.n_inliers - paper) <= 0.01 * paper
    assert abs(abs(fit.normal[2]) - 1.0) < 1e-9 and abs(abs(fit.d) - 6.5) < 1e-9


@given(st.integers(0, 10_000))
def test_ransac_finds_a_rotated_noisy_plane(seed):
    rng = np.random.default_rng(seed)
    R = rot.exp_map(rng.normal(size=3))
    plane = yu2019.rectangle_cloud(800, rng, sigma_cm=0.001) @ R.T
    junk = rng.uniform(-20, 20, (400, 3))
    cloud = np.vstack([plane, junk])
    fit = pl.ransac_plane(cloud, 0.01, rng)
    n_true = R[:, 2]
    assert abs(abs(fit.normal @ n_true) - 1) < 1e-6
    assert fit.inliers[:800].mean() > 0.99 and fit.inliers[800:].mean() < 0.01


def test_bad_clouds_are_handled():
    rng = np.random.default_rng(0)
    assert pl.ransac_plane(np.zeros((0, 3)), 0.01, rng) is None
    assert pl.ransac_plane(np.full((10, 3), np.nan), 0.01, rng) is None
    cloud = yu2019.rectangle_cloud(300, rng)
    cloud[::7] = np.nan  # NaN points never vote and are never inliers
    fit = pl.ransac_plane(cloud, 0.005, rng)
    assert fit.n_inliers == np.sum(np.all(np.isfinite(cloud), axis=1))
    assert not fit.inliers[::7].any()
    with pytest.raises(ValueError):
        pl.ransac_plane(np.zeros((5, 2)), 0.01, rng)
    # a cloud with no plane: consensus stays tiny, so extract_planes finds nothing
    assert pl.extract_planes(rng.uniform(-1, 1, (500, 3)), 1e-4, rng, min_points=50) == []


def test_extract_two_planes():
    rng = np.random.default_rng(3)
    a = yu2019.rectangle_cloud(600, rng)
    b = yu2019.rectangle_cloud(400, rng) @ rot.exp_map([np.pi / 2, 0, 0]).T + [0, 0, 30]
    planes = pl.extract_planes(np.vstack([a, b]), 0.01, rng, min_points=100)
    assert [p.n_inliers for p in planes] == [600, 400]


def test_distribution_matrix_and_rectangle_sides():
    # eq. 17: E(I) = side^2/12 + sigma^2; a large cloud recovers the 10 x 18 cm sides
    rng = np.random.default_rng(11)
    sigma = 0.1
    d = pl.distribution_matrix(yu2019.rectangle_cloud(200_000, rng, sigma_cm=sigma))
    assert np.allclose(d.eigenvalues, sorted(yu2019.theory(sigma)), rtol=0.01)
    assert np.allclose(d.R @ np.diag(d.eigenvalues) @ d.R.T, d.J)
    b, a, s = pl.rectangle_sides(d.eigenvalues, sigma)
    assert b == pytest.approx(10.0, rel=0.01) and a == pytest.approx(18.0, rel=0.01)
    assert s == pytest.approx(sigma, rel=0.02)
    assert pl.match_rectangle((b, a), {"panel": (18.0, 10.0), "bus": (30, 30)}) == "panel"
    assert pl.match_rectangle((b, a), {"bus": (30, 30)}) is None


def test_yu2019_summary_tables_have_the_contract_keys(tmp_path):
    s = yu2019.reproduce(tmp_path)
    assert [r["outliers"] for r in s["table1"]] == [0, 100, 500, 1250]
    assert set(s["table1"][0]) == {
        "outliers",
        "extracted_points",
        "time_ms",
        "paper_extracted",
        "paper_time_ms",
    }
    assert [r["points"] for r in s["table2"]] == [10000, 5000, 2500, 1250, 625]
    assert [r["noise_cm"] for r in s["table3"]] == [0.0, 0.01, 0.1, 1.0]
    assert [r["noise_cm"] for r in s["table4"]] == [0.0, 0.01, 0.1, 1.0]
    assert (tmp_path / "summary.json").exists()


@given(st.integers(0, 10_000))
def test_rectangle_frame_and_symmetry_resolution(seed):
    """Yu 2019 Sec. 2.3: the eigenvectors give the rectangle's frame up to the 4 cases of
    Fig. 2; the prediction (eq. 21-23) picks the right one (eq. 24-25)."""
    rng = np.random.default_rng(seed)
    R_CP = rot.exp_map(rng.normal(size=3) * 2)  # true attitude of the rectangle in C
    cloud = yu2019.rectangle_cloud(3000, rng) - [0, 0, yu2019.Z_CM]
    pts = cloud @ R_CP.T + rng.normal(size=3)
    R_meas = pl.rectangle_frame(pl.distribution_matrix(pts))
    assert np.isclose(np.linalg.det(R_meas), 1.0)
    # R_meas equals the truth up to one of the four half turns
    k_true = int(np.argmax([np.trace(R_CP.T @ R_meas @ S) for S in pl.RECTANGLE_SYMMETRIES]))
    assert np.allclose(R_meas @ pl.RECTANGLE_SYMMETRIES[k_true], R_CP, atol=0.05)
    # a prediction 20 deg off resolves the ambiguity
    R_pred = rot.exp_map(rng.normal(size=3) * 0.2) @ R_CP
    fixed, _ = pl.resolve_symmetry(R_meas, R_pred)
    assert np.allclose(fixed, R_CP, atol=0.05)
