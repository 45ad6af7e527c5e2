"""The lot report (mlaqc.resultsdb.lot_report) opened in a real headless browser: it loads, every plot draws,
no console message; and what it states is the seeded lot's truth."""

import os
import re
import shutil
import subprocess

import pytest

from mlaqc.cli import main
from test_resultsdb import _seeded_lot

REQUIRED = os.environ.get("MLAQC_REQUIRE_BROWSER") == "1"  # .ci/run installs Debian's chromium and sets it


def _browser() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        found = shutil.which(name)
        if found:
            return found
    return None


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    d = tmp_path_factory.mktemp("lot")
    db = str(d / "r.sqlite")
    truth = _seeded_lot(db)
    out = d / "lot.html"
    assert main(["lot", "report", "--db", db, "--lot", "L9", "--out", str(out)]) == 0
    return out, truth, db


def test_the_report_states_the_lots_truth(report):
    out, truth, _ = report
    page = out.read_text()
    passed = sum(truth["passed"].values())
    assert f"Lot L9: yield {passed}/50" in page
    assert "U(5,7) repeats: pitch at" in page and f"in {truth['master']} of 50 arrays" in page
    # two wafer maps, the Pareto, five charts (grid pitch and rotation, the assembly's distance and rotation,
    # flagged lenses; the tilts, read on no array, are said not charted), the stacked map
    assert page.count('<figure class="plot">') == 2 + 1 + 5 + 1
    assert "5 without this reading (not read or not determined): L9/W1/A009, L9/W1/A019" in page
    assert "50 without this reading (not read or not determined): L9/W1/A000" in page and "and 40 more" in page


@pytest.mark.timeout(180)
def test_the_report_draws_every_plot_in_a_headless_browser(report, tmp_path):
    browser = _browser()
    if browser is None:
        if REQUIRED:
            pytest.fail("no chromium on this machine, and MLAQC_REQUIRE_BROWSER=1")
        pytest.skip("no chromium on this machine (Debian: apt-get install chromium)")
    out, _, _ = report
    cmd = [browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
           f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0",
           "--virtual-time-budget=5000", "--dump-dom", out.resolve().as_uri()]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=150)
    body = re.search(r"<body[^>]*>", run.stdout)
    assert body, run.stderr[-2000:]
    plots = re.search(r'data-plots="(\d+)"', body.group(0))
    drawn = re.search(r'data-rendered="(\d+)"', body.group(0))
    assert plots and drawn and int(plots.group(1)) == 9 and int(drawn.group(1)) == 9, body.group(0)
    console = [line for line in run.stderr.splitlines() if ":CONSOLE" in line]
    assert not console, console


def test_bad_requests_are_one_sentence(report, tmp_path, capsys):
    _, _, db = report
    assert main(["lot", "report", "--db", db]) == 2
    assert main(["lot", "report", "--db", db, "--out", str(tmp_path / "no" / "x.html")]) == 2
    assert main(["lot", "report", "--db", db, "--lot", "NOPE", "--out", str(tmp_path / "x.html")]) == 2
    assert not (tmp_path / "x.html").exists()
    err = capsys.readouterr().err
    assert "needs --out" in err and "does not exist" in err and "nothing is recorded for lot 'NOPE'" in err
