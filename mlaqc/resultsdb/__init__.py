"""The results database: every inspection recorded, for lot yield, trends and defects that repeat.

An inspection (`mlaqc inspect`, `mlaqc scan --inspect`, the app) records one row per array inspected — its
identity (lot, wafer, array), verdict, config (hash and text), software version, the array-level readings
(grid pitch and rotation, assembly with sigmas, detection limits, counts by type) — and one row per flagged
lens, in one transaction: an inspection killed at any moment leaves no partial record. The store is an
embedded SQLite file by default (`default_target`), or a shared PostgreSQL server (`postgresql://...`) for
several stations. The report folders stay as they are; the database indexes what they say.

Modules: `schema` (tables, versions, migrations), `store` (opening a database, recording), `lot` (the lot
views: yield, Pareto, stacked defect map, repeating defects).
"""

from mlaqc.resultsdb.record import Identity
from mlaqc.resultsdb.store import DatabaseError, ResultsDB, default_target, open_database

__all__ = ["DatabaseError", "Identity", "ResultsDB", "default_target", "open_database"]
