"""The CLI contract: commands, exit statuses, one-line errors, files written."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from tumblenav.cli import main


def run_cli(args, capsys):
    with pytest.raises(SystemExit) as ei:
        main(args)
    cap = capsys.readouterr()
    return ei.value.code, cap.out, cap.err


def test_scenarios_list_and_show(capsys, tmp_path):
    code, out, _ = run_cli(["scenarios", "list"], capsys)
    assert code == 0
    for name in ("hu2024", "yu2019", "chang2021", "kabir2025"):
        assert name in out
    code, out, _ = run_cli(["scenarios", "show", "hu2024"], capsys)
    assert code == 0 and "inertia_kg_m2" in out
    p = tmp_path / "mine.yaml"
    p.write_text(out)
    code, _, err = run_cli(["simulate", str(p), "-o", str(tmp_path / "o"), "--no-plots"], capsys)
    assert code == 0, err


def test_unknown_scenario_exit_2_one_line(capsys):
    code, _, err = run_cli(["scenarios", "show", "nope"], capsys)
    assert code == 2
    assert "unknown scenario" in err and len(err.strip().splitlines()) == 1
    assert "Traceback" not in err


def test_bad_yaml_exit_2(capsys, tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("name: x\nduration_s: -1\n")
    code, _, err = run_cli(["simulate", str(p), "-o", str(tmp_path / "o")], capsys)
    assert code == 2 and "Traceback" not in err and str(p) in err.replace("\n", "")


def test_simulate_writes_self_describing_files(capsys, tmp_path):
    out = tmp_path / "sim"
    code, _, err = run_cli(["simulate", "hu2024", "-o", str(out), "--seed", "7"], capsys)
    assert code == 0, err
    truth = xr.open_dataset(out / "truth.nc")
    meas = xr.open_dataset(out / "measurements.nc")
    assert truth["time"].attrs["units"] == "s"
    assert truth["r_L"].attrs["units"] == "m"
    assert meas["uv"].attrs["units"] == "px"
    assert meas.sizes["camera"] == 2 and meas.sizes["feature"] == 6
    # missing observations are explicit: NaN exactly where the mask says unobserved
    obs = meas["observed"].values.astype(bool)
    uv = meas["uv"].values
    assert np.all(np.isnan(uv[~obs])) and np.all(np.isfinite(uv[obs]))
    # the 20 s occlusion window is empty
    t = meas["time"].values
    assert not obs[(t >= 60.0) & (t < 80.0)].any()
    assert (out / "truth.png").exists() and (out / "measurements.png").exists()
    # no temporary files left behind
    assert not list(Path(out).glob(".*tmp"))


def test_console_script_help():
    exe = Path(sys.executable).parent / "tumblenav"
    r = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "simulate" in r.stdout
    r = subprocess.run([str(exe), "simulate"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
