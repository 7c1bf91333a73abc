"""Pipeline benchmarks. Each part prints its numbers and a ratio against a baseline measured in
the same process; docs/benchmarks.md (## Pipeline) records a run with the device.

    PYTHONPATH=. python bench/pipeline_bench.py throughput   # clips/s per core + per-stage time share
    PYTHONPATH=. python bench/pipeline_bench.py scaling      # 1 vs 2 Ray workers (ratio)
    PYTHONPATH=. python bench/pipeline_bench.py rss          # peak RSS, 10 vs 50 source videos (ratio)
    PYTHONPATH=. python bench/pipeline_bench.py real         # per-stage costs on real dashcam video at 256x448
    PYTHONPATH=. python bench/pipeline_bench.py all

All runs use the shipped tiny placeholder VAE/T5 (CPU), so "encode.vae" here is NOT the cost of the real
CogVideoX VAE: bench/vae_gpu_bench.py measures that on a GPU, and docs/pipeline.md projects a cluster from
the CPU stages measured here plus the published GPU anchor.
"""
from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from resim.pipeline import runner  # noqa: E402
from resim.pipeline.load import load_config  # noqa: E402
from resim.pipeline.sources.synth.generate import generate, preset  # noqa: E402

SYNTH = REPO / "configs/pipeline/synthetic.yaml"
# $RESIM_SHARED_DIR, else shared/ beside the checkout (main clone), else one level up (worktree wt/<x>)
_SHARED = [Path(os.environ["RESIM_SHARED_DIR"])] if os.environ.get("RESIM_SHARED_DIR") else \
    [REPO.parent / "shared", REPO.parent.parent / "shared"]
DASHCAM = next((s / "data" / "dashcam" for s in _SHARED if (s / "data" / "dashcam").is_dir()),
               _SHARED[0] / "data" / "dashcam")


def _world(tmp: Path, episodes: int = 6) -> Path:
    root = tmp / f"world{episodes}"
    if not root.exists():
        generate(root, episodes, 0, preset("tiny"), progress=False)
    return root


def _run(out: Path, overrides: list[str], base: Path = SYNTH) -> dict:
    cfg = load_config(base, ["ray.progress_bars=false", *overrides], out=out)
    t0 = time.perf_counter()
    res = runner.run(cfg)
    res.stats["bench_wall_s"] = time.perf_counter() - t0
    return res.stats


def _stage_table(stats: dict) -> str:
    rows = []
    for k, v in stats["stages"].items():
        share = f"{v['share']:.1%}" if v["share"] is not None else "  (part)"
        rows.append(f"    {k:<14} {v['seconds']:8.2f} s  {share:>7}  {v['clips_per_s']} clips/s")
    return "\n".join(rows)


def throughput(tmp: Path) -> dict:
    """Whole pipeline, demo resolution, local executor (exactly one core busy) and Ray (2 CPUs)."""
    world = _world(tmp)
    local = _run(tmp / "tp_local", [f"sources.synthetic.root={world}", "ray.executor=local"])
    ray2 = _run(tmp / "tp_ray", [f"sources.synthetic.root={world}"])
    n = local["clips"]["total"]
    stage_s = sum(v["seconds"] for v in local["stages"].values() if v["share"] is not None)
    print(f"[throughput] {n} clips, demo resolution 64x96, tiny placeholder VAE/T5")
    print(f"  local executor (1 core): wall {local['bench_wall_s']:.1f} s -> {n / local['bench_wall_s']:.3f} clips/s/core"
          f" (stage time only: {n / stage_s:.3f} clips/s/core)")
    print(_stage_table(local))
    print(f"  ray, 2 CPUs: wall {ray2['bench_wall_s']:.1f} s -> {n / ray2['bench_wall_s']:.3f} clips/s "
          f"= {n / ray2['bench_wall_s'] / 2:.3f} clips/s/core; ratio vs local wall {local['bench_wall_s'] / ray2['bench_wall_s']:.2f}x")
    return {"clips": n, "local_wall_s": local["bench_wall_s"], "local_stage_s": stage_s,
            "ray2_wall_s": ray2["bench_wall_s"], "stages": local["stages"]}


def scaling(tmp: Path) -> dict:
    """The same job on an embedded Ray with 1 and with 2 CPUs (encode pool 1 vs 2 actors)."""
    world = _world(tmp)
    common = [f"sources.synthetic.root={world}", "ray.stages.label.num_cpus=0.25",
              "ray.stages.write.num_cpus=0.1", "ray.stages.prompts.num_cpus=0.1"]
    one = _run(tmp / "sc1", common + ["ray.num_cpus=1", "ray.stages.encode.actors=1", "ray.stages.encode.num_cpus=0.5"])
    two = _run(tmp / "sc2", common + ["ray.num_cpus=2", "ray.stages.encode.actors=2", "ray.stages.encode.num_cpus=0.5"])
    r = one["bench_wall_s"] / two["bench_wall_s"]
    print(f"[scaling] {one['clips']['total']} clips: 1 worker {one['bench_wall_s']:.1f} s, "
          f"2 workers {two['bench_wall_s']:.1f} s -> speed-up {r:.2f}x (ideal 2.00x)")
    return {"one_s": one["bench_wall_s"], "two_s": two["bench_wall_s"], "speedup": r}


def _rss_child(root: str, out: str, n: int) -> None:
    """Child process: run the local executor over n videos, print peak RSS (MiB)."""
    _run(Path(out), ["sources.synthetic.root=null", f"sources.opendv.root={root}", "sources.opendv.start_discard_s=0",
                     "sources.opendv.end_discard_s=0", "sources.opendv.min_height_px=32", "ray.executor=local",
                     "clip.stride_frames=40", "balance.enabled=false"])
    print(json.dumps({"n": n, "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def rss(tmp: Path) -> dict:
    """Peak RSS of a whole run (local executor: one process holds everything) for 10 vs 50 videos."""
    world = _world(tmp)
    vids = sorted((world / "opendv").rglob("*.mp4"))
    res = {}
    for n in (10, 50):
        d = tmp / f"videos{n}"
        d.mkdir(exist_ok=True)
        for i in range(n):
            shutil.copy(vids[i % len(vids)], d / f"v{i:03d}.mp4")
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, __file__, "_rss_child", str(d), str(tmp / f"rss_out{n}"), str(n)],
                           capture_output=True, text=True, check=True)
        res[n] = json.loads(p.stdout.strip().splitlines()[-1])["peak_rss_mib"]
        print(f"[rss] {n} videos: peak RSS {res[n]:.0f} MiB ({time.perf_counter() - t0:.0f} s)")
    print(f"[rss] 50 / 10 videos: {res[50] / res[10]:.3f}x (flat = 1.0)")
    return {"rss10_mib": res[10], "rss50_mib": res[50], "ratio": res[50] / res[10]}


def real(tmp: Path) -> dict:
    """Per-stage CPU costs on real dashcam footage (540p/576p, 25 fps) at ReSim's 256x448."""
    if not DASHCAM.is_dir():
        print(f"[real] no {DASHCAM} here: skipped")
        return {}
    src = tmp / "dashcam"
    src.mkdir(exist_ok=True)
    for p in DASHCAM.glob("*.mp4"):
        shutil.copy(p, src / p.name)
    st = _run(tmp / "real_out", ["sources.synthetic.root=null", f"sources.opendv.root={src}",
                                 "sources.opendv.start_discard_s=0", "sources.opendv.end_discard_s=0",
                                 "sources.opendv.min_height_px=480", "ray.executor=local",
                                 "encode.height_px=256", "encode.width_px=448",
                                 "encode.frames_height_px=128", "encode.frames_width_px=224"])
    n = st["clips"]["total"]
    print(f"[real] {n} clips from {len(list(src.glob('*.mp4')))} dashcam videos at 256x448 (local executor, 1 core)")
    print(_stage_table(st))
    per_clip = {k: v["seconds"] / max(n, 1) for k, v in st["stages"].items()}
    print("  seconds per clip: " + ", ".join(f"{k} {v:.3f}" for k, v in per_clip.items()))
    return {"clips": n, "per_clip_s": per_clip, "quarantine": st["quarantine"]["rows"]}


PARTS = ["throughput", "scaling", "rss", "real"]

if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "_rss_child":
        _rss_child(sys.argv[2], sys.argv[3], int(sys.argv[4]))
        sys.exit(0)
    what = sys.argv[1:] or ["all"]
    if any(w in ("-h", "--help") for w in what):
        print(__doc__)
        sys.exit(0)
    bad = [w for w in what if w not in (*PARTS, "all")]
    if bad:
        sys.exit(f"usage: pipeline_bench.py [{'|'.join(PARTS)}|all ...]; unknown: {' '.join(bad)}")
    import torch

    torch.set_num_threads(1)
    parts = PARTS if "all" in what else what
    with tempfile.TemporaryDirectory(prefix="resim-bench-") as tmp:
        results = {p: globals()[p](Path(tmp)) for p in parts}
    print("device: 2-core CPU (shared), torch threads 1 per process")
    print(json.dumps(results, indent=1, default=str))
