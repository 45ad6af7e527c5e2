"""Cameras and stages: protocol codecs, transports, real drivers, mocks and protocol simulators.

Imports `mlaqc` (core), never `gui`.
"""
