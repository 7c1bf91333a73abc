"""Loader overhead: samples/s of ``training.data.StreamLoader`` alone vs reading the same tar bytes in plain Python.

Baseline (same process, same files, warm page cache): ``tarfile`` streams every shard and groups member
bytes by key (what any reader must do at least). Loader: one epoch of the real training stream (shard
draws, WebDataset tar iteration, safe npy/json decoding, validation, collation into a ``Batch`` with
prompt embeddings attached). Both read the same number of samples. Prints the overhead ratio
(baseline samples/s / loader samples/s; target <= 1.2) and the device.

    PYTHONPATH=. python bench/loader_overhead.py [--samples 160] [--latent-hw 32 56] [--repeats 3]

Default geometry is stage 2's (256x448 -> 13 x 16 x 32 x 56 fp16 latents, 0.75 MB per sample).
"""
from __future__ import annotations

import argparse
import platform
import tarfile
import tempfile
import time
from pathlib import Path


def write_dataset(root: Path, n: int, latent_hw: tuple[int, int], per_shard: int) -> None:
    from shards.schema import COMMANDS
    from shards.testing import add_dummy_prompts, make_dummy_sample
    from shards.writer import ShardWriter

    add_dummy_prompts(root, seq_len=226, dim=4096)  # CogVideoX T5 size: (226, 4096) bf16
    with ShardWriter(root, "bench", max_samples_per_shard=per_shard, config_hash="bench") as w:
        for i in range(n):
            w.write(make_dummy_sample(source="synthetic", item_id=f"bench/{i // 8}", start_frame=(i % 8) * 10,
                                      command=COMMANDS[i % 3], seed=i, latent_channels=16, latent_hw=latent_hw,
                                      frames_hw=(32, 56)))


def plain_python(root: Path) -> tuple[int, int]:
    """(samples, bytes): every shard read with tarfile, members grouped by key, nothing decoded."""
    samples = nbytes = 0
    for p in sorted((root / "shards").glob("*.tar")):
        with open(p, "rb") as f, tarfile.open(fileobj=f, mode="r|") as t:
            cur, group = None, {}
            for m in t:
                if not m.isfile():
                    continue
                key, ext = m.name.split(".", 1)
                data = t.extractfile(m).read()
                nbytes += len(data)
                if key != cur:
                    samples += cur is not None
                    cur, group = key, {}
                group[ext] = data
            samples += cur is not None
    return samples, nbytes


def make_loader(root: Path, n: int, batch: int, workers: int = 0):
    from resim.config import from_dict
    from training.config import DataConfig
    from training.data import StreamLoader

    cfg = from_dict(DataConfig, {"shards": str(root), "batch_size_per_gpu": batch, "samples_per_epoch": n,
                                 "num_workers": workers, "open_shards_per_worker": 4})
    return StreamLoader(cfg, verbose=False)


def loader_epoch(loader) -> int:
    """One epoch (steady state: the loader and its prompt cache are reused across epochs, as in training)."""
    got = 0
    for b in loader:
        got += len(b)
    return got


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=160)
    ap.add_argument("--latent-hw", type=int, nargs=2, default=(32, 56))
    ap.add_argument("--per-shard", type=int, default=40)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        t = time.perf_counter()
        write_dataset(root, args.samples, tuple(args.latent_hw), args.per_shard)
        print(f"wrote {args.samples} samples in {time.perf_counter() - t:.1f} s")
        plain_python(root)  # warm the page cache
        loader = make_loader(root, args.samples, args.batch)
        loader_epoch(loader)  # warm: imports, prompt embeddings cached
        base, load = [], []
        for _ in range(args.repeats):
            t = time.perf_counter()
            n_base, nbytes = plain_python(root)
            base.append(n_base / (time.perf_counter() - t))
            t = time.perf_counter()
            n_load = loader_epoch(loader)
            load.append(n_load / (time.perf_counter() - t))
        b, l_ = max(base), max(load)
        print(f"device: {platform.processor() or platform.machine()}, {torch.get_num_threads()} torch thread, "
              f"shared 2-core CPU")
        print(f"sample: latent 13x16x{args.latent_hw[0]}x{args.latent_hw[1]} fp16, {nbytes / n_base / 1e6:.2f} MB "
              f"per sample on disk; prompt (226, 4096) bf16 attached per sample")
        print(f"plain Python tar read : {b:8.1f} samples/s ({b * nbytes / n_base / 1e6:.0f} MB/s)  best of {args.repeats}")
        print(f"StreamLoader (0 workers): {l_:8.1f} samples/s  (steady state: 2nd+ epoch of one loader)")
        print(f"overhead ratio (plain / loader): {b / l_:.2f}  (target <= 1.2)")


if __name__ == "__main__":
    main()
