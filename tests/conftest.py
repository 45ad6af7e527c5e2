"""Test-wide settings: Qt offscreen, and helpers shared across test modules."""

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
