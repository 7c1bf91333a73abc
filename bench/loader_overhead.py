"""Loader overhead: samples/s of ``resim.train.data.StreamLoader`` alone vs reading the same tar bytes in plain Python.

Baselines (same process, same files, warm page cache, every member's bytes read, nothing decoded):

* ``tarfile``: the standard library streams every shard, member bytes grouped by key (the
  "plain Python" reader, and what WebDataset itself runs on);
* ``raw``: the least any Python reader can do: per member one 512-byte header read, the size parsed,
  one data read (no checksum, no grouping checks). A lower bound, not a tar reader.

Loader: one epoch of the real training stream (shard draws, tar reading, safe npy/json decoding,
validation (NaN/inf, shapes, prompt ids, trajectories), collation into a ``Batch`` with prompt embeddings
attached), reading every member's bytes too (``plan.read_unused_members``: same bytes as the baselines;
by default the loader seeks over ``frames.mp4``, reported separately). All read the same number of
samples. Each repeat times the three back to back; the overhead ratio (baseline samples/s / loader
samples/s; target <= 1.2 vs ``tarfile``) is reported as the median over repeats.

    PYTHONPATH=. python bench/loader_overhead.py [--samples 160] [--latent-hw 32 56] [--repeats 7]

Default geometry is stage 2's (256x448 -> 13 x 16 x 32 x 56 fp16 latents, 0.75 MB per sample).
"""
from __future__ import annotations

import argparse
import sys
import platform
import statistics
import tarfile
import tempfile
import time
from pathlib import Path

import torch

from resim.config import from_dict
from resim.shards.schema import COMMANDS
from resim.shards.writer import ShardWriter
from resim.train.config import DataConfig
from resim.train.data import StreamLoader

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # the shared fixtures of tests/support
from tests.support.shards import add_dummy_prompts, make_dummy_sample  # noqa: E402


def write_dataset(root: Path, n: int, latent_hw: tuple[int, int], per_shard: int) -> None:
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


def raw_python(root: Path) -> tuple[int, int]:
    """(samples, bytes): per member one header read + one data read; samples counted by key change."""
    samples = nbytes = 0
    for p in sorted((root / "shards").glob("*.tar")):
        with open(p, "rb") as f:
            cur = None
            while True:
                h = f.read(512)
                if len(h) < 512 or not any(h):
                    break
                size = int(h[124:136].split(b"\0", 1)[0] or b"0", 8)
                data = f.read(size)
                f.seek(-size % 512, 1)
                if h[156:157] not in (b"0", b"\0"):
                    continue
                nbytes += len(data)
                key = h[:100].split(b"\0", 1)[0].split(b".", 1)[0]
                if key != cur:
                    samples += 1
                    cur = key
    return samples, nbytes


def make_loader(root: Path, n: int, batch: int, workers: int = 0, read_all: bool = True):
    cfg = from_dict(DataConfig, {"shards": str(root), "batch_size_per_gpu": batch, "samples_per_epoch": n,
                                 "num_workers": workers, "open_shards_per_worker": 4})
    loader = StreamLoader(cfg, verbose=False)
    loader.plan.read_unused_members = read_all  # True: the same bytes as the baselines
    return loader


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
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        t = time.perf_counter()
        write_dataset(root, args.samples, tuple(args.latent_hw), args.per_shard)
        print(f"wrote {args.samples} samples in {time.perf_counter() - t:.1f} s")
        mp4 = sum(len(m) for m in _members(root, "frames.mp4"))
        plain_python(root)  # warm the page cache
        loaders = {"same": make_loader(root, args.samples, args.batch),
                   "skip": make_loader(root, args.samples, args.batch, read_all=False)}
        for lo in loaders.values():
            loader_epoch(lo)  # warm: imports, prompt embeddings cached
        rates: dict[str, list[float]] = {k: [] for k in ("tarfile", "raw", "same", "skip")}
        for _ in range(args.repeats):
            for name, fn in (("tarfile", plain_python), ("raw", raw_python)):
                t = time.perf_counter()
                n_base, nbytes = fn(root)
                rates[name].append(n_base / (time.perf_counter() - t))
            for name, lo in loaders.items():
                t = time.perf_counter()
                n_load = loader_epoch(lo)
                rates[name].append(n_load / (time.perf_counter() - t))
            assert n_load == n_base == args.samples, (n_load, n_base)
        med = {k: statistics.median(v) for k, v in rates.items()}
        ratio = {f"{b}/{l_}": statistics.median([x / y for x, y in zip(rates[b], rates[l_])])
                 for b in ("tarfile", "raw") for l_ in ("same", "skip")}
        print(f"device: {platform.processor() or platform.machine()}, {torch.get_num_threads()} torch thread, "
              f"shared 2-core CPU; {args.repeats} repeats, medians")
        print(f"sample: latent 13x16x{args.latent_hw[0]}x{args.latent_hw[1]} fp16, {nbytes / n_base / 1e6:.3f} MB "
              f"per sample on disk (frames.mp4 {mp4 / n_base / 1e3:.1f} KB of it); prompt (226, 4096) bf16 attached")
        print(f"plain Python, tarfile       : {med['tarfile']:8.1f} samples/s ({med['tarfile'] * nbytes / n_base / 1e6:.0f} MB/s)")
        print(f"plain Python, raw reads     : {med['raw']:8.1f} samples/s ({med['raw'] * nbytes / n_base / 1e6:.0f} MB/s)")
        print(f"StreamLoader, same bytes    : {med['same']:8.1f} samples/s  (0 workers, steady state)")
        print(f"StreamLoader, default (seeks over frames.mp4): {med['skip']:8.1f} samples/s")
        print(f"overhead ratio tarfile / loader (same bytes): {ratio['tarfile/same']:.2f}  (target <= 1.2)")
        print(f"overhead ratio tarfile / loader (default)   : {ratio['tarfile/skip']:.2f}")
        print(f"overhead ratio raw / loader (same bytes)    : {ratio['raw/same']:.2f}  (lower bound reader)")
        print(f"overhead ratio raw / loader (default)       : {ratio['raw/skip']:.2f}")


def _members(root: Path, ext: str) -> list[bytes]:
    out = []
    for p in sorted((root / "shards").glob("*.tar")):
        with tarfile.open(p) as t:
            out += [t.extractfile(m).read() for m in t.getmembers() if m.name.endswith("." + ext)]
    return out


if __name__ == "__main__":
    main()
