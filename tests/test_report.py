"""`tumblenav report DIR`: one self-contained HTML file for any output folder, checked as a
document and, where Chromium is installed, rendered in a real headless browser."""

from __future__ import annotations

import base64
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tumblenav.cli import main
from tumblenav.scenario import load_scenario, scenario_to_yaml

PNG = b"\x89PNG\r\n\x1a\n"


def run(args, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as ei:
        main([str(a) for a in args])
    cap = capsys.readouterr()
    return int(ei.value.code), " ".join((cap.out + cap.err).split())


@pytest.fixture(scope="module")
def estimate_folder(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("rep")
    s = load_scenario("hu2024").with_updates(duration_s=30.0, steady_state_window_s=[20.0, 30.0])
    sc = tmp / "short.yaml"
    sc.write_text(scenario_to_yaml(s))
    out = tmp / "est"
    with pytest.raises(SystemExit) as ei:
        main(["estimate", str(sc), "-e", "ekf-dpacf", "-o", str(out)])
    assert ei.value.code == 0
    return out


def images(text: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r'src="data:image/png;base64,([^"]+)"', text)]


def test_the_report_holds_everything_and_fetches_nothing(estimate_folder, capsys):
    code, shown = run(["report", estimate_folder], capsys)
    assert code == 0, shown
    text = (estimate_folder / "report.html").read_text()
    assert text.startswith("<!DOCTYPE html>") and text.rstrip().endswith("</html>")
    figs = images(text)
    assert len(figs) == len(list(estimate_folder.glob("*.png"))) >= 1  # errors.png
    assert all(f.startswith(PNG) for f in figs)  # every figure is a whole PNG
    assert "tumblenav estimate" in text  # the command that made it
    assert "NEES/dof (95% bounds)" in text and "RMSE attitude_deg" in text
    assert "What differs from the built-in hu2024" in text and "duration_s: 30.0" in text
    assert "Versions" in text and "numpy" in text
    # self-contained: no script, no external resource
    assert "<script" not in text and not re.search(r'(src|href)="(https?:)?//', text)


def test_report_refuses_what_is_no_output_folder(tmp_path, capsys):
    assert run(["report", tmp_path / "nope"], capsys)[0] == 2
    assert run(["report", tmp_path], capsys)[0] == 2


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def test_the_report_renders_in_a_real_browser(estimate_folder, capsys, tmp_path):
    browser = _chromium()
    if browser is None:
        pytest.skip(
            "no Chromium on this machine (Debian: apt-get install chromium; .ci/run installs "
            "it when it runs as root): the report was not rendered in a browser"
        )
    run(["report", estimate_folder], capsys)
    shot = tmp_path / "report.png"
    r = subprocess.run(
        [browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
         "--enable-logging=stderr", "--v=0", "--virtual-time-budget=10000",
         "--window-size=1200,2400", f"--screenshot={shot}",
         (estimate_folder / "report.html").as_uri()],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    assert shot.exists() and shot.read_bytes().startswith(PNG)
    console = [ln for ln in r.stderr.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]
    assert console == [], console
