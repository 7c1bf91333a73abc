"""Stage 5: resize/crop to the configured resolution and encode with the CogVideoX VAE.

One sequential decode pass per unit at the training resolution (resize right after decoding, keep the
aspect ratio, centre-crop); overlapping windows share the decoded frames through a ``num_frames``-deep
buffer, so memory is bounded by one clip however long the video. Per kept window:

* ``latent.npy``: one posterior sample x the VAE's scaling factor, ``(T_lat, C, h, w)``, stored as
  ``encode.latent_dtype``; the sample's noise is seeded from the key so reruns write identical bytes;
* ``frames.mp4``: the clip's frames at ``encode.frames_*_px`` (for the reward model, metrics, previews);
* ``traj.npy`` where the source has poses; ``meta.json`` with every field of ``resim.shards.schema.META_FIELDS``.

Outputs go to ``OUT/_staging/<unit_id>/`` (paths, not tensors, travel to the writer). The model is
built once per actor in ``__init__``; it runs on the actor's GPU when Ray gave it one.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from resim import __version__
from resim.config import config_hash, to_dict
from resim.media.encoders import VideoVAE, to_storage
from resim.media.frames import center_crop, clip_frames, cover_size, sliding_windows
from resim.pipeline import quarantine
from resim.pipeline.clip_quality import clip_quality, quality_problem
from resim.pipeline.config import absolute_paths
from resim.pipeline.dedup import clip_signature
from resim.pipeline.stages.base import BadInput
from resim.pipeline.stages.cut import CutStage
from resim.pipeline.units import clip_of
from resim.shards.schema import SCHEMA_VERSION, make_key, prompt_id, prompt_text
from resim.shards.video import encode_mp4


def staging_dir(out: str | Path, unit_id: str) -> Path:
    return Path(out) / "_staging" / unit_id


def data_config_hash(cfg) -> str:
    """Hash of what determines the data (sources, clip, labels, balance, encode, shards), with paths absolute
    (``config.absolute_paths``: a no-op on the runner's config, which is absolute already, on any worker)."""
    d = to_dict(absolute_paths(cfg))
    return config_hash(_without_new_defaults(
        {k: d[k] for k in ("sources", "clip", "labels", "balance", "quality", "encode", "shards")}))


# Config fields added after datasets were made, with the default that reproduces the data made before them:
# left out of the hash at that default, so those datasets keep their hash (a rerun resumes them, and every
# sample's meta.config_hash stays what it was); any other value is hashed like every field.
NEW_FIELD_DEFAULTS = {"max_held_frames": 0,   # ClipConfig, wherever a clip geometry is configured
                      "fork_fraction": 0.0,    # sources.synthetic: no counterfactual forks
                      "pace_fork_fraction": 0.0}   # sources.synthetic: no pace forks


def _without_new_defaults(d):
    if isinstance(d, dict):
        return {k: _without_new_defaults(v) for k, v in d.items()
                if not (k in NEW_FIELD_DEFAULTS and v == NEW_FIELD_DEFAULTS[k])}
    return d


def key_seed(key: str) -> int:
    return int.from_bytes(hashlib.sha256(key.encode()).digest()[:8], "little") & ((1 << 63) - 1)


class EncodeStage(CutStage):
    name = "encode"

    def __init__(self, cfg, progress=None, device: str | None = None):
        super().__init__(cfg, progress)
        # torch only here, in the actor: the driver imports this module (data_config_hash) and stays torch-free
        import torch

        e = self.cfg.encode
        torch.set_num_threads(e.torch_threads)
        self.vae = VideoVAE(e.vae_path, placeholder_seed=e.placeholder_seed, dtype=e.dtype, device=device,
                            slicing=e.vae_slicing, tiling=e.vae_tiling)
        self.config_hash = data_config_hash(self.cfg)

    def process(self, state: dict) -> None:
        cfg, e, enc, clip = self.cfg, state["episode"], self.cfg.encode, clip_of(state)
        N, H = clip.num_frames, clip.num_history_frames
        out_hw = (enc.height_px, enc.width_px)
        prev_hw = (enc.frames_height_px, enc.frames_width_px)
        sel = sorted(state["selected"], key=lambda w: w["start"])
        stage_dir = staging_dir(cfg.out, state["unit_id"])
        if stage_dir.exists():
            shutil.rmtree(stage_dir)                 # a redo after a crash starts clean
        stage_dir.mkdir(parents=True)
        state["clips"], state["staging"] = [], str(stage_dir)
        if not sel:
            return
        ep = self.open(state)
        first, end = sel[0]["start"], sel[-1]["start"] + N
        decode_hw = cover_size(tuple(e["frame_size_hw"]), out_hw)
        t_dec = t_vae = t_mp4 = t_sig = t_qual = 0.0

        def frames():
            nonlocal t_dec
            it = clip_frames(ep, first, end, e["step"], decode_hw)
            while True:
                t0 = time.perf_counter()
                try:
                    f = next(it)
                except StopIteration:
                    return
                finally:
                    t_dec += time.perf_counter() - t0
                yield center_crop(f, out_hw)

        by_start = {w["start"]: w for w in sel}
        pending: list[tuple[dict, np.ndarray]] = []
        keys: list[str] = []
        info = self.vae.info

        def flush():
            nonlocal t_vae, t_mp4, t_sig
            if not pending:
                return
            clips = np.stack([c for _, c in pending])
            ks = [make_key(e["source"], e["item_id"], w["start"]) for w, _ in pending]
            t0 = time.perf_counter()
            latents = self.vae.encode(clips, [key_seed(k) for k in ks])
            t_vae += time.perf_counter() - t0
            for (w, pix), key, lat in zip(pending, ks, latents):
                t0 = time.perf_counter()
                small = pix if prev_hw == out_hw else np.stack(
                    [cv2.resize(f, prev_hw[::-1], interpolation=cv2.INTER_AREA) for f in pix])
                mp4 = encode_mp4(small, clip.fps_hz)
                t_mp4 += time.perf_counter() - t0
                t0 = time.perf_counter()
                sig = clip_signature(pix)                      # near-duplicate search (resim/pipeline/dedup.py)
                t_sig += time.perf_counter() - t0
                stored = to_storage(lat, enc.latent_dtype)
                meta = {
                    "schema_version": SCHEMA_VERSION, "key": key, "source": e["source"], "item_id": e["item_id"],
                    "start_frame": int(w["start"]), "start_s": round(w["start"] / clip.fps_hz, 6),
                    "fps_hz": clip.fps_hz, "num_frames": N, "num_history_frames": H,
                    "num_future_frames": clip.num_future_frames,
                    "height_px": enc.height_px, "width_px": enc.width_px,
                    "frames_height_px": prev_hw[0], "frames_width_px": prev_hw[1],
                    "command": w["command"], "command_source": w["command_source"],
                    "command_flow": w["command_flow"], "command_trajectory": w["command_trajectory"],
                    "commands_agree": (None if w["command_trajectory"] is None
                                       else w["command_flow"] == w["command_trajectory"]),
                    "yaw_deg": float(w["yaw_deg"]), "yaw_deg_flow": float(w["yaw_deg_flow"]),
                    "yaw_deg_trajectory": w["yaw_deg_trajectory"], "confidence": float(w["confidence"]),
                    "is_turning": bool(w["is_turning"]), "balance_weight": float(w["balance_weight"]),
                    "hazard": e["hazard"], "infraction_score": e["infraction_score"], "infractions": e["infractions"],
                    "prompt_id": prompt_id(prompt_text(w["command"])), "null_prompt_id": prompt_id(prompt_text(None)),
                    "vae_id": info.vae_id, "vae_placeholder": info.placeholder, "latent_dtype": enc.latent_dtype,
                    "latent_shape": list(lat.shape), "latent_scaling_factor": info.scaling_factor,
                    "has_trajectory": w["traj"] is not None, "dino_id": None,
                    "pipeline_version": __version__, "config_hash": self.config_hash,
                    "ego_motion_pct_s": w.get("ego_motion_pct_s"), "stopped": w.get("stopped"),
                    "signature": sig, **w["quality"],
                }
                np.save(stage_dir / f"{key}.latent.npy", stored, allow_pickle=False)
                (stage_dir / f"{key}.frames.mp4").write_bytes(mp4)
                if w["traj"] is not None:
                    np.save(stage_dir / f"{key}.traj.npy", np.asarray(w["traj"], dtype=np.float32), allow_pickle=False)
                (stage_dir / f"{key}.meta.json").write_text(json.dumps(meta, sort_keys=True))
                keys.append(key)
            pending.clear()

        dropped: set[int] = set()
        for start, pix in sliding_windows(frames(), first, list(by_start), N):
            if start in by_start:
                w = by_start[start]
                t0 = time.perf_counter()
                w["quality"] = {**clip_quality(pix), "flow_quality": w.get("flow_quality")}
                why = quality_problem(w["quality"], cfg.quality)
                t_qual += time.perf_counter() - t0
                if why is not None:               # quality filters: dropped before the VAE spends anything
                    quarantine.drop_window(state, self.name, start, why)
                    dropped.add(start)
                    continue
                pending.append((w, pix))
                if len(pending) >= enc.batch_size:
                    flush()
        flush()
        if len(keys) + len(dropped) != len(sel):
            raise BadInput(f"decoded frames for {len(keys) + len(dropped)} of {len(sel)} clips (video ends early)")
        if dropped:
            state["selected"] = [w for w in sel if w["start"] not in dropped]
        state["clips"] = keys
        state["staging"] = str(stage_dir)
        kept = sorted(w["start"] for w in sel if w["start"] not in dropped)
        covered, end_f = 0, -1                    # frames in the union of the written windows
        for st in kept:
            covered += st + N - max(st, end_f)
            end_f = st + N
        covered -= max(0, end_f - (e["num_frames"] - e.get("held_frames", 0)))   # held frames are no footage
        state.setdefault("curation", {})["covered_s"] = round(covered / clip.fps_hz, 3)
        for k, v in (("encode.decode", t_dec), ("encode.vae", t_vae), ("encode.mp4", t_mp4),
                     ("encode.signature", t_sig), ("encode.quality", t_qual)):
            state["timings_s"][k] = state["timings_s"].get(k, 0.0) + v
