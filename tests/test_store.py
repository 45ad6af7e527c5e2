"""The model store: package data first, then the cache; a damaged cache entry is rebuilt and replaced,
an unwritable cache still gives a model, and nothing is built when building is not allowed."""

from __future__ import annotations

import json

import pytest

from mlaqc.models import store


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MLAQC_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(store, "PACKAGE_DATA", tmp_path / "package")
    (tmp_path / "package").mkdir()
    return tmp_path


def lookup(name: str, built: list, **kwargs):
    def build():
        built.append(name)
        return {"value": len(built)}
    return store.stored_json(name, build, dict, dict, **kwargs)


def test_built_once_then_read_from_the_cache(cache):
    built = []
    assert lookup("m_1.json", built) == {"value": 1}
    assert lookup("m_1.json", built) == {"value": 1} and built == ["m_1.json"]
    assert json.loads((cache / "cache" / "m_1.json").read_text()) == {"value": 1}


def test_package_data_wins_over_the_cache_and_rebuild_ignores_both(cache):
    (cache / "package" / "m_2.json").write_text('{"value": 42}')
    built = []
    assert lookup("m_2.json", built) == {"value": 42} and built == []
    assert lookup("m_2.json", built, rebuild=True) == {"value": 1}


def test_a_damaged_cache_entry_is_rebuilt_and_replaced(cache):
    (cache / "cache").mkdir()
    (cache / "cache" / "m_3.json").write_text('{"value": ')  # truncated
    built = []
    assert lookup("m_3.json", built) == {"value": 1}
    assert json.loads((cache / "cache" / "m_3.json").read_text()) == {"value": 1}


def test_an_unwritable_cache_still_gives_the_model(cache):
    (cache / "cache").write_text("a file where the cache folder should be")
    assert lookup("m_4.json", []) == {"value": 1}


def test_nothing_is_built_when_building_is_not_allowed(cache):
    built = []
    with pytest.raises(FileNotFoundError, match="m_5.json"):
        lookup("m_5.json", built, build_if_missing=False)
    assert built == []


def test_a_truncated_npz_entry_is_rebuilt(cache):
    """np.load on a truncated archive raises BadZipFile or EOFError: the entry is built again, not a crash."""
    import numpy as np

    (cache / "cache").mkdir()
    good = cache / "good.npz"
    np.savez_compressed(good, a=np.arange(1000.0))
    (cache / "cache" / "m_6.npz").write_bytes(good.read_bytes()[:200])

    def read(path):
        with np.load(path) as z:
            return float(z["a"].sum())

    def write(value, path):
        np.savez_compressed(path, a=np.array([value]))

    assert store.stored("m_6.npz", lambda: 7.0, read, write) == 7.0
    assert read(cache / "cache" / "m_6.npz") == 7.0
