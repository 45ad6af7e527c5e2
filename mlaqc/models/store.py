"""Where built models are kept: the package's own data (Table 1, shipped), else the user's disk cache,
else built now and cached (best effort: a read-only home still gets a working model). One lookup for
every model that is slow to build (reference, signature tables, pitch/decenter split, through-focus
model curves), so each behaves the same on a damaged or unwritable cache.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from mlaqc.atomic import write_json_atomic
from mlaqc.user_cache import cache_dir

PACKAGE_DATA = Path(__file__).resolve().parents[1] / "data"
T = TypeVar("T")
# what reading a damaged entry raises (a truncated or garbled .npz: BadZipFile, EOFError, zlib.error)
_DAMAGED = (OSError, ValueError, KeyError, TypeError, IndexError, EOFError, zipfile.BadZipFile, zlib.error)


def stored(name: str, build: Callable[[], T], read: Callable[[Path], T], write: Callable[[T, Path], None], *,
           rebuild: bool = False, build_if_missing: bool = True) -> T:
    """The model in file `name`: read from the package's data, else the cache (an entry that cannot be
    read is rebuilt), else `build()` and written to the cache; `rebuild` builds it whatever is stored.
    FileNotFoundError when it is stored nowhere and `build_if_missing` is false."""
    for folder in (() if rebuild else (PACKAGE_DATA, cache_dir())):
        path = folder / name
        if path.is_file():
            try:
                return read(path)
            except _DAMAGED:
                pass  # a damaged entry is built again (and replaced, when it is the cache's)
    if not build_if_missing:
        raise FileNotFoundError(f"no {name} in {PACKAGE_DATA} or {cache_dir()}")
    model = build()
    try:
        cache_dir().mkdir(parents=True, exist_ok=True)
        write(model, cache_dir() / name)
    except OSError:
        pass
    return model


def stored_json(name: str, build: Callable[[], T], to_dict: Callable[[T], Any], from_dict: Callable[[Any], T],
                **kwargs) -> T:
    """`stored` for a model kept as JSON (written atomically)."""
    return stored(name, build, lambda p: from_dict(json.loads(p.read_text())),
                  lambda m, p: write_json_atomic(p, to_dict(m)), **kwargs)
