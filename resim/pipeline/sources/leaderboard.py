"""CARLA leaderboard results / checkpoint JSON (LB 1.0, LB 2.x, Bench2Drive).

Top level: ``{"_checkpoint": {"global_record", "progress", "records": [...]},
"entry_status", "eligible", "sensors", "values", "labels"}``; the Bench2Drive
merger writes ``{"_checkpoint": {"records"}, "driving score", "success rate",
"eval num"}`` instead. A route record carries ``route_id``, ``status``,
``infractions`` (dict of lists of message strings), ``scores`` {score_route
(0-100, int or float), score_penalty (0-1, multiplicative), score_composed}
and ``meta``; LB2 adds ``num_infractions``; Bench2Drive adds
``scenario_name, weather_id, save_name, town_name``. See docs/sources.md.

The *infraction score* of an episode is ``score_penalty``: 1.0 for a clean run,
multiplied down per infraction.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from .episode import Outcome, SourceError

CLEAN_STATUSES = ("Perfect", "Completed")
LB2_ONLY_KEYS = ("min_speed_infractions", "yield_emergency_vehicle_infractions", "scenario_timeouts")
_ROUTE_NUM = re.compile(r"RouteScenario_(\d+)")


@dataclass
class RouteRecord:
    route_id: str
    status: str
    infractions: dict[str, list[str]]
    score_route: float          # route completion, % (0..100)
    score_penalty: float        # infraction score, multiplicative, 0..1 (1 = clean)
    score_composed: float       # driving score, 0..100
    index: int | None = None
    meta: dict = field(default_factory=dict)
    scenario_name: str | None = None
    save_name: str | None = None
    town_name: str | None = None
    weather_id: str | None = None

    @property
    def route_number(self) -> int | None:
        m = _ROUTE_NUM.search(self.route_id)
        return int(m.group(1)) if m else None

    def infraction_names(self) -> list[str]:
        """One entry per infraction message, named by its category (sorted by category)."""
        return [k for k in sorted(self.infractions) for _ in self.infractions[k]]

    @property
    def hazard(self) -> bool:
        """Not a clean success: failed, or any penalised infraction."""
        return self.status not in CLEAN_STATUSES or self.score_penalty < 1.0

    def outcome(self) -> Outcome:
        return Outcome(hazard=self.hazard, infraction_score=float(self.score_penalty),
                       infractions=self.infraction_names())


@dataclass
class ResultsFile:
    path: str
    variant: str                 # "lb1" | "lb2" | "b2d" | "b2d_merged"
    entry_status: str | None
    progress: tuple[int, int] | None
    records: list[RouteRecord]
    global_record: dict


def _num(v, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SourceError(where, f"expected a number, got {v!r}")
    if not math.isfinite(float(v)):
        raise SourceError(where, f"non-finite number {v!r}")
    return float(v)


def _parse_record(rec, where: str) -> RouteRecord:
    if not isinstance(rec, dict):
        raise SourceError(where, f"route record is {type(rec).__name__}, expected an object")
    for k in ("route_id", "status", "infractions", "scores"):
        if k not in rec:
            raise SourceError(where, f"route record lacks key {k!r}")
    inf = rec["infractions"]
    if not isinstance(inf, dict) or not all(isinstance(v, list) and all(isinstance(m, str) for m in v)
                                            for v in inf.values()):
        raise SourceError(where, "infractions must map category -> list of message strings")
    sc = rec["scores"]
    if not isinstance(sc, dict):
        raise SourceError(where, "scores must be an object")
    try:
        route, pen, comp = (sc[k] for k in ("score_route", "score_penalty", "score_composed"))
    except KeyError as e:
        raise SourceError(where, f"scores lacks {e}") from None
    pen = _num(pen, f"{where}.scores.score_penalty")
    if not 0.0 <= pen <= 1.0:
        raise SourceError(where, f"score_penalty {pen} outside [0, 1]")
    if "num_infractions" in rec and rec["num_infractions"] != sum(len(v) for v in inf.values()):
        raise SourceError(where, f"num_infractions {rec['num_infractions']} != number of messages "
                                 f"{sum(len(v) for v in inf.values())}")
    idx = rec.get("index")
    return RouteRecord(
        route_id=str(rec["route_id"]), status=str(rec["status"]), infractions={k: list(v) for k, v in inf.items()},
        score_route=_num(route, f"{where}.scores.score_route"), score_penalty=pen,
        score_composed=_num(comp, f"{where}.scores.score_composed"),
        index=idx if isinstance(idx, int) else None, meta=dict(rec.get("meta") or {}),
        scenario_name=rec.get("scenario_name"), save_name=rec.get("save_name"), town_name=rec.get("town_name"),
        weather_id=None if rec.get("weather_id") is None else str(rec.get("weather_id")),
    )


def parse_results(data, path: str = "<results>") -> ResultsFile:
    """Parse an already-decoded results JSON object (see module docstring)."""
    if not isinstance(data, dict) or not isinstance(data.get("_checkpoint"), dict):
        raise SourceError(path, "not a leaderboard results file (no _checkpoint object)")
    ck = data["_checkpoint"]
    recs_raw = ck.get("records", [])
    if not isinstance(recs_raw, list):
        raise SourceError(path, "_checkpoint.records must be a list")
    records = [_parse_record(r, f"{path} record {i}") for i, r in enumerate(recs_raw)]
    if "driving score" in data:
        variant = "b2d_merged"
    elif any(r.save_name is not None for r in records):
        variant = "b2d"
    elif any(k in r.infractions for r in records for k in LB2_ONLY_KEYS) or len(data.get("labels") or []) == 15:
        variant = "lb2"
    else:
        variant = "lb1"
    prog = ck.get("progress")
    progress = (int(prog[0]), int(prog[1])) if isinstance(prog, list) and len(prog) == 2 else None
    gr = ck.get("global_record") or {}
    return ResultsFile(path=path, variant=variant, entry_status=data.get("entry_status"), progress=progress,
                       records=records, global_record=gr if isinstance(gr, dict) else {})


def load_results(path: str | Path) -> ResultsFile:
    """Read and parse a results file; bad data (not there, not readable by us, not UTF-8 JSON, malformed
    records) is a ``SourceError`` naming it. Any other ``OSError`` (EIO, a stale NFS handle, a timeout) may be
    transient and propagates, as the NAVSIM and CARLA annotation reads do, so the pipeline retries it
    ``quarantine.max_attempts`` times before quarantining."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError) as e:
        raise SourceError(str(p), f"cannot read results file ({e.strerror})") from None
    except OSError as e:                     # transient: propagates, naming the file (quarantine reasons)
        if e.filename is None:
            e.filename = str(p)
        raise
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SourceError(str(p), f"malformed results JSON ({e})") from None
    return parse_results(data, str(p))


# ---- messages (for reports) ----------------------------------------------------------------
_OUTSIDE = re.compile(r"outside its route lanes for about ([\d.]+) meters \(([\d.]+)% of the completed route\)")


def outside_lanes_pct(message: str) -> float | None:
    """Percentage of the completed route driven outside the route lanes, from an LB message."""
    m = _OUTSIDE.search(message)
    return float(m.group(2)) if m else None
