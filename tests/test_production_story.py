"""The mock wafer's production story (drivers.wafer.Production): a master defect most replicas carry and a
process drift, scanned, inspected and recorded as a station would; the lot views name the master's defect
and nothing else (the smallest form of bench/production.py)."""

import json
import sys
from pathlib import Path

import pytest

from drivers.camera.mock import MockCamera
from drivers.wafer import Production, Wafer
from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.optics.config import load_config
from mlaqc.resultsdb import lot as views
from mlaqc.resultsdb.store import open_database

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
from production import raster_plan  # noqa: E402

SMALL = load_config(str(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml"))


def test_the_story_seeds_the_master_share_and_the_drift():
    story = Production(master_lens=(5, 7), master_share=0.8, drift_from=30, drift_um=1.5, first_index=26)
    wafer = Wafer(SMALL, cols=5, rows=5, defects=0, seed=2, production=story)
    truth = wafer.truth()["arrays"]
    carried = [a for a in truth if a["master"]]
    assert 0.55 <= len(carried) / 25 <= 1.0
    for a in carried:  # the master's error on its lens, nowhere else
        lens = a["error_map"]["lenses"]
        assert [(d["m"], d["n"], d["pitch_um"], d["pitch_dir_deg"]) for d in lens] == [(5, 7, 1.5, 30.0)]
    # production indexes 26..50 on this wafer; the drift from 30: 0 before, 1.5 µm more with every array after
    assert [a["index"] for a in truth] == list(range(26, 51))
    assert [a["drift_um"] for a in truth][:6] == [0.0, 0.0, 0.0, 0.0, 1.5, 3.0]
    assert wafer.array(1, 6 - 1).errors.globals["mla_sensor_distance_um"] == 1.5
    share = sum(Production(master_lens=(1, 1), master_share=0.3).carries_master(7, m, n)
                for m in range(1, 41) for n in range(1, 41)) / 1600
    assert abs(share - 0.3) < 0.04  # the seeded draw has the share asked for


@pytest.mark.parametrize("query, words", [("master=5", "must name a lens"), ("master=30,7", "is not on the"),
                                          ("master=5,7&master_type=tilt", "must be one of"),
                                          ("master=5,7&master_share=1.5", "must lie in 0..1")])
def test_a_bad_story_is_one_sentence(query, words):
    with pytest.raises(InputError, match=words):
        MockCamera.from_url(f"mock://?{query}")


@pytest.mark.timeout(300)
def test_a_scanned_lot_names_the_masters_defect_and_nothing_else(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(raster_plan(3, 5.0))
    db = str(tmp_path / "lot.sqlite")
    seeded = 0
    for w in (1, 2):
        url = (f"mock://?wafer=3x3&pitch_mm=5&defects=2&seed={w}&rpp=40&master=5,7&master_size=1.5&master_dir=30"
               f"&master_share=0.9&first_index={9 * (w - 1) + 1}")
        out = tmp_path / f"w{w}"
        assert main(["scan", "--camera", url, "--stage", "mock://", "--plan", str(plan), "--out", str(out),
                     "--inspect", "--db", db, "--lot", "L1", "--wafer", f"W{w}", "--quiet"]) == 1
        header = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
        seeded += sum(a["master"] for a in header["truth"]["arrays"])
    with open_database(db, create=False) as store:
        repeats = views.repeating_defects(store, "L1")
        assert [w["arrays"] for w in views.yield_table(store, "L1")] == [9, 9]
    assert [(d.m, d.n) for d in repeats] == [(5, 7)]
    d = repeats[0]
    assert d.error_type in ("pitch", "position") and abs(d.direction_deg - 30) < 10
    assert d.of_arrays == 18 and abs(d.arrays - seeded) <= 1
