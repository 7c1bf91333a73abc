"""The quarantine table: items the pipeline could not use (or used with a caveat), with the stage, the reason
and the attempts.

Bad input (a corrupt, truncated, zero-byte, too-short or too-low-resolution video, a log with missing
frames, NaN annotations) never stops the job: the reader raises ``SourceError(item, reason)``, the
stage records a row here and the unit (or just the affected clip window) is skipped. Anything else is
a bug in our code and propagates, failing the job loudly.

Rows are written per unit, ``quarantine/<unit_id>.parquet``, atomically and *before* the unit's commit
marker, so a rerun never loses or duplicates them. Columns (``QUARANTINE_COLUMNS``):

* ``item``      the item (``<item_id>`` for a whole unit, ``<item_id>#f<start>`` for one clip window)
* ``unit_id``   the work unit
* ``source``    origin (``opendv``, ``synthetic/carla``, ...)
* ``stage``     cut | label | balance | encode | write
* ``status``    ``quarantined`` (the whole unit is skipped) or ``dropped`` (this window only; the
                unit's other clips were written — or, for an enumerate row, this file only, e.g. an
                unreadable CARLA results file; the source's units still ran) or ``warning`` (the unit was
                used, and its clips written, but the reader repaired or could not fill something: one row
                per ``Episode.warnings`` entry, e.g. a NaN compass interpolated, a route without outcome)
* ``reason``    why, in words (the reader's ``SourceError.reason`` or our check's message), prefixed
                with the file/frame the reader named when that is not the item itself
* ``attempts``  how many times the item was tried (I/O errors are retried; reruns with
                ``quarantine.retry_quarantined`` count up)
"""
from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from resim.shards.fsio import atomic_write_bytes

QUARANTINE_COLUMNS = ("item", "unit_id", "source", "stage", "status", "reason", "attempts")
WARNING = "warning"          # a row that did not keep anything out of the dataset
# how the label stage's curation reasons start (stats.json counts the windows they dropped by these)
SPANS_CUT = "spans a scene cut"
STANDS_STILL = "stands still"


def row(state: dict, stage: str, reason: str, *, item: str | None = None, status: str = "quarantined",
        attempts: int | None = None) -> dict:
    return {"item": item or state["item_id"], "unit_id": state["unit_id"], "source": state["origin"],
            "stage": stage, "status": status, "reason": str(reason),
            "attempts": int(attempts if attempts is not None else state.get("attempts", 1))}


def quarantine_unit(state: dict, stage: str, reason: str, attempts: int | None = None) -> None:
    """Mark the whole unit bad; later stages pass it through untouched, the writer records it."""
    state["status"] = "quarantined"
    state["quarantine"].append(row(state, stage, reason, attempts=attempts))


def drop_window(state: dict, stage: str, start: int, reason: str) -> None:
    state["quarantine"].append(row(state, stage, reason, item=f"{state['item_id']}#f{start:07d}", status="dropped"))


def warn(state: dict, stage: str, reason: str) -> None:
    """Record a caveat on a unit that is still used (status ``warning``); its clips are written as usual."""
    state["quarantine"].append(row(state, stage, reason, status=WARNING))


def problems(rows: list[dict]) -> list[dict]:
    """The rows that kept something out of the dataset (``quarantined`` / ``dropped``), warnings left out."""
    return [r for r in rows if r["status"] != WARNING]


def table_path(root: str | Path, unit_id: str) -> Path:
    return Path(root) / "quarantine" / f"{unit_id}.parquet"


def write_rows(root: str | Path, unit_id: str, rows: list[dict]) -> Path | None:
    """Write (or, with no rows, remove) the unit's quarantine file atomically."""
    path = table_path(root, unit_id)
    if not rows:
        path.unlink(missing_ok=True)
        return None
    cols = {c: [r[c] for r in rows] for c in QUARANTINE_COLUMNS}
    table = pa.table({**cols, "attempts": pa.array(cols["attempts"], pa.int32())})
    buf = pa.BufferOutputStream()
    pq.write_table(table, buf)
    atomic_write_bytes(path, buf.getvalue().to_pybytes())     # a full disk leaves no temporary file behind
    return path


def read_table(root: str | Path) -> list[dict]:
    """All quarantine rows of a dataset folder (sorted by unit, then item)."""
    d = Path(root) / "quarantine"
    rows: list[dict] = []
    for p in sorted(d.glob("*.parquet")) if d.is_dir() else []:
        rows.extend(pq.read_table(p).to_pylist())
    return sorted(rows, key=lambda r: (r["unit_id"], r["item"], r["stage"]))
