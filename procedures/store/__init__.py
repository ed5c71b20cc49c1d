"""The run store: runs, their samples, streams, events and leases in one database, and the run states.

What it offers:

- ``RunStore``: one SQLite file in the runs folder (the default) or a PostgreSQL server shared by many
  cells (``store_location``, ``STORE_ENV``); every sample committed before the next motion, leases for
  exclusive runs, compare-and-set state changes;
- typed samples in and out: ``Sample`` and its blocks (``SolvedPose`` with its ``PoseQuality``,
  ``CorrectedPose``, ``Reference``, ``Commanded``; ``Pose``, ``as_pose``), a move's ``StoredStream``, and the
  run-level record of each session's test conditions (``SessionConditions``); ``Lease``;
- ``RunState`` (the states of a run, an Enum) and ``RESUMABLE_STATES``;
- the schema's versioned migrations (``MIGRATIONS``, ``LATEST``), for SQLite and PostgreSQL alike;
- its errors (``StoreError``, ``DuplicateStep``; store trouble: ``StoreTrouble`` (``StoreFull``, ``StoreLocked``: a
  run pauses on it), ``StoreDamaged``, ``StoreReadOnly``), kinds of ``procedures.station.RunError``.

It stands on ``procedures.station`` only: the kinds, the engine, the report and the faces read and write
runs through it.
"""

from procedures.store._db import (
    SQLITE_FILE,
    STORE_ENV,
    DuplicateStep,
    StoreDamaged,
    StoreError,
    StoreFull,
    StoreLocked,
    StoreReadOnly,
    StoreTrouble,
    store_location,
)
from procedures.store._run_state import RESUMABLE_STATES, RunState
from procedures.store._samples import (
    Commanded,
    CorrectedPose,
    ExposureEvidence,
    FrameExposure,
    Pose,
    PoseQuality,
    Reference,
    Sample,
    SolvedPose,
    as_pose,
)
from procedures.store._schema import LATEST, MIGRATIONS, Migration
from procedures.store._sessions import SessionConditions
from procedures.store._store import Lease, RunStore, StoredStream

__all__ = [
    "LATEST", "MIGRATIONS", "RESUMABLE_STATES", "SQLITE_FILE", "STORE_ENV", "Commanded", "CorrectedPose",
    "DuplicateStep", "ExposureEvidence", "FrameExposure", "Lease", "Migration", "Pose", "PoseQuality", "Reference",
    "RunState", "RunStore", "Sample",
    "SessionConditions", "SolvedPose", "StoreDamaged", "StoreError", "StoreFull", "StoreLocked", "StoreReadOnly",
    "StoreTrouble", "StoredStream", "as_pose", "store_location",
]
