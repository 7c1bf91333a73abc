"""``stats.json`` and ``report.png`` of a pipeline run, computed from the commit markers of all units.

Because every unit's marker carries its own summary (clips, commands, balance counts, seconds per
stage), a resumed run reports on the whole dataset, not just the units it redid.

stats.json keys: ``units`` (total / ok / quarantined), ``clips`` (total, by origin, commands by origin,
by command source, flow/trajectory agreement), ``turning_share`` (before and after the turn balance),
``quarantine`` (quarantined/dropped rows by stage and status, first reasons), ``warnings`` (rows of status
``warning``: units used with a caveat their reader reported, first reasons), ``stages`` (seconds, share of
time and clips per stage-second for each stage), ``this_run`` (wall time, units run/skipped, clips per
second and per core).
"""
from __future__ import annotations

import json
from collections import Counter, defaultdict
from pathlib import Path

import pyarrow.parquet as pq

from resim.pipeline import curation, quarantine
from resim.shards.duplicates import duplicates_path
from resim.shards.fsio import atomic_write_bytes
from resim.shards.schema import COMMANDS

STAGE_ORDER = ("cut", "label", "label.cuts", "balance", "encode", "encode.decode", "encode.vae", "encode.mp4",
               "encode.signature", "encode.quality", "write")


def compute_stats(out: str | Path, markers: list[dict], this_run: dict, cfg=None) -> dict:
    ok = [m for m in markers if m["status"] == "ok"]
    clips_by_origin: Counter = Counter()
    cmd_by_origin: dict[str, Counter] = defaultdict(Counter)
    by_source_kind: Counter = Counter()
    agree = []
    for m in ok:
        clips_by_origin[m["origin"]] += m["written"]["num_samples"]
        for w in m["selected"]:
            cmd_by_origin[m["origin"]][w["command"]] += 1
            by_source_kind[w["command_source"]] += 1
        agree.extend(m.get("commands_agree") or [])
    before = Counter()
    after = Counter()
    for m in ok:
        before.update(m["balance"]["before"])
        after.update(m["balance"]["after"])
    seconds: Counter = Counter()
    for m in markers:
        seconds.update(m.get("timings_s") or {})
    total_clips = sum(clips_by_origin.values())
    top = {k: v for k, v in seconds.items() if "." not in k}
    top_total = sum(top.values()) or 1.0
    stages = {k: {"seconds": round(seconds[k], 3),
                  "share": round(seconds[k] / top_total, 4) if "." not in k else None,
                  "clips_per_s": round(total_clips / seconds[k], 3) if seconds[k] > 0 else None}
              for k in STAGE_ORDER if k in seconds}
    table = quarantine.read_table(out)
    rows = quarantine.problems(table)
    warned = [r for r in table if r["status"] == quarantine.WARNING]
    dups = _duplicates(out)
    wall = float(this_run.get("wall_s", 0.0))
    run_clips = int(this_run.get("clips_written", 0))
    cpus = float(this_run.get("cpus", 1.0)) or 1.0
    stats = {
        "units": {"total": len(markers), "ok": len(ok), "quarantined": len(markers) - len(ok)},
        "clips": {
            "total": total_clips,
            "by_origin": dict(sorted(clips_by_origin.items())),
            "commands_by_origin": {o: dict(sorted(c.items())) for o, c in sorted(cmd_by_origin.items())},
            "by_command_source": dict(sorted(by_source_kind.items())),
            "flow_trajectory_agreement": round(sum(agree) / len(agree), 4) if agree else None,
        },
        "turning_share": {
            "before": round(before["turning"] / before["clips"], 4) if before["clips"] else None,
            "after": round(after["turning"] / after["clips"], 4) if after["clips"] else None,
            "clips_before": before["clips"], "clips_after": after["clips"],
            "turn_factor": cfg.balance.turn_factor if cfg is not None and cfg.balance.enabled else 1,
        },
        "quarantine": {
            "rows": len(rows),
            "units": len({r["unit_id"] for r in rows if r["status"] == "quarantined"}),
            "by_stage": dict(Counter(r["stage"] for r in rows)),
            "by_status": dict(Counter(r["status"] for r in rows)),
            "examples": [f"{r['item']} [{r['stage']}]: {r['reason']}" for r in rows[:20]],
        },
        "duplicates": dups,
        # hours in -> after discards -> windows dropped per reason -> clips (resim/pipeline/curation.py)
        "curation": curation.funnel(markers, rows, dups["clips_left_out"],
                                    cfg.clip.num_frames / cfg.clip.fps_hz if cfg is not None else None),
        # curation's cost beside the labeler's, in this dataset's runs (docs/pipeline.md: target <= 25 %)
        "curation_cost": _curation_cost(seconds, this_run),
        "standing_still": {   # labels.still: clips written with stopped: true, and windows dropped as stopped
            "clips_tagged": sum(1 for m in ok for w in m["selected"] if w.get("stopped")),
            "windows_dropped": sum(1 for r in rows if r["reason"].startswith(quarantine.STANDS_STILL)),
        },
        "scene_cuts": {       # resim/labeling/cuts.py: per unit in its commit marker, every clip across one dropped
            "cuts": sum(len(m.get("cuts") or []) for m in markers),
            "videos_with_cuts": sum(1 for m in markers if m.get("cuts")),
            "windows_dropped": sum(1 for r in rows if r["reason"].startswith(quarantine.SPANS_CUT)),
        },
        "warnings": {
            "rows": len(warned),
            "units": len({r["unit_id"] for r in warned}),
            "examples": [f"{r['item']} [{r['stage']}]: {r['reason']}" for r in warned[:20]],
        },
        "stages": stages,
        "this_run": {**this_run, "clips_per_s": round(run_clips / wall, 4) if wall > 0 else None,
                     "clips_per_s_per_core": round(run_clips / wall / cpus, 4) if wall > 0 else None},
    }
    return stats


def _curation_cost(seconds: Counter, this_run: dict) -> dict:
    """Seconds of scene-cut detection, signatures and the dedup pass, and their share of the label stage's
    own time (the label stage's total minus the cut detector's: the flow labeler and the stillness medians)."""
    cuts, sig, dedup = seconds.get("label.cuts", 0.0), seconds.get("encode.signature", 0.0), this_run.get("dedup_s", 0.0)
    qual, sheet = seconds.get("encode.quality", 0.0), this_run.get("curation_sheet_s", 0.0)
    labeling = seconds.get("label", 0.0) - cuts
    total = cuts + sig + dedup + qual     # per video-hour; the contact sheet is a fixed cost per run (a few frames)
    return {"scene_cuts_s": round(cuts, 3), "signatures_s": round(sig, 3), "dedup_s": round(dedup, 3),
            "quality_s": round(qual, 3), "contact_sheet_s": round(sheet, 3), "labeling_s": round(labeling, 3), "share_of_labeling": round(total / labeling, 4) if labeling > 0 else None}


def _duplicates(out: str | Path) -> dict:
    """``dedup/duplicates.parquet`` in numbers: clips left out, and the groups they belong to."""
    p = duplicates_path(out)
    if not p.is_file():
        return {"clips_left_out": 0, "groups": 0, "checked": False}
    t = pq.read_table(p).to_pydict()
    return {"clips_left_out": len(t["key"]), "groups": len(set(t["duplicate_of"])), "checked": True}


def write_stats(out: str | Path, stats: dict) -> Path:
    p = Path(out) / "stats.json"
    atomic_write_bytes(p, json.dumps(stats, indent=2, sort_keys=False).encode())   # no temp file left on failure
    return p


def write_report_png(out: str | Path, stats: dict) -> Path:
    """Four panels: commands by source, turning share before/after, clip counts, throughput per stage."""
    # matplotlib is slow to import: only for the report's figure
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(11, 7.5))
    cbo = stats["clips"]["commands_by_origin"]
    origins = list(cbo) or ["(none)"]
    bottom = [0] * len(origins)
    for cmd, color in zip(COMMANDS, ("tab:blue", "tab:gray", "tab:orange")):
        vals = [cbo.get(o, {}).get(cmd, 0) for o in origins]
        ax[0, 0].bar(origins, vals, bottom=bottom, label=cmd, color=color)
        bottom = [b + v for b, v in zip(bottom, vals)]
    ax[0, 0].set_title("commands by source (clips written)")
    ax[0, 0].legend(fontsize=8)
    ax[0, 0].tick_params(axis="x", labelrotation=20, labelsize=8)

    ts = stats["turning_share"]
    vals = [ts["before"] or 0.0, ts["after"] or 0.0]
    ax[0, 1].bar(["before balance", f"after ({ts['turn_factor']}x)"], vals, color=["tab:gray", "tab:green"])
    for i, v in enumerate(vals):
        ax[0, 1].text(i, v, f"{v:.1%}", ha="center", va="bottom")
    ax[0, 1].set_ylim(0, 1)
    ax[0, 1].set_title(f"turning share ({ts['clips_before']} → {ts['clips_after']} clips)")

    by_origin = stats["clips"]["by_origin"]
    names = list(by_origin) + ["quarantined units"]
    ax[1, 0].bar(names, list(by_origin.values()) + [stats["units"]["quarantined"]],
                 color=["tab:blue"] * len(by_origin) + ["tab:red"])
    ax[1, 0].set_title(f"clips written: {stats['clips']['total']}  (units: {stats['units']['total']})")
    ax[1, 0].tick_params(axis="x", labelrotation=20, labelsize=8)

    st = stats["stages"]
    names = [k for k in st if st[k]["clips_per_s"]]
    ax[1, 1].barh(names, [st[k]["clips_per_s"] for k in names], color="tab:purple")
    ax[1, 1].set_xscale("log")
    ax[1, 1].set_title("throughput per stage (clips per stage-second, one worker)")
    fig.suptitle(f"resim pipeline report — {Path(out).name}")
    fig.tight_layout()
    p = Path(out) / "report.png"
    fig.savefig(p, dpi=80)
    plt.close(fig)
    return p


def format_summary(stats: dict, out: Path, report_png: Path | None) -> str:
    ts, q, run = stats["turning_share"], stats["quarantine"], stats["this_run"]
    wr = stats.get("warnings") or {"rows": 0}
    sc = stats.get("scene_cuts") or {"cuts": 0}
    st = stats.get("standing_still") or {"clips_tagged": 0, "windows_dropped": 0}
    du = stats.get("duplicates") or {}
    cc = stats.get("curation_cost") or {}
    lines = [
        f"clips written     {stats['clips']['total']}  ({', '.join(f'{k}: {v}' for k, v in stats['clips']['by_origin'].items()) or 'none'})",
        f"units             {stats['units']['ok']} ok, {stats['units']['quarantined']} quarantined "
        f"({run.get('units_run', 0)} run now, {run.get('units_skipped', 0)} already committed)",
        f"quarantine rows   {q['rows']}" + (f"  e.g. {q['examples'][0]}" if q["examples"] else ""),
        *([f"warnings          {wr['rows']} in {wr['units']} unit(s) (quarantine/*.parquet, status warning)  "
           f"e.g. {wr['examples'][0]}"] if wr["rows"] else []),
        *([f"duplicates        {du['clips_left_out']} clip(s) left out in {du['groups']} group(s) "
           "(dedup/duplicates.parquet; training skips them)"] if du.get("clips_left_out") else []),
        *([f"standing still    {st['clips_tagged']} clip(s) tagged stopped, {st['windows_dropped']} window(s) dropped"]
          if st["clips_tagged"] or st["windows_dropped"] else []),
        *([f"scene cuts        {sc['cuts']} in {sc['videos_with_cuts']} video(s): {sc['windows_dropped']} window(s) "
           "across one dropped"] if sc["cuts"] else []),
        f"turning share     {_pct(ts['before'])} before → {_pct(ts['after'])} after {ts['turn_factor']}x balance",
        *([f"split             {sp['episodes_train']} episode(s) train, {sp['episodes_heldout']} held out "
           f"(split.json; seed {sp['seed']}, fraction {sp['heldout_fraction']})"] if (sp := stats.get("split")) else []),
        (f"throughput        {run.get('clips_per_s')} clips/s ({run.get('clips_per_s_per_core')} per core), "
         f"wall {run.get('wall_s', 0):.1f} s" if run.get("units_run", 0) else
         f"throughput        n/a: nothing to run (every unit already committed), wall {run.get('wall_s', 0):.1f} s"),
        f"stage time share  " + ", ".join(f"{k} {v['share']:.0%}" for k, v in stats["stages"].items() if v["share"] is not None),
        *([curation.format_funnel(stats["curation"])] if stats.get("curation") else []),
        *([f"curation cost     {cc['share_of_labeling']:.0%} of labeling (scene cuts {cc['scene_cuts_s']:.1f} s, "
           f"signatures {cc['signatures_s']:.1f} s, quality {cc.get('quality_s', 0):.1f} s, dedup "
           f"{cc['dedup_s']:.1f} s, contact sheet {cc.get('contact_sheet_s', 0):.1f} s; labeling "
           f"{cc['labeling_s']:.1f} s)"]
          if cc.get("share_of_labeling") is not None else []),
        f"output            {out}  (stats.json, report: {report_png}"
        + (f", dropped examples: {out / 'curation.png'}" if (Path(out) / "curation.png").is_file() else "") + ")",
    ]
    return "\n".join(lines)


def _pct(x) -> str:
    return "n/a" if x is None else f"{x:.1%}"
