"""Third-party estimators register through the ``tumblenav.estimators`` entry-point group: the
example plugin of docs/extending.md (tests/plugin_example) is installed into a folder, found
by ``tumblenav estimators`` and run by ``tumblenav estimate`` like a built-in one."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).parent


@pytest.fixture(scope="module")
def plugin_path(tmp_path_factory) -> Path:
    """The example plugin installed (pip, offline, no dependencies) into a folder of its own."""
    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    src = build / "src"
    subprocess.run(
        ["cp", "-r", str(HERE / "plugin_example"), str(src)], check=True
    )  # pip builds in place: keep tests/ clean
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
         "--no-index", "--target", str(target), str(src)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert list(target.glob("tumblenav_hold-*.dist-info"))
    return target


def _cli(args: list[str], plugin_path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(plugin_path), "COLUMNS": "250"}  # tables unwrapped
    return subprocess.run(
        [sys.executable, "-m", "tumblenav.cli", *args],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip


def test_an_installed_plugin_is_listed(plugin_path):
    r = _cli(["estimators"], plugin_path)
    assert r.returncode == 0, r.stderr
    assert "hold-centroid" in r.stdout and "tumblenav-hold" in r.stdout
    assert "not loaded" not in r.stderr


def test_an_installed_plugin_runs_like_a_built_in_estimator(plugin_path, tmp_path):
    sc = tmp_path / "short.yaml"
    from tumblenav.scenario import load_scenario, scenario_to_yaml

    # the example holds the first centroid while the target moves away: judge its first 2 s
    s = load_scenario("hu2024").with_updates(duration_s=20.0, steady_state_window_s=[0.0, 2.0])
    sc.write_text(scenario_to_yaml(s))
    out = tmp_path / "est"
    r = _cli(
        ["estimate", str(sc), "-e", "hold-centroid", "--no-plots", "-o", str(out)], plugin_path
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["estimator"] == "hold-centroid"
    # evaluated by the generic convention: position in L against the truth (the features'
    # centroid is within a metre of the mass centre)
    assert 0 < summary["rmse"]["position_m"] < 2.0


def test_without_the_plugin_the_name_is_unknown(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "tumblenav.cli", "estimate", "hu2024", "-e", "hold-centroid",
         "-o", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 2 and "unknown estimator" in r.stderr


def test_a_broken_plugin_is_reported_not_fatal(tmp_path):
    """An entry point whose module fails to import: the tool still works and says why."""
    dist = tmp_path / "broken_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(
        "[tumblenav.estimators]\nbroken = no_such_module_xyz:Factory\n"
    )
    r = _cli(["estimators"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "ekf-dpacf" in r.stdout
    assert "plugin broken not loaded" in " ".join(r.stderr.split())
