"""Synthetic world cost: seconds per episode and per rendered frame, 1 vs 2 workers.

Prints the ratio of the 2-worker run to the 1-worker baseline in the same process.
Usage: PYTHONPATH=. python bench/bench_synth.py [--episodes 12]
"""
import argparse
import tempfile
import time
from pathlib import Path

from resim.pipeline.sources.synth.generate import SynthConfig, generate


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--episodes", type=int, default=12)
    args = ap.parse_args()
    cfg = SynthConfig()
    with tempfile.TemporaryDirectory() as d:
        out = {}
        for workers in (1, 2):
            t0, c0 = time.perf_counter(), time.process_time()
            generate(Path(d) / f"w{workers}", args.episodes, seed=0, cfg=cfg, progress=False, workers=workers)
            out[workers] = (time.perf_counter() - t0, time.process_time() - c0)
            print(f"workers={workers}: {out[workers][0]:.1f} s wall, {out[workers][0] / args.episodes:.2f} s/episode "
                  f"({cfg.height_px}x{cfg.width_px}, {cfg.episode_s:.0f} s episodes)")
        print(f"ratio 2 workers / 1 worker (wall): {out[2][0] / out[1][0]:.2f}")


if __name__ == "__main__":
    main()
