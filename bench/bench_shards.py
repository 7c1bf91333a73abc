"""Shard write/read throughput and bytes per sample at ReSim's real sizes, against plain WebDataset.

Baselines in the same process: ``webdataset.TarWriter`` writing the same member bytes (no validation,
no fsync/rename, no index/manifest), and ``webdataset.WebDataset`` iterating raw bytes (no decoding).
Run: PYTHONPATH=. python bench/bench_shards.py [--samples 24]
"""
from __future__ import annotations

import argparse
import sys
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import webdataset as wds

from resim.shards.npy import float32_to_bf16_bits
from resim.shards.prompts import PromptTable
from resim.shards.reader import iter_samples, make_webdataset
from resim.shards.schema import COMMANDS, prompt_text
from resim.shards.stats import compute_stats
from resim.shards.writer import ShardWriter, encode_member

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # the shared fixtures of tests/support
from tests.support.shards import add_dummy_prompts, make_dummy_sample  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--samples", type=int, default=24)
    args = ap.parse_args()

    # ReSim sizes: 49 frames at 480x720 -> latent (13, 16, 60, 90) bf16; frames.mp4 at 224 px wide
    samples = []
    for i in range(args.samples):
        s = make_dummy_sample(item_id=f"bench/{i}", command=COMMANDS[i % 3], seed=i, latent_channels=16,
                              latent_hw=(60, 90), latent_dtype="bfloat16", frames_hw=(128, 224))
        samples.append(s)
    tmp = Path(tempfile.mkdtemp(prefix="resim-bench-"))
    try:
        root = tmp / "ds"
        # real-size prompt table: 4 x (226, 4096) bf16

        t = PromptTable(root)
        rng = np.random.default_rng(0)
        for c in (*COMMANDS, None):
            t.add(prompt_text(c), float32_to_bf16_bits(rng.standard_normal((226, 4096)).astype(np.float32)),
                  "null" if c is None else "command", "bench-random", dtype="bfloat16", placeholder=True)

        # warm up one-time imports (pyarrow pulls in pandas on first Parquet write: ~1 s once per process)
        with ShardWriter(tmp / "warm", "warm") as w:
            w.write(samples[0])
        list(make_webdataset(tmp / "warm"))
        t0 = time.perf_counter()
        with wds.TarWriter(str(tmp / "plain.tar")) as tw:
            for s in samples:
                tw.write({"__key__": s["__key__"], **{k: encode_member(k, v) for k, v in s.items()
                                                      if not k.startswith("__")}})
        t_plain_w = time.perf_counter() - t0
        t0 = time.perf_counter()
        with ShardWriter(root, "bench", max_samples_per_shard=8) as w:
            for s in samples:
                w.write(s)
        t_ours_w = time.perf_counter() - t0

        t0 = time.perf_counter()
        n_plain = sum(1 for _ in wds.WebDataset(str(tmp / "plain.tar"), shardshuffle=False, empty_check=False))
        t_plain_r = time.perf_counter() - t0
        t0 = time.perf_counter()
        n_ours = sum(1 for _ in make_webdataset(root, latent_as="stored"))
        t_ours_r = time.perf_counter() - t0
        t0 = time.perf_counter()
        n_f32 = sum(1 for _ in iter_samples(root))
        t_f32 = time.perf_counter() - t0
        assert n_plain == n_ours == n_f32 == len(samples)
        st = compute_stats(root)
        n = len(samples)
        print(f"samples: {n}, latent (13,16,60,90) bf16, frames.mp4 49x128x224")
        print(f"write  plain TarWriter {n / t_plain_w:8.1f} samples/s | ShardWriter {n / t_ours_w:8.1f} samples/s "
              f"| ratio ours/plain time {t_ours_w / t_plain_w:.2f}")
        print(f"read   plain raw       {n / t_plain_r:8.1f} samples/s | make_webdataset(stored) {n / t_ours_r:8.1f} "
              f"samples/s | ratio {t_ours_r / t_plain_r:.2f}")
        print(f"read   iter_samples(float32 + prompts) {n / t_f32:8.1f} samples/s | ratio vs plain {t_f32 / t_plain_r:.2f}")
        print("bytes per sample:")
        for k, v in st["bytes_per_sample"].items():
            print(f"  {k:<24} {v / 1024:10.1f} KiB")
        per_sample_prompt = 226 * 4096 * 2
        print(f"storing the prompt in every sample instead would add {per_sample_prompt / 1024:.0f} KiB/sample "
              f"(+{100 * per_sample_prompt / st['bytes_per_sample']['in_shards']:.0f}% of the in-shard size)")
    finally:
        shutil.rmtree(tmp)


if __name__ == "__main__":
    main()
