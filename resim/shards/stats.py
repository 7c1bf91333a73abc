"""``stats``: what a dataset holds, from manifests, indexes, the prompt table and quarantine (no tar is opened).

Keys of the returned dict (also ``resim shards stats --json``):

* ``root``; ``num_shards``; ``num_samples``; ``shard_bytes`` (sum of tar sizes);
  ``uncommitted_shards`` (tars without index, not counted elsewhere);
  ``schema_versions``, ``config_hashes`` (distinct values over indexes).
* ``by_source``, ``by_command``, ``by_command_source``: sample counts;
  ``by_hazard``: counts under ``"true"``/``"false"``/``"null"`` (null: source has no outcomes);
  ``by_source_command``: ``{source: {command: count}}``.
* ``turning_share``: fraction of samples whose command is not "Moving forward" (null if no samples).
* ``quarantine``: ``num_items``, ``by_source``, ``by_stage``, ``by_reason`` (top 20), ``items`` (first 20 rows:
  item, unit_id, source, stage, status, reason, attempts) of the rows that kept something out of the dataset
  (status ``quarantined`` / ``dropped``, or no status column); ``num_items`` 0 when ``DIR/quarantine`` is absent.
* ``warnings``: the same keys for the rows with status ``warning`` (the unit was used, its clips written).
* ``bytes_per_sample``: mean bytes per sample for each member (``meta.json``, ``latent.npy``, ``traj.npy``,
  ``frames.mp4``, ``dino.npy``; samples without an optional member count 0), ``tar_overhead`` (headers and
  padding), ``in_shards`` (tar bytes / samples), ``prompt_table_amortised`` (prompt table bytes / samples) and
  ``total`` (in_shards + prompt_table_amortised).
* ``member_presence``: how many samples carry each member.
* ``latent``: ``shapes`` (``"TxCxhxw"`` -> count) and ``dtypes`` (-> count).
* ``quality``: for ``ego_motion_pct_s`` and each per-clip quality column (schema v3, ``resim.shards.schema.QUALITY_META``):
  ``n`` (samples with a value), ``min``, ``p05``, ``p50``, ``p95``, ``max``; ``--plot PNG`` draws their
  histograms by source.
* ``prompt_table``: ``num_prompts``, ``bytes`` (embedding files + prompts.json), ``entries`` (id, role, command,
  text, shape, dtype, encoder_id, placeholder, num_tokens, bytes).
"""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from resim.shards import layout
from resim.shards.manifest import read_indexes, read_manifest, read_quarantine
from resim.shards.prompts import PromptTable
from resim.shards.schema import MEMBERS, QUALITY_META

# the manifest's per-clip columns a user filters on (resim/pipeline/clip_quality.py, labels.still) and their units
QUALITY_COLUMNS = {"ego_motion_pct_s": "% of frame width / s", "luma_mean_8bit": "0..255",
                   "luma_std_8bit": "8-bit levels", "sharpness_lapvar": "8-bit levels²", "static_edge_frac": "0..1",
                   "flow_quality": "0..1"}
assert set(QUALITY_META) < set(QUALITY_COLUMNS), "a quality column without its unit"


def _counts(values) -> dict:
    return dict(sorted(Counter(values).items(), key=lambda kv: (-kv[1], str(kv[0]))))


WARNING_STATUS = "warning"   # = resim.pipeline.quarantine.WARNING (shards/ does not import pipelines/)


def _row_summary(rows: list[dict]) -> dict:
    return {
        "num_items": len(rows),
        "by_source": _counts(r.get("source") for r in rows),
        "by_stage": _counts(r.get("stage") for r in rows),
        "by_reason": dict(list(_counts(r.get("reason") for r in rows).items())[:20]),
        "items": rows[:20],
    }


def compute_stats(root) -> dict:
    root = Path(root)
    indexes = [i for i in read_indexes(root) if (layout.shards_dir(root) / i["shard"]).is_file()]
    man = read_manifest(root).to_pydict()
    n = len(man["key"])
    # sample counts come from the manifests, shard counts and bytes from the indexes: say where they disagree
    # (a lost or stale manifest) instead of printing totals and bytes per sample that do not add up
    rows = Counter(man["shard"])
    mismatch = [f"{i['shard']}: index says {i['num_samples']} samples, its manifest has {rows.get(i['shard'], 0)} rows"
                for i in indexes if rows.get(i["shard"], 0) != i["num_samples"]]
    hazard = ["null" if h is None else ("true" if h else "false") for h in man["hazard"]]
    by_sc: dict[str, Counter] = {}
    for s, c in zip(man["source"], man["command"]):
        by_sc.setdefault(s, Counter())[c] += 1
    member_bytes, member_counts, shapes, dtypes = Counter(), Counter(), Counter(), Counter()
    shard_bytes = 0
    for idx in indexes:
        member_bytes.update(idx.get("member_bytes", {}))
        member_counts.update(idx.get("member_counts", {}))
        shapes.update(idx.get("histograms", {}).get("latent_shape", {}))
        dtypes.update(idx.get("histograms", {}).get("latent_dtype", {}))
        shard_bytes += idx["bytes"]
    table = PromptTable(root)
    entries = table.entries()
    ptab_bytes = table.total_bytes()
    bps: dict = {}
    n_idx = sum(i["num_samples"] for i in indexes)   # bytes come from the indexes: divide by their counts
    if n_idx:
        for ext in MEMBERS:
            bps[ext] = member_bytes.get(ext, 0) / n_idx
        bps["tar_overhead"] = (shard_bytes - sum(member_bytes.values())) / n_idx
        bps["in_shards"] = shard_bytes / n_idx
        bps["prompt_table_amortised"] = ptab_bytes / n_idx
        bps["total"] = bps["in_shards"] + bps["prompt_table_amortised"]
    q = read_quarantine(root)
    q_rows = q.to_pylist() if q is not None else []
    # status "warning" (resim/pipeline/quarantine.py): the unit was used, nothing was kept out; counted apart.
    # Rows without a status column (other writers) count as quarantined.
    warned = [r for r in q_rows if r.get("status") == WARNING_STATUS]
    quarantine = _row_summary([r for r in q_rows if r.get("status") != WARNING_STATUS])
    warnings = _row_summary(warned)
    committed = {i["shard"] for i in indexes}
    return {
        "root": str(root),
        "num_shards": len(indexes),
        "num_samples": n,
        "shard_bytes": shard_bytes,
        "uncommitted_shards": sum(p.name not in committed for p in layout.all_shard_files(root)),
        "manifest_mismatch": mismatch,
        "schema_versions": sorted({i.get("schema_version") for i in indexes}),
        "config_hashes": sorted({i.get("config_hash", "") for i in indexes}),
        "by_source": _counts(man["source"]),
        "by_command": _counts(man["command"]),
        "by_command_source": _counts(man["command_source"]),
        "by_hazard": _counts(hazard),
        "by_source_command": {s: dict(sorted(c.items())) for s, c in sorted(by_sc.items())},
        "turning_share": (sum(man["is_turning"]) / n) if n else None,
        "quarantine": quarantine,
        "warnings": warnings,
        "bytes_per_sample": bps,
        "member_presence": dict(sorted(member_counts.items())),
        "latent": {"shapes": dict(shapes), "dtypes": dict(dtypes)},
        "quality": {c: _spread(man.get(c, [])) for c in QUALITY_COLUMNS},
        "prompt_table": {
            "num_prompts": len(entries),
            "bytes": ptab_bytes,
            "entries": [{"id": pid, **{k: e.get(k) for k in ("role", "command", "text", "shape", "dtype",
                                                                  "encoder_id", "placeholder", "num_tokens",
                                                                  "bytes")}}
                        for pid, e in sorted(entries.items())],
        },
    }


def _spread(values) -> dict:
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    v = v[np.isfinite(v)]
    if not len(v):
        return {"n": 0}
    q = np.percentile(v, [0, 5, 50, 95, 100])
    return {"n": int(len(v)), **{k: round(float(x), 4) for k, x in zip(("min", "p05", "p50", "p95", "max"), q)}}


def plot_quality(root, path) -> Path:
    """Histograms of the per-clip columns (``QUALITY_COLUMNS``) by source, one panel each, to ``path`` (PNG)."""
    # matplotlib is slow to import and only the plot needs it (the light install may lack it)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    man = read_manifest(Path(root)).to_pydict()
    sources = sorted(set(man["source"]))
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    for ax, (col, unit) in zip(axes.ravel(), QUALITY_COLUMNS.items()):
        vals = man.get(col) or []
        per = {s: [v for v, src in zip(vals, man["source"]) if src == s and v is not None and np.isfinite(v)]
               for s in sources}
        allv = [v for vs in per.values() for v in vs]
        if not allv:
            ax.text(0.5, 0.5, "no values\n(written before schema v3?)", ha="center", va="center", fontsize=9)
        else:
            lo, hi = min(allv), max(allv)
            pad = 0.05 * max(abs(hi), 1e-3) if hi - lo < 1e-9 else 0.0    # one value: a visible bar around it
            bins = np.linspace(lo - pad, hi + pad, 30)
            ax.hist([per[s] for s in sources if per[s]], bins=bins, stacked=True,
                    label=[s for s in sources if per[s]])
            ax.legend(fontsize=7)
        ax.set_title(f"{col} ({unit})", fontsize=9)
        ax.set_ylabel("clips", fontsize=8)
    fig.suptitle(f"per-clip quality — {Path(root).name} ({len(man['key'])} clips); filters: the pipeline "
                 "config's quality section", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def _h(nbytes: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(nbytes) < 1024 or unit == "TiB":
            return f"{nbytes:.0f} {unit}" if unit == "B" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return str(nbytes)


def format_stats(st: dict) -> str:
    """Human-readable rendering of :func:`compute_stats`."""
    n = st["num_samples"]
    lines = [f"dataset {st['root']}: {n} samples in {st['num_shards']} shards ({_h(st['shard_bytes'])})"]
    if st["uncommitted_shards"]:
        lines.append(f"  ! {st['uncommitted_shards']} uncommitted shard(s) (no index; run `resim shards verify`)")
    if st["manifest_mismatch"]:
        lines.append(f"  ! {len(st['manifest_mismatch'])} shard(s) whose manifest does not match the index; the "
                     "counts below are from the manifests (run `resim shards verify`):")
        lines += [f"    {m}" for m in st["manifest_mismatch"][:5]]

    def block(title, d):
        lines.append(f"{title}:")
        for k, v in d.items():
            lines.append(f"  {str(k):<24} {v:>8}  ({100 * v / n:5.1f}%)" if n else f"  {k}: {v}")

    block("by source", st["by_source"])
    block("by command", st["by_command"])
    block("command from", st["by_command_source"])
    block("hazard", st["by_hazard"])
    if st["turning_share"] is not None:
        lines.append(f"turning share: {100 * st['turning_share']:.1f}%")
    q = st["quarantine"]
    lines.append(f"quarantined items: {q['num_items']}")
    for k, v in q["by_stage"].items():
        lines.append(f"  stage {k}: {v}")
    for k, v in list(q["by_reason"].items())[:5]:
        lines.append(f"  {v} x {k}")
    w = st.get("warnings") or {"num_items": 0}
    lines.append(f"warnings: {w['num_items']}" + ("  (units used, clips written; quarantine/*.parquet, "
                                                  "status warning)" if w["num_items"] else ""))
    for k, v in list(w.get("by_reason", {}).items())[:5]:
        lines.append(f"  {v} x {k}")
    if st["bytes_per_sample"]:
        lines.append("bytes per sample:")
        for k, v in st["bytes_per_sample"].items():
            lines.append(f"  {k:<24} {_h(v):>10}")
    lines.append("latent: " + ", ".join(f"{s} ({c})" for s, c in st["latent"]["shapes"].items())
                 + " | " + ", ".join(f"{d} ({c})" for d, c in st["latent"]["dtypes"].items()))
    qual = {c: v for c, v in (st.get("quality") or {}).items() if v.get("n")}
    if qual:
        lines.append("per-clip quality (min / 5% / median / 95% / max):")
        for c, v in qual.items():
            lines.append(f"  {c:<18} {v['min']:>9.3g} {v['p05']:>9.3g} {v['p50']:>9.3g} {v['p95']:>9.3g} "
                         f"{v['max']:>9.3g}  ({v['n']} clips; {QUALITY_COLUMNS[c]})")
    pt = st["prompt_table"]
    lines.append(f"prompt table: {pt['num_prompts']} prompts, {_h(pt['bytes'])}")
    for e in pt["entries"]:
        ph = " PLACEHOLDER" if e["placeholder"] else ""
        lines.append(f"  {e['id'][:12]} {e['role']:<7} {e['dtype']}{e['shape']} {e['encoder_id']}{ph}: "
                     f"{e['command'] or '(prefix only)'}")
    return "\n".join(lines)
