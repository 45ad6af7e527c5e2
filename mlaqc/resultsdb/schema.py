"""Tables of the results database, per schema version, and the migrations between versions.

Written once for both dialects: `{id}` is the auto-numbered key, `{real}` a double, `{text}` text. A
database records its schema version in `schema_info`; opening one brings an older schema up to
SCHEMA_VERSION (each step in its own transaction) and refuses a newer one (written by a newer mlaqc).
"""

from __future__ import annotations

SCHEMA_VERSION = 1

DIALECT_TYPES = {
    "sqlite": {"id": "INTEGER PRIMARY KEY AUTOINCREMENT", "real": "REAL", "text": "TEXT"},
    "postgresql": {"id": "BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY", "real": "DOUBLE PRECISION",
                   "text": "TEXT"},
}

# version -> the statements that bring the previous version to it (version 1 from an empty database)
MIGRATIONS: dict[int, tuple[str, ...]] = {
    1: (
        "CREATE TABLE schema_info (version INTEGER NOT NULL)",
        "CREATE TABLE configs (hash {text} PRIMARY KEY, body {text} NOT NULL)",
        """CREATE TABLE inspections (
            id {id},
            run_key {text} NOT NULL UNIQUE,
            recorded_utc {text} NOT NULL,
            inspected_utc {text},
            lot {text}, wafer {text}, array_id {text}, position {text},
            station {text}, operator {text},
            source {text} NOT NULL, report_dir {text},
            verdict {text} NOT NULL,
            software_version {text} NOT NULL,
            config_hash {text} REFERENCES configs(hash),
            packing {text}, lens_rows INTEGER, lens_cols INTEGER,
            found INTEGER, missing INTEGER, flagged INTEGER, out_of_tolerance INTEGER,
            pitch_x_px {real}, pitch_y_px {real}, rotation_deg {real}, grid_rms_px {real},
            distance_um {real}, distance_sigma_um {real},
            mla_rotation_deg {real}, mla_rotation_sigma_deg {real},
            tilt_x_deg {real}, tilt_x_sigma_deg {real}, tilt_y_deg {real}, tilt_y_sigma_deg {real},
            shift_x_um {real}, shift_x_sigma_um {real}, shift_y_um {real}, shift_y_sigma_um {real},
            limit_pitch_um {real}, limit_decenter_um {real}, limit_radius_rel {real},
            counts_json {text}
        )""",
        "CREATE INDEX inspections_lot ON inspections (lot, wafer, recorded_utc)",
        "CREATE INDEX inspections_array ON inspections (array_id, recorded_utc)",
        """CREATE TABLE flagged_lenses (
            inspection_id BIGINT NOT NULL REFERENCES inspections(id) ON DELETE CASCADE,
            m INTEGER NOT NULL, n INTEGER NOT NULL,
            error_type {text} NOT NULL, magnitude {real}, unit {text}, direction_deg {real}, score {real},
            within_tolerance INTEGER NOT NULL
        )""",
        "CREATE INDEX flagged_lenses_inspection ON flagged_lenses (inspection_id)",
        "CREATE INDEX flagged_lenses_lens ON flagged_lenses (m, n, error_type)",
        "INSERT INTO schema_info (version) VALUES (1)",
    ),
}


def statements(version: int, dialect: str) -> list[str]:
    """The migration to `version` in a dialect's spelling."""
    types = DIALECT_TYPES[dialect]
    return [s.format(**types) for s in MIGRATIONS[version]]
