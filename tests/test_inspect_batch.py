"""`mlaqc inspect` on a production batch: one calibration (--grid or --white) reused for every frame."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from mlaqc.cli import main
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene
from mlaqc.optics.sensor import expose

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SMALL_TOML = str(FIXTURES / "small_camera.toml")
SMALL = load_config(SMALL_TOML)
SEEDED = {(6, 7): dict(pitch_um=2.5, pitch_dir_deg=45.0), (15, 12): dict(decenter_um=9.0, decenter_dir_deg=200.0),
          (10, 18): dict(radius_front_rel=-0.12, radius_back_rel=-0.12)}


@pytest.fixture(scope="module")
def raws(tmp_path_factory):
    """A white image, a defective frame, a perfect frame and a truncated one (all 496 x 496 NPY)."""
    d = tmp_path_factory.mktemp("batch")
    em = ErrorMap.zeros(24, 24)
    for (m, n), kw in SEEDED.items():
        em = em.with_lens(m, n, **kw)
    perfect = Renderer(SMALL).render(WhiteScene(), rays_per_pixel=30, seed=5).photons
    np.save(d / "white.npy", expose(perfect, SMALL.sensor, seed=1))
    np.save(d / "perfect.npy", expose(perfect, SMALL.sensor, seed=2))
    bad = Renderer(SMALL, em).render(WhiteScene(), rays_per_pixel=50, seed=6).photons
    np.save(d / "defects.npy", expose(bad, SMALL.sensor, seed=3))
    (d / "truncated.npy").write_bytes((d / "perfect.npy").read_bytes()[:5000])
    return d


def test_batch_with_a_saved_grid(raws, tmp_path, capsys):
    grid = tmp_path / "grid.json"
    assert main(["calibrate", str(raws / "white.npy"), "-c", SMALL_TOML, "-o", str(grid), "-q"]) == 0
    out = tmp_path / "reports"
    frames = [raws / "defects.npy", raws / "perfect.npy", raws / "truncated.npy", raws / "perfect.npy"]
    code = main(["inspect", *map(str, frames), "--grid", str(grid), "-c", SMALL_TOML, "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2  # one frame could not be read; the others were still inspected
    assert "[3/4]" in err and "truncated" in err and "Traceback" not in err
    rows = list(csv.DictReader((out / "batch.csv").open()))
    assert [r["verdict"] for r in rows] == ["FAIL", "PASS", "ERROR", "PASS"]
    assert rows[2]["error"] and not rows[2]["report"]
    assert {Path(r["report"]).name for r in rows if r["report"]} == {"defects", "perfect", "perfect-2"}
    rep = json.loads((out / "defects" / "report.json").read_text())
    assert {(d["row"], d["col"]) for d in rep["defects"]} == set(SEEDED)
    assert not (out / "truncated").exists()


def test_batch_with_a_white_image_exit_1_on_fail(raws, tmp_path):
    out = tmp_path / "reports"
    code = main(["inspect", str(raws / "perfect.npy"), str(raws / "defects.npy"), "--white", str(raws / "white.npy"),
                 "-c", SMALL_TOML, "-o", str(out), "-q"])
    assert code == 1
    assert [r["verdict"] for r in csv.DictReader((out / "batch.csv").open())] == ["PASS", "FAIL"]


def test_grid_from_another_camera_is_refused(raws, tmp_path, capsys):
    grid = tmp_path / "grid.json"
    assert main(["calibrate", str(raws / "white.npy"), "-c", SMALL_TOML, "-o", str(grid), "-q"]) == 0
    out = tmp_path / "reports"
    code = main(["inspect", str(raws / "perfect.npy"), "--grid", str(grid), "-o", str(out), "-q"])  # Table 1 config
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "grid file" in err and "102x102" in err
    assert not out.exists()
    assert main(["inspect", str(raws / "perfect.npy"), "--grid", str(tmp_path / "none.json"), "-c", SMALL_TOML,
                 "-o", str(out), "-q"]) == 2
    assert not out.exists()


def test_white_and_grid_are_exclusive(raws, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["inspect", str(raws / "perfect.npy"), "--grid", "g.json", "--white", "w.npy", "-o", str(tmp_path / "r")])
    assert exc.value.code == 2
