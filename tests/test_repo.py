"""The README's commands are the ones CI runs, and the layering rules of DESIGN.md hold."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    cmd = "python3 -m pip install -e '.[test]' && python3 -m pytest -q -n auto --dist loadfile"
    lines = [line.strip() for text in (readme, ci) for line in text.splitlines() if "pytest -q" in line
             and "pip install" in line]
    assert lines and all(line == cmd for line in lines), lines  # the whole command, the same in both
    assert cmd in readme and cmd in ci


def test_core_never_imports_qt_or_hardware_and_drivers_never_import_gui():
    bad = []
    pattern = re.compile(r"^\s*(from|import)\s+(gui|drivers|PySide6|serial|linuxpy)\b", re.M)
    for path in (ROOT / "mlaqc").rglob("*.py"):
        if path.name == "cli.py":
            continue
        bad += [f"{path}: {m.group(0).strip()}" for m in pattern.finditer(path.read_text())]
    gui_pattern = re.compile(r"^\s*(from|import)\s+(gui|PySide6)\b", re.M)
    for path in (ROOT / "drivers").rglob("*.py"):
        bad += [f"{path}: {m.group(0).strip()}" for m in gui_pattern.finditer(path.read_text())]
    assert not bad, bad


def test_core_packages_import_only_downwards():
    """optics sits below models and inspection, report below commands; the two cross-links are the
    documented ones (docs/architecture.md): simulate writes through raw_write, signatures measure with metrics
    (and the assembly model with the projection fit)."""
    allowed = {
        "optics": {"optics", "inspection.raw_write"},
        "models": {"optics", "models", "inspection.metrics", "inspection.metrics_kernels", "inspection.subimages",
                   "inspection.calibrate", "inspection.projection"},
        "inspection": {"optics", "models", "inspection"},
        "report": {"inspection", "report", "optics.lattice"},  # the lattice: where each lens' cell is drawn
    }
    pattern = re.compile(r"^\s*(?:from|import)\s+mlaqc\.(\w+)(?:\.(\w+))?", re.M)
    bad = []
    for package, ok in allowed.items():
        for path in (ROOT / "mlaqc" / package).glob("*.py"):
            for m in pattern.finditer(path.read_text()):
                target, sub = m.group(1), m.group(2)
                if target in ("errors", "atomic", "progress", "lazy", "cluster", "parallel", "compiled", "numba_inliner", "numba_liveness", "numba_ssa", "numba_patch",
                              "numba_typing_memo", "numba_callee_ir", "user_cache"):
                    continue
                if target not in ok and f"{target}.{sub}" not in ok:
                    bad.append(f"{path.relative_to(ROOT)}: mlaqc.{target}.{sub}")
    assert not bad, bad
