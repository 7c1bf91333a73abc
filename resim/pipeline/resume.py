"""Resumability: one commit marker per work unit, written last.

``commits/<unit_id>.json`` holds the unit's summary (source, status, clips written, shard names,
balance counts, per-stage seconds, quarantine and warning row counts). It is written atomically after the
unit's shards (with their manifests and indexes) and its quarantine rows, so its presence means the unit is
complete.
The driver reads the markers before starting: committed units are skipped (quarantined ones too,
unless ``quarantine.retry_quarantined``); everything else is redone from scratch. Stats and the report
are computed from all markers, so a resumed run reports on the whole dataset.
"""
from __future__ import annotations

import json
from pathlib import Path

from resim.pipeline import quarantine
from resim.shards.fsio import atomic_write_bytes

SUMMARY_KEYS = ("unit_id", "kind", "origin", "item_id", "status", "attempts", "balance", "timings_s", "written",
                "cuts", "curation")


def marker_path(out: str | Path, unit_id: str) -> Path:
    return Path(out) / "commits" / f"{unit_id}.json"


def summary(state: dict) -> dict:
    s = {k: state.get(k) for k in SUMMARY_KEYS}
    s["num_quarantined"] = len(quarantine.problems(state["quarantine"]))   # quarantined + dropped rows
    s["num_warnings"] = len(state["quarantine"]) - s["num_quarantined"]
    s["selected"] = [{k: w.get(k) for k in ("start", "command", "command_source", "is_turning", "stopped")}
                     for w in state.get("selected") or []] if state["status"] == "ok" else []
    s["commands_agree"] = [w.get("command_flow") == w.get("command_trajectory")
                           for w in state.get("selected") or [] if w.get("command_trajectory") is not None] \
        if state["status"] == "ok" else []
    return s


def write_marker(out: str | Path, state: dict) -> Path:
    path = marker_path(out, state["unit_id"])
    atomic_write_bytes(path, json.dumps(summary(state), sort_keys=True).encode())   # no temp file left on failure
    return path


def read_markers(out: str | Path) -> dict[str, dict]:
    d = Path(out) / "commits"
    markers = {}
    for p in sorted(d.glob("*.json")) if d.is_dir() else []:
        with open(p) as fh:
            markers[p.stem] = json.load(fh)
    return markers


def plan(states: list[dict], markers: dict[str, dict], retry_quarantined: bool) -> tuple[list[dict], list[str]]:
    """Split enumerated units into (to run, skipped ids). Retried quarantined units count attempts up."""
    todo, skipped = [], []
    for st in states:
        m = markers.get(st["unit_id"])
        if m is None:
            todo.append(st)
        elif m["status"] == "quarantined" and retry_quarantined:
            st["attempts"] = int(m.get("attempts", 1)) + 1
            todo.append(st)
        else:
            skipped.append(st["unit_id"])
    return todo, skipped
