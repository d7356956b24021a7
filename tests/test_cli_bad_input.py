"""Bad input found by a hostile user's sweep of the CLI (thirteenth session): each gets one
line and exit status 2 before any work (or, for damaged stored runs, a warning and a
recomputation), never an internal error, and no other command's results are replaced."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml

from tumblenav.cli import main
from tumblenav.scenario import load_scenario, scenario_to_yaml


def run(args, capsys):
    with pytest.raises(SystemExit) as ei:
        main([str(a) for a in args])
    cap = capsys.readouterr()
    return ei.value.code, cap.out, cap.err


def short(tmp_path: Path, name: str = "short.yaml", **changes) -> Path:
    """hu2024, 20 s: small enough to run in a test."""
    s = load_scenario("hu2024").with_updates(
        duration_s=20.0, steady_state_window_s=[10.0, 20.0], **{"montecarlo.runs": 2}
    )
    d = yaml.safe_load(scenario_to_yaml(s))
    for key, value in changes.items():
        node = d
        *path, last = key.split(".")
        for p in path:
            node = node[p]
        node[last] = value
    p = tmp_path / name
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


def one_line_error(code, err, *needles):
    assert code == 2, err
    assert "Traceback" not in err and "internal error" not in err
    for n in needles:
        assert n in " ".join(err.split()), (n, err)  # rich wraps where the path ends


def test_output_folders_that_cannot_be_used(tmp_path, capsys):
    sc = short(tmp_path)
    a_file = tmp_path / "afile"
    a_file.write_text("mine")
    for out, why in ((a_file, "is a file"), (a_file / "sub", "is a file"), ("", "empty path")):
        code, _, err = run(["estimate", sc, "-o", out, "--no-plots"], capsys)
        one_line_error(code, err, why)
    assert a_file.read_text() == "mine"
    code, _, err = run(["estimate", sc, "--seed", "-5", "-o", tmp_path / "neg"], capsys)
    assert code == 2 and not (tmp_path / "neg").exists()


def test_one_command_does_not_replace_another_commands_results(tmp_path, capsys):
    sc = short(tmp_path)
    camp = tmp_path / "camp"
    code, _, err = run(["montecarlo", sc, "--runs", 2, "--workers", 1, "-o", camp], capsys)
    assert code == 0, err
    before = (camp / "summary.json").read_bytes()
    code, _, err = run(["estimate", sc, "-o", camp, "--no-plots"], capsys)
    one_line_error(code, err, "Monte Carlo campaign", "choose another folder")
    assert (camp / "summary.json").read_bytes() == before
    single = tmp_path / "single"
    code, _, err = run(["estimate", sc, "-o", single, "--no-plots"], capsys)
    assert code == 0, err
    code, _, err = run(["montecarlo", sc, "--runs", 2, "--workers", 1, "-o", single], capsys)
    one_line_error(code, err, "one estimate", "choose another folder")
    code, _, err = run(
        ["compare", sc, "-e", "ekf-dpacf,ekf-baseline", "--runs", 2, "--workers", 1, "-o", camp],
        capsys,
    )
    one_line_error(code, err, "Monte Carlo campaign", "choose another folder")
    assert (camp / "summary.json").read_bytes() == before


@pytest.mark.parametrize(
    "changes, needles",
    [
        ({"target.r0_L_m": [0.0, 0.0, 0.0]}, ["target.r0_L_m", "starts at the chaser"]),
        ({"target.r0_L_m": [float("nan"), 10.0, 10.0]}, ["target.r0_L_m[0]", "finite"]),
        ({"target.v0_L_m_s": [float("inf"), 0.0, 0.0]}, ["target.v0_L_m_s[0]", "finite"]),
        ({"duration_s": True}, ["duration_s", "expected a number, got true"]),
        ({"target.omega0_T_rad_s": [1e6, 0.0, 0.0]}, ["omega0_T_rad_s", "half a turn"]),
        ({"target.features_T_m": {"count": 100000}}, ["count", "10000"]),
        (
            {"target.features_T_m": {"count": 6, "low_m": 1.0, "high_m": -2.0}},
            ["high_m must be greater than low_m"],
        ),
        ({"estimator.name": "nosuch"}, ["estimator.name", "unknown estimator 'nosuch'"]),
        (
            {
                "chaser.attitude": "target-pointing",
                "chaser.camera_mount_R_LC": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]],
            },
            ["camera_mount_R_LC", "applies to attitude 'lvlh' only"],
        ),
        ({"sensor.noise": {"angular_rad": 0.0}}, ["sensor.noise is 0", "ekf-dpacf"]),
    ],
)
def test_bad_scenario_values_are_named(changes, needles, tmp_path, capsys):
    sc = short(tmp_path, **changes)
    out = tmp_path / "o"
    code, _, err = run(["estimate", sc, "-o", out, "--no-plots"], capsys)
    one_line_error(code, err, *needles)
    assert not out.exists()


def test_a_folder_given_as_a_file(tmp_path, capsys):
    d = tmp_path / "adir.yaml"
    d.mkdir()
    code, _, err = run(["estimate", d, "-o", tmp_path / "o"], capsys)
    one_line_error(code, err, "a folder, not a scenario file")


def test_a_damaged_stored_run_is_set_aside_and_computed_again(tmp_path, capsys):
    sc = short(tmp_path)
    camp = tmp_path / "camp"
    code, _, err = run(["montecarlo", sc, "--runs", 3, "--workers", 1, "-o", camp], capsys)
    assert code == 0, err
    good = (camp / "runs" / "run_000001.npz").read_bytes()
    (camp / "runs" / "run_000001.npz").write_bytes(good[:100])  # truncated
    (camp / "runs" / "run_000002.npz").write_bytes(b"")  # emptied
    code, _, err = run(["montecarlo", sc, "--runs", 3, "--workers", 1, "-o", camp], capsys)
    assert code == 0, err
    flat = " ".join(err.split())  # rich wraps at the console's width, where the path ends
    assert "2 stored run(s)" in flat and "computed again" in flat
    assert (camp / "runs" / "run_000001.npz").read_bytes() == good  # the same seed again
    assert (camp / "runs" / "run_000002.npz.damaged").exists()
    assert json.loads((camp / "summary.json").read_text())["runs"] == 3


def _edited(tmp_path: Path, capsys, edit) -> tuple[int, str]:
    sc = short(tmp_path)
    sim = tmp_path / "sim"
    code, _, err = run(["simulate", sc, "-o", sim, "--no-plots"], capsys)
    assert code == 0, err
    ds = xr.load_dataset(sim / "measurements.nc")
    edit(ds)
    bad = tmp_path / "bad"
    bad.mkdir()
    ds.to_netcdf(bad / "measurements.nc")
    code, _, err = run(
        ["estimate", sc, "--measurements", bad, "-o", tmp_path / "o", "--no-plots"], capsys
    )
    return code, err


def _zero_quaternion(ds):
    ds["q_CL"].values[5] = 0.0


def _observed_7(ds):
    ds["observed"].values[3, 0, 0] = 7


def _nan_where_observed(ds):
    k, c, j = np.argwhere(ds["observed"].values == 1)[0]
    ds["uv"].values[k, c, j, 0] = np.nan


@pytest.mark.parametrize(
    "edit, needles",
    [
        (_zero_quaternion, ["q_CL at epoch 5", "not a unit quaternion"]),
        (_observed_7, ["observed holds [7.0]"]),
        (_nan_where_observed, ["uv at epoch", "not finite where observed is 1"]),
    ],
)
def test_edited_measurement_files_are_refused(edit, needles, tmp_path, capsys):
    code, err = _edited(tmp_path, capsys, edit)
    one_line_error(code, err, "measurements.nc", *needles)


def test_a_run_that_measures_nothing_says_so(tmp_path, capsys):
    # the target behind the chaser of an LVLH-pointing camera: no feature is ever seen
    sc = short(
        tmp_path,
        **{
            "chaser.attitude": "lvlh",
            "target.r0_L_m": [-20.0, 0.0, 0.0],
            "target.v0_L_m_s": [0.0, 0.0, 0.0],
        },
    )
    code, out, err = run(["estimate", sc, "-o", tmp_path / "o", "--no-plots"], capsys)
    assert code == 0, err
    assert "the sensor measured nothing in the whole run" in (out + err).replace("\n", " ")
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert any("measured nothing" in w for w in summary["estimator_warnings"])


def test_the_report_of_an_unfinished_campaign_says_how_to_finish_it(tmp_path, capsys):
    sc = short(tmp_path)
    camp = tmp_path / "camp"
    code, _, err = run(["montecarlo", sc, "--runs", 2, "--workers", 1, "-o", camp], capsys)
    assert code == 0, err
    (camp / "summary.json").unlink()  # as a campaign interrupted before its summary
    code, _, err = run(["report", camp], capsys)
    one_line_error(code, err, "summary is not written yet", "montecarlo command again")


def test_two_commands_on_one_campaign_folder_at_once(tmp_path, capsys):
    from tumblenav.campaign.store import CampaignStore

    sc = short(tmp_path)
    camp = tmp_path / "camp"
    with CampaignStore(camp).exclusive():  # as another command writing there now
        code, _, err = run(["montecarlo", sc, "--runs", 2, "--workers", 1, "-o", camp], capsys)
        one_line_error(code, err, "another tumblenav command is writing this campaign now")
        assert not (camp / "campaign.json").exists()
    code, _, err = run(["montecarlo", sc, "--runs", 2, "--workers", 1, "-o", camp], capsys)
    assert code == 0, err


def test_malformed_point_clouds_and_summaries(tmp_path, capsys):
    from tumblenav.errors import InputError
    from tumblenav.importers.clouds import read_cloud

    cases = {
        "neg.ply": b"ply\nformat ascii 1.0\nelement vertex -3\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n",
        "extra.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n0 0 5\n0 1 5\n",
        "word.pcd": b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n0.1 abc 5\n",
        "view.pcd": b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nVIEWPOINT 0 0 0 foo\nPOINTS 1\n"
        b"DATA ascii\n0 0 5\n",
        "negbin.pcd": b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH -3\nPOINTS -3\nDATA binary\n"
        + bytes(72),
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError) as ei:
            read_cloud(tmp_path / name)
        assert name in str(ei.value)
    folder = tmp_path / "s"
    folder.mkdir()
    for text, why in (
        ("[1, 2, 3]", "JSON list"),
        ('{"window_s": 5}', "window_s: 5 where tumblenav writes a list"),
    ):
        (folder / "summary.json").write_text(text)
        code, _, err = run(["report", folder], capsys)
        one_line_error(code, err, why)


def test_a_comparison_is_not_shrunk_by_a_later_one(tmp_path, capsys):
    sc = short(tmp_path)
    out = tmp_path / "cmp"
    args = ["--runs", 1, "--workers", 1, "-o", out, "--no-plots"]
    code, _, err = run(["compare", sc, "-e", "ekf-dpacf,ekf-baseline", *args], capsys)
    assert code == 0, err
    before = (out / "summary.json").read_bytes()
    code, _, err = run(["compare", sc, "-e", "ekf-dpacf,ekf-pose", *args], capsys)
    one_line_error(code, err, "would drop ekf-baseline", "-e ekf-dpacf,ekf-baseline,ekf-pose")
    assert (out / "summary.json").read_bytes() == before


def test_scenarios_show_of_a_file_says_what_show_is_for(tmp_path, capsys):
    sc = short(tmp_path)
    code, _, err = run(["scenarios", "show", sc], capsys)
    one_line_error(code, err, "prints a built-in scenario", "this is a file")


def test_import_tables_name_missing_columns_and_accept_extras_and_a_bom(tmp_path):
    from tumblenav.errors import InputError
    from tumblenav.importers.clouds import read_index
    from tumblenav.importers.tracks import read_tracks

    index = tmp_path / "clouds.csv"
    index.write_text("t_s,path\n0.0,000000.ply\n1.0,000001.ply\n")
    with pytest.raises(InputError) as ei:
        read_index(index, ("file",))
    assert "missing column(s) file" in str(ei.value) and "the header has t_s, path" in str(ei.value)
    tracks = tmp_path / "tracks.csv"
    rows = "0.0,1,10.0,10.0,5.0,10.0,a note\n0.2,1,11.0,10.0,6.0,10.0,\n"
    head = "t_s,feature_id,u_left_px,v_left_px,u_right_px,v_right_px,comment\n"
    tracks.write_bytes(b"\xef\xbb\xbf" + (head + rows).encode())  # a BOM, an extra column
    table = read_tracks(tracks)
    assert table.labels == ["1"] and np.allclose(table.uv[1, 0, 0], [11.0, 10.0])
