"""``verify``: check a whole dataset folder; every problem names its shard and key.

Checks, in order:
* leftovers: temporary files of an interrupted writer, tars and manifests
  without an index (uncommitted, e.g. an interrupted write or stale-shard
  removal), indexes whose tar is missing;
* prompt table: every entry's ``.npy`` exists, matches its sha256, decodes to the
  declared dtype/shape, and its id is ``sha256(text)``;
* per shard: size and sha256 against the index; the tar parses; sample count and
  keys equal the index's, **in tar order** and without duplicates (a key listed
  twice in the index, or a sample key repeated within the tar, is an error; an
  order mismatch is reported once, at the first key out of place); the manifest
  has one row per sample with the same keys; the index's label histograms match
  the samples;
* per sample: no forbidden member, every member decodes with the safe decoders,
  the sample matches the schema (members, dtypes, shapes vs meta, meta fields),
  frames.mp4 decodes to meta.num_frames frames of the declared size, and
  ``prompt_id``/``null_prompt_id`` resolve in the prompt table (command prompts
  naming the sample's command);
* keys are unique across the dataset.
"""
from __future__ import annotations

import hashlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pyarrow as pa
import pyarrow.parquet as pq

from resim.shards import layout, safejson
from resim.shards.fsio import is_tmp_name, sha256_file
from resim.shards.npy import NpyError, decode_npy
from resim.shards.prompts import EMBED_DTYPES, PromptTable, PromptTableError
from resim.shards.reader import ShardReadError, decode_sample, iter_raw_shard
from resim.shards.schema import READABLE_SCHEMA_VERSIONS, prompt_id
from resim.shards.validate import sample_problems, video_problems
from resim.shards.video import VideoError, decode_mp4


@dataclass(frozen=True)
class Problem:
    shard: str | None
    key: str | None
    message: str

    def __str__(self) -> str:
        where = []
        if self.shard:
            where.append(f"shard {self.shard}")
        if self.key:
            where.append(f"key {self.key}")
        return f"{' '.join(where) or 'dataset'}: {self.message}"


def _check_prompts(root, problems: list[Problem]) -> dict:
    table = PromptTable(root)
    try:
        entries = table.entries()
    except (OSError, ValueError, KeyError) as e:
        problems.append(Problem(None, None, f"prompt table {table.json_path} unreadable: {e}"))
        return {}
    for pid, e in entries.items():
        where = f"prompt {pid}"
        if prompt_id(e.get("text", "")) != pid:
            problems.append(Problem(None, None, f"{where}: id is not sha256 of its text {e.get('text')!r}"))
        try:
            path = table.file_path(pid)   # confined to prompts/: a hostile "file" is a problem, never opened
        except PromptTableError as err:
            problems.append(Problem(None, None, str(err)))
            continue
        if not path.is_file():
            problems.append(Problem(None, None, f"{where}: embedding file {path} is missing"))
            continue
        try:
            data = table.read_file(pid)   # size checked against the entry before reading
        except (PromptTableError, OSError) as err:
            problems.append(Problem(None, None, f"{where}: {err}" if isinstance(err, OSError) else str(err)))
            continue
        if hashlib.sha256(data).hexdigest() != e.get("npy_sha256"):
            problems.append(Problem(None, None, f"{where}: {path.name} does not match its sha256 in prompts.json"))
            continue
        try:
            arr = decode_npy(data)
        except NpyError as err:
            problems.append(Problem(None, None, f"{where}: {err}"))
            continue
        want = EMBED_DTYPES.get(e.get("dtype"))
        if want is None or arr.dtype != want or list(arr.shape) != list(e.get("shape", [])):
            problems.append(Problem(None, None, f"{where}: holds {arr.dtype}{list(arr.shape)}, table says "
                                                f"{e.get('dtype')}{e.get('shape')}"))
    return entries


def _key_order_problems(shard: str, keys: list[str], ikeys: list[str]) -> list[Problem]:
    """Keys the index lists more than once, and the first key (of those both in the tar and the index) whose
    position in the tar differs from the index's order. ``keys``: the tar's sample keys in order (repeats in
    the tar are reported while reading it); ``ikeys``: the index's ``keys``."""
    out = []
    counts = Counter(ikeys)
    for k in dict.fromkeys(ikeys):   # first-occurrence order
        if counts[k] > 1:
            out.append(Problem(shard, k, f"listed {counts[k]} times in the index (keys must be unique)"))
    common = set(keys) & set(ikeys)
    in_tar = [k for k in dict.fromkeys(keys) if k in common]
    in_index = [k for k in dict.fromkeys(ikeys) if k in common]
    for k, ik in zip(in_tar, in_index):
        if k != ik:
            out.append(Problem(shard, k, f"out of order: sample {keys.index(k)} of the tar, but position "
                                         f"{ikeys.index(k)} in the index, which lists {ik} at {ikeys.index(ik)} "
                                         "(the index lists keys in tar order)"))
            break
    return out


def verify(root, decode_video: bool = True, progress: Callable[[str], None] | None = None) -> list[Problem]:
    """All problems found in dataset ``root`` (empty list: everything holds)."""
    root = Path(root)
    problems: list[Problem] = []
    if not layout.shards_dir(root).is_dir():
        return [Problem(None, None, f"{root} has no shards/ folder")]
    for d in (layout.shards_dir(root), layout.index_dir(root), layout.manifest_dir(root), layout.prompts_dir(root)):
        for p in sorted(d.iterdir()) if d.is_dir() else []:
            if is_tmp_name(p.name):
                problems.append(Problem(None, None, f"leftover temporary file {p} from an interrupted writer "
                                                    "(rerun that work unit, or delete it)"))
    prompts = _check_prompts(root, problems)
    tars = {p.name for p in layout.all_shard_files(root)}
    idx_files = sorted(p for p in layout.index_dir(root).glob("*.json") if not p.name.startswith(".")) \
        if layout.index_dir(root).is_dir() else []
    indexed = {p.stem + ".tar" for p in idx_files}
    for name in sorted(tars - indexed):
        problems.append(Problem(name, None, "shard has no index (uncommitted: its writer was interrupted; "
                                            "rerun that work unit, or delete it)"))
    mdir = layout.manifest_dir(root)
    for mp in sorted(mdir.glob("*.parquet")) if mdir.is_dir() else []:
        shard = mp.stem + ".tar"
        if not mp.name.startswith(".") and shard not in indexed and shard not in tars:
            problems.append(Problem(shard, None, f"manifest {mp.name} has neither an index nor a shard (left by an "
                                                 "interrupted writer; rerun that work unit, or delete it)"))
    seen_keys: dict[str, str] = {}
    for ip in idx_files:
        shard = ip.stem + ".tar"
        if progress:
            progress(shard)
        try:
            index = safejson.load_file(ip)
        except (OSError, ValueError) as e:
            problems.append(Problem(shard, None, f"index {ip} unreadable: {e}"))
            continue
        if not isinstance(index, dict):
            problems.append(Problem(shard, None, f"index {ip} is a JSON {type(index).__name__}, not an object"))
            continue
        if index.get("schema_version") not in READABLE_SCHEMA_VERSIONS:
            problems.append(Problem(shard, None, f"index schema_version {index.get('schema_version')} "
                                                 f"is not one this reader knows ({READABLE_SCHEMA_VERSIONS})"))
        path = layout.shards_dir(root) / shard
        if shard not in tars:
            problems.append(Problem(shard, None, f"index {ip.name} exists but {path} is missing"))
            continue
        sha, nbytes = sha256_file(path)
        if nbytes != index.get("bytes"):
            problems.append(Problem(shard, None, f"size {nbytes} bytes != index {index.get('bytes')} (truncated?)"))
        if sha != index.get("sha256"):
            problems.append(Problem(shard, None, f"sha256 {sha[:16]}... != index {str(index.get('sha256'))[:16]}... "
                                                 "(corrupted or modified)"))
        keys: list[str] = []
        hist = {k: Counter() for k in ("command", "source", "hazard")}
        undecoded = 0   # samples whose members or meta could not be read: the histograms cannot be compared
        try:
            for raw in iter_raw_shard(path):
                key = raw["__key__"]
                keys.append(key)
                if seen_keys.get(key) == shard:
                    problems.append(Problem(shard, key, "duplicate key: a second sample with this key in the shard "
                                                        "(keys must be unique)"))
                elif key in seen_keys:
                    problems.append(Problem(shard, key, f"key also in shard {seen_keys[key]}"))
                seen_keys.setdefault(key, shard)
                try:
                    s = decode_sample(raw, latent_as="stored")
                except ShardReadError as e:
                    problems.append(Problem(shard, key, str(e)))
                    undecoded += 1
                    continue
                for msg in sample_problems(s):
                    problems.append(Problem(shard, key, msg))
                meta = s.get("meta.json")
                if not isinstance(meta, dict):
                    undecoded += 1
                    continue
                # a field of the wrong type (reported by sample_problems above) is counted by its repr: a list or
                # dict is unhashable and would end the whole check with a TypeError
                for name in ("command", "source"):
                    v = meta.get(name)
                    hist[name][v if v is None or isinstance(v, str) else repr(v)] += 1
                h = meta.get("hazard")
                hist["hazard"]["null" if h is None else ("true" if h else "false")] += 1
                for field in ("prompt_id", "null_prompt_id"):
                    pid = meta.get(field)
                    if not isinstance(pid, str):
                        problems.append(Problem(shard, key, f"meta.{field} {pid!r} is not a prompt id (a string)"))
                    elif pid not in prompts:
                        problems.append(Problem(shard, key, f"meta.{field} {pid} does not resolve in the prompt table"))
                    elif field == "prompt_id" and prompts[pid].get("role") == "command" \
                            and prompts[pid].get("command") not in (None, meta.get("command")):
                        problems.append(Problem(shard, key, f"prompt {pid} is for {prompts[pid].get('command')!r}, "
                                                            f"the sample's command is {meta.get('command')!r}"))
                    elif field == "null_prompt_id" and prompts[pid].get("role") != "null":
                        problems.append(Problem(shard, key, f"null_prompt_id {pid} has role "
                                                            f"{prompts[pid].get('role')!r}, not 'null'"))
                if decode_video and isinstance(s.get("frames.mp4"), bytes):
                    try:
                        frames = decode_mp4(s["frames.mp4"])
                    except VideoError as e:
                        problems.append(Problem(shard, key, f"frames.mp4: {e}"))
                    else:
                        if isinstance(meta.get("num_frames"), int):
                            problems += [Problem(shard, key, m) for m in video_problems(frames, meta)]
        except ShardReadError as e:
            problems.append(Problem(shard, None, str(e)))
        n_index = index.get("num_samples")
        if len(keys) != n_index:
            problems.append(Problem(shard, None, f"holds {len(keys)} samples, index says {n_index}"))
        ikeys = index.get("keys") or []
        if len(ikeys) != n_index:
            problems.append(Problem(shard, None, f"index lists {len(ikeys)} keys but num_samples is {n_index}"))
        for k in sorted(set(ikeys) - set(keys)):
            problems.append(Problem(shard, k, "listed in the index but missing from the shard"))
        for k in sorted(set(keys) - set(ikeys)):
            problems.append(Problem(shard, k, "in the shard but not listed in the index"))
        problems += _key_order_problems(shard, keys, ikeys)
        ih = index.get("histograms", {})
        for name, c in hist.items():
            if set(ikeys) == set(keys) and not undecoded and dict(c) != ih.get(name):
                problems.append(Problem(shard, None, f"index histogram {name} {ih.get(name)} != samples {dict(c)}"))
        mp = layout.manifest_path(root, shard)
        if not mp.is_file():
            problems.append(Problem(shard, None, f"manifest {mp} is missing"))
        else:
            try:
                mkeys = pq.read_table(mp, columns=["key"])["key"].to_pylist()
            except (OSError, pa.ArrowException) as e:
                problems.append(Problem(shard, None, f"manifest {mp.name} unreadable: {e}"))
            else:
                if sorted(mkeys) != sorted(ikeys):
                    problems.append(Problem(shard, None, f"manifest has {len(mkeys)} rows whose keys differ from "
                                                         f"the index's {len(ikeys)}"))
    return problems
