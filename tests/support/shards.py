"""Valid dummy samples and datasets for tests (of this package and of the training code).

``make_dummy_sample`` builds a sample that passes the schema: random latents (fp16
or bf16 bits), a real mp4 of moving stripes, an optional trajectory and DINO
features. ``add_dummy_prompts`` fills a prompt table with small random embeddings
for the three commands and the null prompt (marked as placeholders). ``insert_raw_sample``
puts a hand-made sample (any key, any member bytes, members left out or written as links or devices:
:class:`NotRegular`) into a committed shard, as an attacker would.
"""
from __future__ import annotations

import io
import json
import tarfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from resim.shards import layout
from resim.shards.errors import split_member_name
from resim.shards.fsio import sha256_file
from resim.shards.npy import float32_to_bf16_bits
from resim.shards.prompts import PromptTable
from resim.shards.schema import COMMANDS, SCHEMA_VERSION, ClipSpec, make_key, prompt_id, prompt_text
from resim.shards.video import encode_mp4
from resim.shards.writer import ShardWriter

DUMMY_ENCODER_ID = "placeholder-t5-random"


def dummy_frames(num_frames: int, height_px: int, width_px: int, yaw_deg: float = 0.0, seed: int = 0) -> np.ndarray:
    """(T, H, W, 3) uint8 RGB: vertical stripes drifting sideways (as if turning by ``yaw_deg`` overall)."""
    rng = np.random.default_rng(seed)
    base = rng.integers(40, 220, size=3)
    x = np.arange(width_px)[None, :]
    y = np.arange(height_px)[:, None]
    out = np.empty((num_frames, height_px, width_px, 3), np.uint8)
    for t in range(num_frames):
        shift = -yaw_deg * t / max(num_frames - 1, 1) * width_px / 60.0
        stripes = (np.sin((x + shift) * 2 * np.pi / 16.0) * 60).astype(np.int32)
        sky = (y < height_px // 2).astype(np.int32) * 40
        for c in range(3):
            out[t, :, :, c] = np.clip(base[c] + stripes + sky, 0, 255)
    return out


def dummy_trajectory(yaw_deg: float, num_waypoints: int = 8, dt_s: float = 0.5, speed_mps: float = 8.0):
    """(N, 3) float32 constant-speed constant-curvature path ending at heading ``yaw_deg`` (left +)."""
    t = np.arange(1, num_waypoints + 1) * dt_s
    total_t = t[-1]
    yaw = np.deg2rad(yaw_deg) * t / total_t
    rate = np.deg2rad(yaw_deg) / total_t
    if abs(rate) < 1e-9:
        x, y = speed_mps * t, np.zeros_like(t)
    else:
        r = speed_mps / rate
        x, y = r * np.sin(yaw), r * (1 - np.cos(yaw))
    return np.stack([x, y, yaw], -1).astype(np.float32)


def make_dummy_sample(source: str = "synthetic", item_id: str = "dummy/episode-0", start_frame: int = 0, *,
                      command: str = "Moving forward", yaw_deg: float | None = None, seed: int = 0,
                      spec: ClipSpec | None = None, latent_channels: int = 4, latent_hw: tuple[int, int] = (4, 6),
                      latent_dtype: str = "float16", frames_hw: tuple[int, int] = (32, 48),
                      with_trajectory: bool = True, with_dino: bool = False, hazard: bool | None = None,
                      config_hash: str = "dummy") -> dict:
    """A valid sample dict for ``ShardWriter.write`` (random latent; real mp4; placeholder ids)."""
    spec = spec or ClipSpec()
    if command not in COMMANDS:
        raise ValueError(f"unknown command {command!r}")
    rng = np.random.default_rng(seed)
    if yaw_deg is None:
        yaw_deg = {"Turning left": 30.0, "Moving forward": 0.5, "Turning right": -30.0}[command]
    key = make_key(source, item_id, start_frame)
    shape = (spec.num_latent_frames, latent_channels, *latent_hw)
    lat32 = rng.standard_normal(shape).astype(np.float32)
    if latent_dtype == "float16":
        latent = lat32.astype(np.float16)
    elif latent_dtype == "bfloat16":
        latent = float32_to_bf16_bits(lat32)
    else:
        raise ValueError(f"latent_dtype must be float16 or bfloat16, got {latent_dtype!r}")
    h, w = frames_hw
    frames = dummy_frames(spec.num_frames, h, w, yaw_deg, seed)
    meta = {
        "schema_version": SCHEMA_VERSION, "key": key, "source": source, "item_id": item_id,
        "start_frame": start_frame, "start_s": start_frame / spec.fps_hz, "fps_hz": spec.fps_hz,
        "num_frames": spec.num_frames, "num_history_frames": spec.num_history_frames,
        "num_future_frames": spec.num_future_frames, "height_px": latent_hw[0] * 8, "width_px": latent_hw[1] * 8,
        "frames_height_px": h, "frames_width_px": w, "command": command,
        "command_source": "trajectory" if with_trajectory else "flow",
        "command_flow": command, "command_trajectory": command if with_trajectory else None,
        "commands_agree": True if with_trajectory else None, "yaw_deg": float(yaw_deg),
        "yaw_deg_flow": float(yaw_deg), "yaw_deg_trajectory": float(yaw_deg) if with_trajectory else None,
        "confidence": 0.9, "is_turning": command != "Moving forward",
        "balance_weight": 5.0 if command != "Moving forward" else 1.0,
        "hazard": hazard, "infraction_score": None if hazard is None else (0.4 if hazard else 1.0),
        "infractions": None if hazard is None else (["collision_vehicle"] if hazard else []),
        "prompt_id": prompt_id(prompt_text(command)), "null_prompt_id": prompt_id(prompt_text(None)),
        "vae_id": "placeholder-tiny-random", "vae_placeholder": True, "latent_dtype": latent_dtype,
        "latent_shape": list(shape), "latent_scaling_factor": 1.15258426, "has_trajectory": with_trajectory,
        "dino_id": "placeholder-dinov2-random" if with_dino else None, "pipeline_version": "test",
        "config_hash": config_hash, "ego_motion_pct_s": 8.0, "stopped": False,
        "signature": None, "luma_mean_8bit": float(frames.mean()), "luma_std_8bit": float(frames.std()),
        "sharpness_lapvar": 100.0, "static_edge_frac": 0.0, "flow_quality": 1.0,
    }
    sample = {"__key__": key, "meta.json": meta, "latent.npy": latent, "frames.mp4": encode_mp4(frames, spec.fps_hz)}
    if with_trajectory:
        sample["traj.npy"] = dummy_trajectory(yaw_deg, spec.num_waypoints, spec.waypoint_dt_s)
    if with_dino:
        sample["dino.npy"] = rng.standard_normal((spec.num_frames, 5, 8)).astype(np.float16)
    return sample


def add_dummy_prompts(root, seq_len: int = 16, dim: int = 32, dtype: str = "bfloat16", seed: int = 0) -> dict:
    """Add random (seq_len, dim) embeddings for the three commands and the null prompt; return text -> id."""
    table = PromptTable(root)
    rng = np.random.default_rng(seed)
    ids = {}
    for command in (*COMMANDS, None):
        emb = rng.standard_normal((seq_len, dim)).astype(np.float32)
        emb[seq_len // 2:] = 0.0  # padding positions, as a T5 encoder's padded output would hold
        emb = float32_to_bf16_bits(emb) if dtype == "bfloat16" else emb.astype(dtype)
        text = prompt_text(command)
        ids[text] = table.add(text, emb, "null" if command is None else "command", DUMMY_ENCODER_ID,
                              dtype=dtype, placeholder=True, num_tokens=seq_len // 2)
    return ids


def write_dummy_dataset(root, num_samples: int = 12, prefix: str = "dummy", max_samples_per_shard: int = 5,
                        seed: int = 0, **sample_kw):
    """Write ``num_samples`` dummy samples (commands cycling) plus the prompt table; return the ShardInfos."""
    add_dummy_prompts(root, seed=seed)
    with ShardWriter(root, prefix, max_samples_per_shard=max_samples_per_shard, config_hash="dummy") as w:
        for i in range(num_samples):
            w.write(make_dummy_sample(item_id=f"dummy/episode-{seed}-{i // 4}", start_frame=(i % 4) * 10,
                                      command=COMMANDS[i % 3], seed=seed * 1000 + i, **sample_kw))
    return w.close()


@dataclass(frozen=True)
class NotRegular:
    """An ``insert_raw_sample`` override: the member is written as a tar link or device, not as a file."""

    type: bytes       # tarfile.SYMTYPE, tarfile.LNKTYPE, tarfile.CHRTYPE, ...
    target: str = ""  # the link's target


def insert_raw_sample(root, shard: str, key: str, overrides: dict[str, bytes | NotRegular | None] | None = None, *,
                      first: bool = True) -> str:
    """Put a sample into committed ``shard`` of dataset ``root`` as a hand-made hostile dataset would: the members
    of the shard's first sample with ``overrides`` applied (ext -> bytes, a :class:`NotRegular` link or device, or
    None: the member is left out), under ``key`` as given (no schema check:
    ``../../x`` or ``/tmp/x`` go in as they are), before (``first``) or after the others. The manifest gets a row
    for it and the index its key, count, size and sha256, so tar, manifest and index agree and only the sample
    itself is bad. Returns ``key``."""
    path = layout.shards_dir(root) / shard
    with tarfile.open(path) as t:
        old = [(m.name, t.extractfile(m).read()) for m in t.getmembers() if m.isfile()]
    first_key = split_member_name(old[0][0])[0]
    members = {split_member_name(n)[1]: d for n, d in old if split_member_name(n)[0] == first_key}
    members.update(overrides or {})
    new = [(f"{key}.{ext}", data) for ext, data in members.items() if data is not None]
    with tarfile.open(path, "w", format=tarfile.PAX_FORMAT) as t:
        for name, data in (new + old if first else old + new):
            info = tarfile.TarInfo(name)
            if isinstance(data, NotRegular):
                info.type, info.linkname = data.type, data.target
                t.addfile(info)
                continue
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
    mp = layout.manifest_path(root, shard)
    table = pq.read_table(mp)
    rows = table.to_pylist()
    row = dict(rows[0], key=key)
    pq.write_table(pa.Table.from_pylist([row] + rows if first else rows + [row], schema=table.schema), mp)
    idx = layout.read_index(root, shard)
    idx["keys"] = [key] + idx["keys"] if first else idx["keys"] + [key]
    idx["num_samples"] += 1
    idx["sha256"], idx["bytes"] = sha256_file(path)
    layout.index_path(root, shard).write_text(json.dumps(idx, indent=1, sort_keys=True) + "\n")
    return key


def write_data_encode(folder, vae: str = "placeholder-cogvideox-vae-tiny") -> None:
    """The ``data_encode.yaml`` a trained export carries (``resim.sample.load.ENCODE_FILE``): which VAE encoded the
    model's latents. Hand-made test checkpoints write it as training does; without it loading refuses to guess."""
    (Path(folder) / "data_encode.yaml").write_text(f"encode:\n  vae: {vae}\n")
