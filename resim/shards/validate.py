"""Check one sample against the schema (``resim.shards.schema``): members, dtypes, shapes, metadata.

Used by the writer (refuse before anything is written) and by ``verify`` (check
what was read back). ``sample_problems`` returns human-readable problems; the
writer turns a non-empty list into :class:`SampleError`.
"""
from __future__ import annotations

import functools

import math
import re
from typing import Any

import numpy as np

from resim.shards.schema import (
    COMMAND_SOURCES,
    COMMANDS,
    FORBIDDEN_EXTENSIONS,
    MEMBERS,
    READABLE_SCHEMA_VERSIONS,
    SCHEMA_VERSION,
    SOURCES,
    make_key,
    meta_fields_of,
)
from resim.shards.video import mp4_looks_valid

KEY_RE = re.compile(r"^[A-Za-z0-9_-]+$")
SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
LATENT_DTYPES = {"float16": np.dtype("float16"), "bfloat16": np.dtype("uint16")}  # bf16 stored as uint16 bits

_PY_TYPES = {
    "int": (int,),
    "float": (int, float),
    "str": (str,),
    "bool": (bool,),
    "list": (list,),
    "object": (dict,),
}


class SampleError(ValueError):
    """A sample does not match the schema; ``problems`` lists why."""

    def __init__(self, key: str, problems: list[str]):
        self.key = key
        self.problems = problems
        super().__init__(f"sample {key!r} does not match the shard schema: " + "; ".join(problems))


@functools.lru_cache(maxsize=4096)  # pure, and called per member of every sample a loader reads
def is_forbidden_ext(ext: str) -> bool:
    """True if any dot-separated part of a member extension names a code-executing decoder."""
    return any(part.lower() in FORBIDDEN_EXTENSIONS for part in ext.split("."))


def _type_ok(value: Any, type_spec: str) -> bool:
    for t in type_spec.split("|"):
        if t == "null":
            if value is None:
                return True
            continue
        if isinstance(value, bool) and t != "bool":
            continue  # bool is an int in Python; not in the schema
        if isinstance(value, _PY_TYPES[t]):
            if t == "float" and not math.isfinite(value):
                continue
            return True
    return False


def meta_problems(meta: Any, key: str | None = None) -> list[str]:
    """Problems with a ``meta.json`` object (types, enums, internal consistency)."""
    if not isinstance(meta, dict):
        return [f"meta.json must be a JSON object, got {type(meta).__name__}"]
    p: list[str] = []
    version = meta.get("schema_version")
    version = version if version in READABLE_SCHEMA_VERSIONS else SCHEMA_VERSION   # another: reported below
    fields = meta_fields_of(version)
    names = {f.name for f in fields}
    missing = [f.name for f in fields if f.name not in meta]
    if missing:
        p.append(f"meta.json lacks fields {missing}")
    unknown = sorted(set(meta) - names)
    if unknown:
        p.append(f"meta.json has fields not in schema v{version}: {unknown}")
    for f in fields:
        if f.name in meta and not _type_ok(meta[f.name], f.type):
            p.append(f"meta.{f.name} = {meta[f.name]!r} is not of type {f.type}")
    # a sample from another schema version explains the field problems above: say so first, always
    if "schema_version" in meta and meta["schema_version"] not in READABLE_SCHEMA_VERSIONS:
        p.insert(0, f"meta.schema_version = {meta['schema_version']!r} but this reader knows "
                    f"{', '.join(map(str, READABLE_SCHEMA_VERSIONS))}")
    if p:
        return p  # the checks below assume well-typed fields

    def enum(field: str, allowed, nullable=False):
        v = meta[field]
        if not (v in allowed or (nullable and v is None)):
            p.append(f"meta.{field} = {v!r} is not one of {tuple(allowed)}")

    enum("source", SOURCES)
    enum("command", COMMANDS)
    enum("command_source", COMMAND_SOURCES)
    enum("command_flow", COMMANDS, nullable=True)
    enum("command_trajectory", COMMANDS, nullable=True)
    enum("latent_dtype", tuple(LATENT_DTYPES))
    if key is not None and meta["key"] != key:
        p.append(f"meta.key = {meta['key']!r} differs from the sample key {key!r}")
    if meta["source"] in SOURCES and meta["start_frame"] >= 0:
        expect = make_key(meta["source"], meta["item_id"], meta["start_frame"])
        if meta["key"] != expect:
            p.append(f"meta.key = {meta['key']!r} is not make_key(source, item_id, start_frame) = {expect!r}")
    if meta["start_frame"] < 0:
        p.append(f"meta.start_frame = {meta['start_frame']} < 0")
    if meta["fps_hz"] <= 0:
        p.append(f"meta.fps_hz = {meta['fps_hz']} must be > 0")
    if meta["num_frames"] != meta["num_history_frames"] + meta["num_future_frames"]:
        p.append("meta.num_frames != num_history_frames + num_future_frames")
    for f in ("num_history_frames", "num_future_frames", "height_px", "width_px", "frames_height_px",
              "frames_width_px"):
        if meta[f] < 1:
            p.append(f"meta.{f} = {meta[f]} must be >= 1")
    if meta["is_turning"] != (meta["command"] != "Moving forward"):
        p.append(f"meta.is_turning = {meta['is_turning']} contradicts command {meta['command']!r}")
    if not 0.0 <= meta["confidence"] <= 1.0:
        p.append(f"meta.confidence = {meta['confidence']} outside [0, 1]")
    if meta["balance_weight"] <= 0:
        p.append(f"meta.balance_weight = {meta['balance_weight']} must be > 0")
    if meta["infraction_score"] is not None and not 0.0 <= meta["infraction_score"] <= 1.0:
        p.append(f"meta.infraction_score = {meta['infraction_score']} outside [0, 1]")
    if meta["infractions"] is not None and not all(isinstance(s, str) for s in meta["infractions"]):
        p.append("meta.infractions must be a list of strings")
    for f in ("prompt_id", "null_prompt_id"):
        if not SHA256_RE.match(meta[f]):
            p.append(f"meta.{f} = {meta[f]!r} is not a lowercase sha256 hex digest")
    ls = meta["latent_shape"]
    if len(ls) != 4 or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 1 for d in ls):
        p.append(f"meta.latent_shape = {ls!r} must be 4 positive ints [T_latent, C, h, w]")
    if meta["latent_scaling_factor"] <= 0:
        p.append(f"meta.latent_scaling_factor = {meta['latent_scaling_factor']} must be > 0")
    return p


def sample_problems(sample: dict) -> list[str]:
    """Problems with a decoded sample: ``{"__key__", "meta.json": dict, "latent.npy": ndarray, ...}``.

    Arrays are as stored (bfloat16 latents as uint16 bits); ``frames.mp4`` is bytes.
    Keys starting with ``__`` (``__key__``, ``__url__``) are bookkeeping, not members.
    """
    p: list[str] = []
    key = sample.get("__key__")
    if not isinstance(key, str) or not key:
        return ["sample has no __key__ string"]
    if not KEY_RE.match(key):
        p.append(f"key {key!r} may only contain [A-Za-z0-9_-] (WebDataset splits keys at the first dot)")
    members = {k for k in sample if not k.startswith("__")}
    forbidden = sorted(m for m in members if is_forbidden_ext(m))
    if forbidden:
        p.append(f"members {forbidden} use a code-executing format (forbidden: {FORBIDDEN_EXTENSIONS})")
    unknown = sorted(members - set(MEMBERS) - set(forbidden))
    if unknown:
        p.append(f"members {unknown} are not in the schema (known: {list(MEMBERS)})")
    missing = sorted(e for e, m in MEMBERS.items() if not m.optional and sample.get(e) is None)
    if missing:
        p.append(f"required members {missing} are missing")
    nones = sorted(e for e, m in MEMBERS.items() if m.optional and e in sample and sample[e] is None)
    if nones:
        p.append(f"optional members {nones} are None (leave an absent member out of the sample)")
    meta = sample.get("meta.json")
    mp = meta_problems(meta, key) if meta is not None else []
    p += mp
    meta_ok = meta is not None and not mp

    lat = sample.get("latent.npy")
    if lat is not None:
        if not isinstance(lat, np.ndarray):
            p.append(f"latent.npy must be a numpy array, got {type(lat).__name__}")
        else:
            if lat.ndim != 4:
                p.append(f"latent.npy has shape {lat.shape}; expected 4-D (T_latent, C, h, w)")
            if meta_ok:
                want = LATENT_DTYPES[meta["latent_dtype"]]
                if lat.dtype != want:
                    p.append(f"latent.npy dtype {lat.dtype} but meta.latent_dtype {meta['latent_dtype']!r} "
                             f"needs {want} (bfloat16 is stored as uint16 bits)")
                if list(lat.shape) != list(meta["latent_shape"]):
                    p.append(f"latent.npy shape {list(lat.shape)} != meta.latent_shape {meta['latent_shape']}")
            elif lat.dtype not in LATENT_DTYPES.values():
                p.append(f"latent.npy dtype {lat.dtype} is neither float16 nor uint16 (bfloat16 bits)")
            if lat.dtype == np.float16 and not np.isfinite(lat).all():
                p.append("latent.npy holds non-finite values")

    traj = sample.get("traj.npy")
    if traj is not None:
        if not isinstance(traj, np.ndarray) or traj.dtype != np.float32 or traj.ndim != 2 or traj.shape[1] != 3 \
                or traj.shape[0] < 1:
            p.append(f"traj.npy must be float32 (num_waypoints, 3), got "
                     f"{getattr(traj, 'shape', None)} {getattr(traj, 'dtype', type(traj).__name__)}")
        elif not np.isfinite(traj).all():
            p.append("traj.npy holds non-finite values")
    if meta_ok and meta["has_trajectory"] != (traj is not None):
        p.append(f"meta.has_trajectory = {meta['has_trajectory']} but traj.npy is "
                 f"{'present' if traj is not None else 'absent'}")

    dino = sample.get("dino.npy")
    if dino is not None:
        if not isinstance(dino, np.ndarray) or dino.dtype != np.float16 or dino.ndim != 3:
            p.append(f"dino.npy must be float16 (T_dino, N_tokens, D), got "
                     f"{getattr(dino, 'shape', None)} {getattr(dino, 'dtype', type(dino).__name__)}")
    if meta_ok and (meta["dino_id"] is not None) != (dino is not None):
        p.append(f"meta.dino_id = {meta['dino_id']!r} but dino.npy is {'present' if dino is not None else 'absent'}")

    mp4 = sample.get("frames.mp4")
    if mp4 is not None:
        if not isinstance(mp4, (bytes, bytearray)):
            p.append(f"frames.mp4 must be encoded mp4 bytes (see resim.shards.video.encode_mp4), got {type(mp4).__name__}")
        elif not mp4_looks_valid(mp4):
            p.append("frames.mp4 is not an MP4 file (no ftyp box)")
    return p


def video_problems(frames: np.ndarray, meta: dict) -> list[str]:
    """Problems of decoded frames.mp4 against the metadata (frame count and size)."""
    p = []
    t, h, w, _ = frames.shape
    if t != meta["num_frames"]:
        p.append(f"frames.mp4 has {t} frames, meta.num_frames = {meta['num_frames']}")
    if (h, w) != (meta["frames_height_px"], meta["frames_width_px"]):
        p.append(f"frames.mp4 is {h}x{w}, meta says {meta['frames_height_px']}x{meta['frames_width_px']}")
    return p
