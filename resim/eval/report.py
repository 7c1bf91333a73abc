"""Writing evaluation reports: protocol text (printed with every number) and PNG plots (the JSON goes through
:func:`resim.shards.safejson.write_json`, grouped bars through :func:`resim.train.metrics.plot_bars`).

Every ``resim eval`` command writes ``DIR/<name>.json`` (the numbers *and* the protocol they were measured
under) and ``DIR/<name>.png``, and prints the protocol before the numbers.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any


def _brief(v: Any) -> str:
    """A value as one readable line: a list of records (e.g. skipped clips) is its count and the first one,
    not a dump of them all (the JSON report keeps the full list)."""
    if isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
        first = ", ".join(f"{a}: {b}" for a, b in v[0].items())
        return f"{len(v)} (e.g. {first}; all of them in the JSON report)" if len(v) > 1 else first
    if isinstance(v, dict):
        return "{" + ", ".join(f"{a}: {_brief(b)}" for a, b in v.items()) + "}"
    return str(v)


def format_protocol(protocol: dict, indent: str = "  ") -> str:
    lines = ["protocol:"]
    for k, v in protocol.items():
        if isinstance(v, dict):
            lines.append(f"{indent}{k}:")
            for k2, v2 in v.items():
                lines.append(f"{indent * 2}{k2}: {_brief(v2)}")
        else:
            lines.append(f"{indent}{k}: {_brief(v)}")
    return "\n".join(lines)


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def format_quality(report: dict) -> str:
    """Protocol, then the per-horizon table, the overall numbers and the warnings."""
    out = [format_protocol(report["protocol"]), "", "per horizon (future frames in (from, to] s):"]
    rows = report["per_horizon"]
    cols = [c for c in ("psnr", "psnr_capped_frames", "ssim", "lpips", "dreamsim", "fid") if rows and c in rows[0]]
    heads = {"psnr_capped_frames": "psnr capped"}   # frames at the PSNR cap (identical), included in the mean
    out.append("  " + "  ".join(f"{h:>10s}" for h in ["horizon", "frames", *(heads.get(c, c) for c in cols)]))
    for r in rows:
        vals = [f"{r['from_s']:g}-{r['horizon_s']:g} s", str(r["frames_per_clip"]), *[_fmt(r[c]) for c in cols]]
        out.append("  " + "  ".join(f"{v:>10s}" for v in vals))
    for r in report.get("fvd_per_horizon", []):
        out.append(f"  FVD first {r['horizon_s']:g} s ({r['frames']} frames): {_fmt(r['fvd'])}")
    out.append("overall (all future frames):")
    for k, v in report["overall"].items():
        if isinstance(v, dict):
            v = ", ".join(f"{a}={_fmt(b)}" for a, b in v.items())
        out.append(f"  {k}: {_fmt(v)}")
    for w in report.get("warnings", []):
        out.append(f"WARNING: {w}")
    return "\n".join(out)


def plot_quality(report: dict, path: str | Path, title: str = "") -> Path:
    """One panel per metric: per-frame curves (PSNR/SSIM/LPIPS/DreamSim) with per-horizon means as steps,
    FID per horizon bin, FVD per cumulative horizon."""
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pf = report["per_frame"]
    panels = [m for m in ("psnr", "ssim", "lpips", "dreamsim") if m in pf]
    has_fid = any(r.get("fid") is not None for r in report["per_horizon"])
    has_fvd = any(r.get("fvd") is not None for r in report.get("fvd_per_horizon", []))
    panels += (["fid"] if has_fid else []) + (["fvd"] if has_fvd else [])
    n = max(len(panels), 1)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.0), dpi=110, squeeze=False)
    for ax, m in zip(axes[0], panels):
        if m in pf:
            ax.plot(pf["time_s"], pf[m], ".-", lw=1, ms=3, label="per frame")
            for r in report["per_horizon"]:
                if r.get(m) is not None:
                    ax.hlines(r[m], r["from_s"], r["horizon_s"], colors="tab:orange", lw=2)
            ax.plot([], [], color="tab:orange", lw=2, label="horizon mean")
            ax.legend(fontsize=6)
        elif m == "fid":
            xs = [r["horizon_s"] for r in report["per_horizon"] if r.get("fid") is not None]
            ax.plot(xs, [r["fid"] for r in report["per_horizon"] if r.get("fid") is not None], "o-")
        else:
            rows = [r for r in report["fvd_per_horizon"] if r.get("fvd") is not None]
            ax.plot([r["horizon_s"] for r in rows], [r["fvd"] for r in rows], "o-")
        ax.set_xlabel("prediction horizon (s)")
        ax.set_title(m.upper(), fontsize=9)
        ax.grid(alpha=0.3)
    proto = report["protocol"]
    sub = f"{proto['clips']} clips, {proto.get('metric_resolution_hw')}"
    if proto.get("placeholder_networks"):
        sub += f"; PLACEHOLDER nets: {','.join(proto['placeholder_networks'])}"
    fig.suptitle(f"{title}  ({sub})".strip(), fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)
