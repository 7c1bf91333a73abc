"""Near-duplicate clips: re-uploaded or repeated footage, found across the whole dataset in one pass.

ReSim's OpenDV source is 1,700 h of uploads, some of them the same drive twice (re-uploads, compilations that
reuse a segment). Training on both copies weights that footage double and leaks it across a train/held-out
split. cosmos-curate and NeMo Curator dedup on embeddings; a perceptual hash of a few frames is enough for
re-uploads and costs nothing beside the VAE:

* **signature** (encode stage, per clip, from the frames it already holds at the training resolution): the
  64-bit difference hash (dHash: 9×8 grey thumbnail, one bit per horizontal neighbour pair) of 4 frames evenly
  spaced over the clip: 256 bits, 64 hex digits, in ``meta.json`` and the manifest (``signature``). A re-encode,
  a resize, a logo or a fraction of a second's offset flips a few bits; another scene flips about half;
* **grouping** (driver, once, after every unit committed): clips whose signatures differ in at most
  ``dedup.max_bits`` bits are one group, unless they are overlapping windows of the same video (those share
  frames by construction and are distinct training windows). Candidates come from exact matches of
  ``band_bits``-bit bands (locality-sensitive hashing), then the full distance decides. Measured on the real
  dashcam clips: the same footage a few frames (0.2-0.8 s) apart differs in 16-40 of the 256 bits, other
  footage in 87-116; with 8-bit bands a pair 40 bits apart shares a band with near certainty (32 bands,
  each clean with p ≈ 0.26); 16-bit bands cut the candidate pairs ~256× for large datasets at some recall. The first clip of a group (by item, start) is kept;
  ``OUT/dedup/duplicates.parquet`` lists the others (``key``, ``duplicate_of``, ``distance_bits``), and the
  training loader skips them (``data.skip_duplicates``).
"""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from resim.shards.duplicates import duplicates_path
from resim.shards.fsio import atomic_write_bytes
from resim.shards.manifest import read_manifest

SIGNATURE_FRAMES = 4


def dhash(frame: np.ndarray) -> int:
    """64-bit difference hash of an RGB uint8 frame ``(H, W, 3)``."""
    g = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    t = cv2.resize(g, (9, 8), interpolation=cv2.INTER_AREA).astype(np.int16)
    bits = (t[:, 1:] > t[:, :-1]).ravel()
    return int(np.packbits(bits).view(">u8")[0])


def clip_signature(frames: np.ndarray) -> str:
    """64 hex digits: the dHash of ``SIGNATURE_FRAMES`` frames evenly spaced over ``frames`` ``(T, H, W, 3)``."""
    idx = np.linspace(0, len(frames) - 1, SIGNATURE_FRAMES).round().astype(int)
    return "".join(f"{dhash(frames[i]):016x}" for i in idx)


def distance_bits(a: str, b: str) -> int:
    return bin(int(a, 16) ^ int(b, 16)).count("1")


def find_duplicates(rows: list[dict], max_bits: int, num_frames: int, band_bits: int = 8) -> list[dict]:
    """``rows``: ``{"key", "item_id", "start_frame", "signature"}``; returns one ``{"key", "duplicate_of",
    "distance_bits"}`` per clip left out (each group keeps its first clip by (item_id, start_frame, key))."""
    rows = sorted((r for r in rows if r.get("signature")), key=lambda r: (r["item_id"], r["start_frame"], r["key"]))
    width = band_bits // 4                                     # hex digits per band
    bands = 16 * SIGNATURE_FRAMES // width
    buckets: dict[tuple[int, str], list[int]] = defaultdict(list)
    for i, r in enumerate(rows):
        for b in range(bands):
            buckets[(b, r["signature"][b * width:(b + 1) * width])].append(i)
    parent = list(range(len(rows)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    best: dict[int, int] = {}
    seen: set[tuple[int, int]] = set()
    for members in buckets.values():
        for x in range(len(members)):
            for y in range(x + 1, len(members)):
                i, j = members[x], members[y]
                if (i, j) in seen:
                    continue
                seen.add((i, j))
                a, b = rows[i], rows[j]
                if a["item_id"] == b["item_id"] and abs(a["start_frame"] - b["start_frame"]) < num_frames:
                    continue                                  # overlapping windows of one video: not copies
                d = distance_bits(a["signature"], b["signature"])
                if d <= max_bits:
                    ri, rj = root(i), root(j)
                    if ri != rj:
                        parent[max(ri, rj)] = min(ri, rj)     # the earlier clip is the group's root
                    best[max(i, j)] = min(best.get(max(i, j), d), d)
    out = []
    for i, r in enumerate(rows):
        k = root(i)
        if k != i:
            out.append({"key": r["key"], "duplicate_of": rows[k]["key"], "distance_bits": int(best.get(i, 0))})
    return out


def write_duplicates(out: str | Path, dups: list[dict]) -> Path:
    """``OUT/dedup/duplicates.parquet`` (atomic; an empty table when there are none)."""
    path = duplicates_path(out)
    table = pa.table({"key": [d["key"] for d in dups], "duplicate_of": [d["duplicate_of"] for d in dups],
                      "distance_bits": pa.array([d["distance_bits"] for d in dups], pa.int32())})
    buf = pa.BufferOutputStream()
    pq.write_table(table, buf)
    atomic_write_bytes(path, buf.getvalue().to_pybytes())
    return path


def dedup_dataset(out: str | Path, max_bits: int, num_frames: int, band_bits: int = 8) -> list[dict]:
    """The one pass at the end of a run: the manifest's signatures → groups → ``dedup/duplicates.parquet``."""
    t = read_manifest(out).select(["key", "item_id", "start_frame", "signature"]).to_pylist()
    dups = find_duplicates(t, max_bits, num_frames, band_bits)
    write_duplicates(out, dups)
    return dups
