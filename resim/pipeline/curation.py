"""The curation report of a run: what went in, what each step kept out and why, and pictures of it.

ReSim trains on 1,700 h of uploads; a user who filters them needs to see that each filter removes what it
should and nothing else. Per run (the whole dataset, from the commit markers, the quarantine table and the
dedup table, so a resumed run reports on everything):

* ``funnel`` (``stats.json`` ``curation``): hours of source video, hours after the readers' discards (OpenDV's
  intros and outros), units quarantined whole, candidate windows, windows dropped per reason (scene
  cut, standing still, each quality column, NaN poses), clips written, clips left out as near-duplicates, and
  the hours the written clips cover;
* ``contact_sheet`` (``OUT/curation.png``): up to ``per_reason`` dropped examples per reason, each the first
  and last frame of the window (a cut shows two shots, a stop two equal frames), decoded again from the
  source; near-duplicates beside the clip they copy; units quarantined whole as text (their file could not
  be read).
"""
from __future__ import annotations

import logging
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from resim.media.frames import cover_size, rate_step
from resim.pipeline import quarantine
from resim.pipeline.clip_quality import LOW_QUALITY
from resim.pipeline.sources.episode import SourceError
from resim.pipeline.stages.cut import CutStage
from resim.pipeline.units import clip_of
from resim.shards.duplicates import duplicates_path
from resim.shards.manifest import read_manifest

log = logging.getLogger("resim.pipeline")

NAN_POSES = "NaN/inf poses"      # the label stage's reason for a window with broken poses
THUMB_H = 72                     # px, height of a contact-sheet frame


def reason_group(row: dict) -> str:
    """The curation step behind a quarantine row: ``scene cut``, ``standing still``, ``low quality:
    COLUMN``, ``NaN poses``, ``other drop`` for windows; ``unusable item`` for units quarantined whole."""
    if row["status"] == "quarantined":
        return "unusable item"
    r = row["reason"]
    if r.startswith(quarantine.SPANS_CUT):
        return "scene cut"
    if r.startswith(quarantine.STANDS_STILL):
        return "standing still"
    if r.startswith(LOW_QUALITY):
        return f"{LOW_QUALITY}: {r[len(LOW_QUALITY) + 2:].split()[0]}"
    if r.startswith(NAN_POSES):
        return "NaN poses"
    return "other drop"


def funnel(markers: list[dict], rows: list[dict], num_duplicates: int, clip_s: float) -> dict:
    """The numbers of the curation report (``markers``: the dataset's commit markers; ``rows``: its
    quarantine rows that kept something out; ``clip_s``: one clip's duration)."""
    cur = [m.get("curation") or {} for m in markers]
    ok = [m for m in markers if m["status"] == "ok"]
    written = sum((m.get("written") or {}).get("num_samples", 0) for m in ok)
    dropped = Counter(reason_group(r) for r in rows if r["status"] == "dropped")
    h = 3600.0
    return {
        "hours_in": round(sum(c.get("source_s", 0.0) for c in cur) / h, 4),
        "hours_after_discards": round(sum(c.get("used_s", 0.0) for c in cur) / h, 4),
        "units": len(markers),
        "units_quarantined": len(markers) - len(ok),
        "candidate_windows": sum(c.get("windows", 0) for c in cur),
        "windows_dropped": dict(sorted(dropped.items(), key=lambda kv: -kv[1])),
        "clips_written": written,
        "clips_left_out_as_duplicates": num_duplicates,
        "clips_for_training": written - num_duplicates,
        "hours_covered_by_clips": round(sum(c.get("covered_s", 0.0) for c in cur) / h, 4),
        "clip_s": clip_s,
        "note": "candidate windows lie on the balance stage's fine grid and overlap; the balance stage keeps "
                "every turning one and the coarse-grid ones elsewhere, so candidates - drops > clips written",
    }


def format_funnel(f: dict) -> str:
    drops = ", ".join(f"{v} {k}" for k, v in f["windows_dropped"].items()) or "none"
    return (f"curation          {f['hours_in'] * 60:.1f} min in, {f['hours_after_discards'] * 60:.1f} after discards, "
            f"{f['units_quarantined']} unit(s) unusable; windows dropped: {drops}; "
            f"{f['clips_for_training']} clip(s) for training ({f['clips_left_out_as_duplicates']} duplicate(s) left "
            f"out) covering {f['hours_covered_by_clips'] * 60:.1f} min")


class _Frames:
    """Re-open a unit's source and decode single frames at thumbnail size (readers built once per spec)."""

    def __init__(self, cfg, states: list[dict]):
        self.cut = CutStage(cfg)
        self.by_unit = {s["unit_id"]: s for s in states}

    def pair(self, unit_id: str, start: int, num_frames: int) -> np.ndarray | None:
        """First and last frame of the window starting at clip frame ``start``, side by side, or None."""
        st = self.by_unit.get(unit_id)
        if st is None:
            return None
        try:
            ep = self.cut.open(st)
            step = rate_step(ep.fps_hz, clip_of(st).fps_hz) or 1
            h, w = ep.frame_size_hw
            hw = cover_size((h, w), (THUMB_H, max(1, round(THUMB_H * w / h))))
            tiles = []
            for i in (start * step, min((start + num_frames - 1) * step, ep.num_frames - 1)):
                tiles.append(next(iter(ep.frames(i, i + 1, size_hw=hw))))
        except (SourceError, OSError, IndexError, StopIteration) as e:
            # the source changed or went away since the run (bad input, not our bug): a missing tile, not a failed run
            log.info("curation sheet: no frames for %s@%d (%s)", unit_id, start, e)
            return None
        sep = np.full((hw[0], 2, 3), 255, np.uint8)
        return np.concatenate([tiles[0], sep, tiles[1]], axis=1)


def contact_sheet(out: str | Path, cfg, states: list[dict], rows: list[dict], per_reason: int = 6) -> Path:
    """``OUT/curation.png``: one row of examples per reason (see the module docstring)."""
    # matplotlib is slow to import: only for the contact sheet
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    N = cfg.clip.num_frames
    groups: dict[str, list] = defaultdict(list)
    for r in rows:
        groups[reason_group(r)].append(r)
    frames = _Frames(cfg, states)
    lines: list[tuple[str, int, list[tuple[np.ndarray | None, str]]]] = []
    for g, rs in sorted(groups.items(), key=lambda kv: (kv[0] == "unusable item", kv[0])):
        ex = []
        for r in _spread(rs, per_reason):
            if g == "unusable item":
                ex.append((None, f"{r['item']}\n[{r['stage']}] {r['reason'][:60]}"))
                continue
            start = int(r["item"].rsplit("#f", 1)[1])
            ex.append((frames.pair(r["unit_id"], start, N), f"{r['item'].rsplit('#f', 1)[0][-28:]} @{start}\n"
                                                           f"{r['reason'][:60]}"))
        lines.append((g, len(rs), ex))
    man = read_manifest(out).to_pydict()
    unit_of = {s["item_id"]: s["unit_id"] for s in states}
    if any(man["stopped"]):       # labels.still.policy tag: kept, but a user should see what was tagged
        tagged = [(i, st) for i, st, stop in zip(man["item_id"], man["start_frame"], man["stopped"]) if stop]
        ex = [(frames.pair(unit_of.get(i, ""), int(st), N), f"{i[-28:]} @{st}") for i, st in _spread(tagged, per_reason)]
        lines.append(("stopped\n(tagged, kept)", len(tagged), ex))
    duplicates = duplicate_pairs(out, man)
    if duplicates:
        ex = []
        for d in _spread(duplicates, per_reason):
            a = frames.pair(unit_of.get(d["item_id"], ""), int(d["start_frame"]), N)
            b = frames.pair(unit_of.get(d["of_item_id"], ""), int(d["of_start_frame"]), N)
            pic = None if a is None or b is None else np.concatenate(
                [a[:, : a.shape[1] // 2], np.full((a.shape[0], 6, 3), 255, np.uint8), b[:, : b.shape[1] // 2]], axis=1)
            ex.append((pic, f"{d['item_id'][-20:]}@{d['start_frame']} = {d['of_item_id'][-20:]}@{d['of_start_frame']}"
                            f"\n{d['distance_bits']} bits apart (copy | kept)"))
        lines.append(("near-duplicate", len(duplicates), ex))
    p = Path(out) / "curation.png"
    if not lines:
        fig, ax = plt.subplots(figsize=(6, 1.2))
        ax.axis("off")
        ax.text(0.5, 0.5, "nothing was dropped: no scene cut, stop, quality drop, duplicate or unusable item",
                ha="center", va="center", fontsize=9)
    else:
        cols = max(len(ex) for _, _, ex in lines)
        fig, axes = plt.subplots(len(lines), cols, figsize=(2.6 * cols, 1.55 * len(lines)), squeeze=False)
        for i, (g, n, ex) in enumerate(lines):
            for j in range(cols):
                ax = axes[i, j]
                ax.set_xticks([])
                ax.set_yticks([])
                if j >= len(ex):
                    ax.axis("off")
                    continue
                pic, caption = ex[j]
                if pic is None:
                    ax.text(0.5, 0.5, caption, ha="center", va="center", fontsize=5, wrap=True)
                else:
                    ax.imshow(pic)
                    ax.set_xlabel(caption, fontsize=5)
            axes[i, 0].set_ylabel(f"{g}\n({n})", fontsize=7)
        fig.suptitle(f"curation: dropped examples per reason — {Path(out).name}", fontsize=9)
    fig.tight_layout()
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p


def duplicate_pairs(out: str | Path, man: dict) -> list[dict]:
    """The dedup table joined with the manifest (``man``, as a dict of columns): ``item_id``/``start_frame`` of each
    copy and of the clip kept."""
    p = duplicates_path(out)
    if not p.is_file():
        return []
    where = {k: (i, s) for k, i, s in zip(man["key"], man["item_id"], man["start_frame"])}
    pairs = []
    for d in pq.read_table(p).to_pylist():
        if d["key"] in where and d["duplicate_of"] in where:
            (i, s), (oi, os_) = where[d["key"]], where[d["duplicate_of"]]
            pairs.append({"item_id": i, "start_frame": s, "of_item_id": oi, "of_start_frame": os_,
                          "distance_bits": d["distance_bits"]})
    return pairs


def _spread(items: list, n: int) -> list:
    """``n`` items spread over ``items`` (first, last and between), so one long video does not fill a row."""
    if len(items) <= n:
        return list(items)
    idx = np.linspace(0, len(items) - 1, n).round().astype(int)
    return [items[i] for i in idx]
