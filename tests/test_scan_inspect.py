"""Scanned mock-camera frames of a seeded wafer, inspected as they are recorded, find the seeded defects
at the right wafer positions."""

import json

import pytest

from drivers.scan import default_inspect_hook, run_scan
from drivers.scan_plan import load_plan

PLAN = """
[scan]
settle_s = 0.0
[[positions]]
x_mm = 10.0
y_mm = 10.0
label = "W(1,1)"
[[positions]]
x_mm = 15.0
y_mm = 10.0
label = "W(1,2)"
"""


@pytest.mark.timeout(240)
def test_scan_with_inspection_finds_the_seeded_defects_per_array(tmp_path):
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(PLAN)
    hook = default_inspect_hook()
    assert hook is not None
    camera = "mock://?wafer=2x1&defects=3&defect_types=decenter&seed=4&rpp=40"
    result = run_scan(camera, "mock://", load_plan(plan_path), tmp_path / "scan", inspect=hook)
    assert result is not None
    lines = [json.loads(x) for x in (tmp_path / "scan" / "manifest.jsonl").read_text().splitlines()]
    header, records = lines[0], [r for r in lines[1:] if r.get("type") != "header"]
    truth = header["truth"]
    assert len(records) == 2
    for rec in records:
        raw = tmp_path / "scan" / rec["files"][0]["file"]
        report = json.loads(raw.with_name(raw.name + ".inspect.json").read_text())
        found = {(d["row"], d["col"]) for d in report["defects"]}
        array = rec["truth"]["array"]  # which array the camera saw at this position, e.g. 'W(1,2)'
        assert rec["truth"]["in_view"] and array == rec["label"]
        seeded = _seeded_lenses(truth, array)
        assert seeded and found == seeded, (rec["label"], found, seeded)
        assert report["verdict"] == "FAIL"


def _seeded_lenses(truth, array):
    """U(m,n) of the defective lenses of the array `array` in the wafer's ground truth."""
    for entry in truth["arrays"]:
        if entry["name"] == array:
            return {(lens["m"], lens["n"]) for lens in entry["error_map"]["lenses"]}
    raise AssertionError(f"array {array!r} not in the ground truth {list(truth)}")
