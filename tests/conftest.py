"""Test-wide settings: Qt offscreen, and helpers shared across test modules."""

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.pop("MLAQC_SCHEDULER", None)  # a developer's cluster must not take over the tests that inspect locally
