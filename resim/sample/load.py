"""Loading what a sampling run needs: the trained world model, the history latents, prompt embeddings.

World-model checkpoint (the trainer's export): ``RUN_DIR/final/`` (or ``RUN_DIR`` itself, or the
``final`` folder) holding ``config.yaml`` (the resolved ``RunConfig``: ``model_name`` + ``model`` dict) and
``model.safetensors`` (+ ``ema.safetensors``, preferred for sampling when present). The model is built through
``resim.models.registry`` by ``model_name`` ("world": ``resim.train.tasks.world_model.build_world``, the same builder training used,
so LoRA layers and overrides match the saved tensors), then the saved weights are loaded strictly; finding,
checking and loading are ``resim.models.exported``'s, shared with the IDM and the reward model.

History: a video file (resampled to the clip rate the model was trained at, 10 Hz for video sources, then its
last ``1 + r (H - 1)`` frames, r the VAE's temporal ratio, resized, encoded with the VAE) or a shard sample key (its
stored latents' first ``H`` latent frames, i.e. the clip's history, and its pixel frames for outputs; the shard's
own rate).
Prompts: the dataset's prompt table when it holds the prompt, else the T5 encoder.
"""
from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import yaml

from resim.config import from_dict, safe_yaml
from resim.diffusion.config import ObjectiveConfig
from resim.media.encoders import TextEncoder
from resim.media.files import NotARegularFile, check_regular
from resim.media.frames import MIN_RATE_SLACK, cover_crop   # the pipeline's rules: a history is resampled and cropped as clips were
from resim.models.exported import ExportError, find_export, load_exported, read_config
from resim.models.world.lora import to_peft_layout
from resim.sample.plan import CANDIDATE_NAMES, make_candidate
from resim.shards.prompts import PromptTable, PromptTableError
from resim.shards.reader import ShardReadError, find_sample
from resim.shards.schema import (latent_frame_count, pixel_frame_count, prompt_id, prompt_text,
                           temporal_compression_of)
from resim.shipped import PLACEHOLDER_VAE, shipped_dir, shipped_model


class SamplingInputError(ValueError):
    """A checkpoint, history or prompt given to the sampler is missing or unusable (names it and why)."""


def check_finite(x: torch.Tensor | np.ndarray, what: str) -> None:
    """``SamplingInputError`` naming ``what`` where ``x`` holds NaN or inf: a rollout from it would be NaN (or
    garbage) with exit 0, so every input of ``sample``/``plan``/``simulate`` passes here first."""
    t = torch.as_tensor(x)
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):
        n = int((~torch.isfinite(t)).sum())
        raise SamplingInputError(f"{what}: {n} of {t.numel()} values are NaN or inf; refusing to sample from it")


# Video sources are cut into clips at 10 Hz (ReSim; OpenDV-YouTube toolkit; configs/pipeline/opendv.yaml
# clip.fps_hz), so one latent frame = 4 pixel frames = 0.4 s (ObjectiveConfig.latent_frame_dt_s). The fallback
# when the model states no time scale; see video_clip_fps_hz.
VIDEO_CLIP_FPS_HZ = 10.0


def video_clip_fps_hz(objective: Any, temporal_compression: int = 4) -> float:
    """The pixel frame rate the world model was trained at for video histories: ``temporal_compression /
    objective.latent_frame_dt_s`` of the run's objective (``run_objective(checkpoint)``;
    4 / 0.4 s = 10 Hz), else 10 Hz."""
    dt = getattr(objective, "latent_frame_dt_s", None)
    return temporal_compression / float(dt) if dt else VIDEO_CLIP_FPS_HZ


def _checkpoint_dir(ckpt: str | Path) -> Path:
    """The folder of a world-model export: a run folder, its final/, or a shipped model's name (synth-world)."""
    try:
        return find_export(ckpt, shipped=True)
    except ExportError as e:
        raise SamplingInputError(f"checkpoint {e} (the trainer writes them at the end of a run)") from None


def load_world_model(ckpt: str | Path, device: str = "cpu", dtype: torch.dtype = torch.float32,
                     prefer_ema: bool = True) -> tuple[Any, dict]:
    """Build + load the world model of a training run (``resim.models.exported``); returns (model in eval mode, info
    dict). A config without ``model_name`` is a world model's."""
    _checkpoint_dir(ckpt)   # its own message when the files are not there

    def without_init_weights(model_cfg: dict, state: Any) -> dict:
        # the previous stage's weights are replaced by this checkpoint's anyway; don't require that file here
        return {**model_cfg, "init_weights": None} if "init_weights" in model_cfg else model_cfg

    try:
        ex = load_exported(ckpt, shipped=True, default_name="world", prefer_ema=prefer_ema,
                           adapt_config=without_init_weights,
                           adapt_state=to_peft_layout)   # LoRA saved before peft: its keys renamed
    except ExportError as e:
        raise SamplingInputError(f"checkpoint {e}") from None
    # once at load (a pass over the weights, ~1 ms per MB): NaN weights gave all-NaN rollouts with no warning
    bad = [n for n, t in [*ex.model.named_parameters(), *ex.model.named_buffers()]
           if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if bad:
        raise SamplingInputError(f"checkpoint {ex.folder / ex.weights.name}: {len(bad)} weight tensors hold NaN or "
                                 f"inf (first: {bad[0]}); the run that wrote it diverged or the file is corrupt")
    model = ex.model.to(device=device, dtype=dtype).eval().requires_grad_(False)
    return model, {"checkpoint": str(ex.folder), "weights": ex.weights.name, "builder": f"registry:{ex.model_name}",
                   "model_name": ex.model_name}


SAMPLING_KEY = "sampling"   # a distilled student's export: how to sample it (resim/train/tasks/distill.py)


def sampling_defaults(ckpt: str | Path) -> dict:
    """The ``sampling`` section of a world-model export, ``{}`` when it has none: a distilled student's
    ``num_steps`` and ``guidance`` ("none"), which the samplers use where the command line does not say otherwise."""
    try:
        raw = read_config(find_export(ckpt, shipped=True), default_name="world").raw
    except ExportError:
        return {}
    sec = raw.get(SAMPLING_KEY) or {}
    return dict(sec) if isinstance(sec, dict) else {}


def resolve_steps_and_guidance(ckpt: str | Path, steps: int | None, preset: str, no_guidance: bool,
                               guidance_scale: float | None) -> tuple[int | None, str, str]:
    """(DDIM steps or None = the preset's, guidance preset name, where they came from) for a sampling command:
    the command line first, then the checkpoint's ``sampling`` section (a distilled student: its own steps, no
    guidance), then the rollout preset's."""
    d = sampling_defaults(ckpt)
    if steps is None and d.get("num_steps") is not None:
        steps = int(d["num_steps"])
    if no_guidance:
        guidance = "none"
    elif guidance_scale is None and d.get("guidance") == "none":
        guidance = "none"
    else:
        guidance = preset
    origin = (f"distilled student of {d.get('distilled_from', '?')}: {d.get('num_steps')} steps, guidance "
              f"{d.get('guidance')} (its config's sampling section)") if d else ""
    return steps, guidance, origin


def run_objective(ckpt: str | Path) -> ObjectiveConfig:
    """The diffusion objective a checkpoint's run trained with, from its saved config (not from the model object):
    its ``schedule`` is what the sampler steps over, its ``latent_frame_dt_s`` the time between latent frames."""
    try:
        cfg = read_config(_checkpoint_dir(ckpt), default_name="world")
    except ExportError as e:
        raise SamplingInputError(f"checkpoint {e}") from None
    return from_dict(ObjectiveConfig, cfg.model.get("objective") or {}, prefix="model.objective")


@dataclass
class History:
    latents: torch.Tensor             # (1, H, C, h, w) float32
    frames: np.ndarray | None         # (1 + r (H - 1), H_px, W_px, 3) uint8: the pixel history, for outputs
    fps_hz: float
    source: str                       # what it came from
    prompt_root: Path | None = None   # dataset whose prompt table can be used
    meta: dict | None = None
    trajectory: np.ndarray | None = None   # (8, 3) a shard clip's traj.npy: the recorded future after the history


def history_from_shard(root: str | Path, key: str, num_latent_frames: int) -> History:
    try:
        s = find_sample(root, key, decode_video=True, attach_prompts=False)
    except KeyError as e:
        raise SamplingInputError(f"history {key!r}: not found in dataset {root}") from e
    except ShardReadError as e:   # a corrupt or hostile sample (a JSON bomb, a manifest naming a shard outside)
        raise SamplingInputError(f"history {key!r}: {e}") from None
    meta = s["meta.json"]
    lat = np.asarray(s["latent.npy"], dtype=np.float32)
    check_finite(lat, f"history {key!r} of {root}: latent.npy")
    tc = temporal_compression_of(int(meta["num_frames"]), lat.shape[0])   # the VAE that encoded this dataset
    h_meta = latent_frame_count(int(meta["num_history_frames"]), tc)
    if num_latent_frames > h_meta:
        raise SamplingInputError(f"history {key!r}: asks for {num_latent_frames} latent history frames, the clip's "
                                 f"history has {h_meta} ({meta['num_history_frames']} pixel frames)")
    lat = lat[h_meta - num_latent_frames:h_meta]
    px = pixel_frame_count(h_meta, tc)
    frames = s.get("frames")
    frames = frames[px - pixel_frame_count(num_latent_frames, tc):px] if frames is not None else None
    traj = s.get("traj.npy")
    if traj is not None:
        check_finite(np.asarray(traj, np.float32), f"history {key!r} of {root}: traj.npy")
    return History(torch.from_numpy(lat)[None], frames, float(meta["fps_hz"]), f"shard:{key}", Path(root), meta,
                   None if traj is None else np.asarray(traj, np.float32))


def history_from_video(path: str | Path, vae: Any, num_latent_frames: int, size_hw: tuple[int, int],
                       clip_fps_hz: float = VIDEO_CLIP_FPS_HZ) -> History:
    """The last ``1 + r (H - 1)`` frames (``r``: the VAE's temporal ratio) of a video file at ``clip_fps_hz``,
    resized to ``size_hw``, encoded by ``vae`` (VideoVAE). The model learnt motion at the training clip rate (a 9-frame history spans 0.8 s at 10 Hz),
    so the file is resampled first, as the pipeline's OpenDV reader does: clip frame k takes the source frame
    nearest to its time, counted back from the last frame (the "now" the rollout continues from). A file slower
    than the clip rate is refused: its missing frames would have to be invented."""

    p = Path(path)
    try:
        check_regular(p)
    except NotARegularFile as e:
        raise SamplingInputError(f"history {e} (give a video file or --shards ROOT with a sample key)") from None
    if not clip_fps_hz > 0:
        raise ValueError(f"clip_fps_hz must be > 0, got {clip_fps_hz}")  # our bug: the caller derives it
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise SamplingInputError(f"history {p}: cannot be opened as a video")
    src_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    if not (math.isfinite(src_fps) and src_fps > 0):
        cap.release()
        raise SamplingInputError(f"history {p}: the file states no frame rate; cannot resample it to the "
                                 f"{clip_fps_hz:g} Hz the model was trained at (re-mux it with a frame rate)")
    if src_fps < clip_fps_hz * (1 - MIN_RATE_SLACK):
        cap.release()
        raise SamplingInputError(f"history {p}: {src_fps:g} fps is below the {clip_fps_hz:g} Hz clip rate the "
                                 f"model was trained at; give a video of at least {clip_fps_hz:g} fps")
    step = max(src_fps / clip_fps_hz, 1.0)   # source frames per clip frame (>= 1 within the slack)
    need = pixel_frame_count(num_latent_frames, vae.info.temporal_compression)
    back = [round((need - 1 - k) * step) for k in range(need)]    # source frames before the last one
    buf: deque = deque(maxlen=back[0] + 1)   # only the tail is kept: long files need no memory for the rest
    n = 0
    ok, fr = cap.read()
    while ok:
        buf.append(fr)
        n += 1
        ok, fr = cap.read()
    cap.release()
    if n < back[0] + 1:
        raise SamplingInputError(f"history {p}: {n} readable frames at {src_fps:g} fps ({n / src_fps:.2f} s); "
                                 f"{need} frames at {clip_fps_hz:g} Hz need {back[0] + 1} "
                                 f"({(need - 1) / clip_fps_hz:.2f} s)")
    last = len(buf) - 1
    # the pipeline's clip geometry (cover-resize keeping the aspect ratio, centre crop): a 16:9 dashcam frame
    # is not squeezed into the training clips' shape
    clip = np.stack([cv2.cvtColor(cover_crop(buf[last - d], tuple(size_hw)), cv2.COLOR_BGR2RGB) for d in back])
    lat = vae.encode(clip[None], seeds=[0])
    check_finite(lat, f"history {p}: its latents from the VAE")
    return History(torch.from_numpy(lat), clip, float(clip_fps_hz), f"video:{p.name}",
                   meta={"source_fps_hz": src_fps, "clip_fps_hz": float(clip_fps_hz)})


class PromptSource:
    """Command → T5 embedding ``(1, L, D)``: from the dataset's prompt table if present, else encoded by T5."""

    def __init__(self, prompt_root: Path | None = None, text_encoder_dir: str | Path | None = None,
                 device: str = "cpu", max_tokens: int = 226):
        self.table = None
        if prompt_root is not None:
            self.table = PromptTable(prompt_root)
        self.encoder_dir, self.device, self.max_tokens = text_encoder_dir, device, max_tokens
        self._encoder = None
        self.used: dict[str, str] = {}

    def __call__(self, command: str | None) -> torch.Tensor:
        text = prompt_text(command)
        pid = prompt_id(text)
        try:
            if self.table is not None and pid in self.table.ids():
                self.used[text] = "prompt_table"
                emb = torch.from_numpy(np.array(self.table.get(pid, as_float32=True)))[None]
                check_finite(emb, f"prompt {text!r}: its embedding in {self.table.root}/prompts")
                return emb
        except PromptTableError as e:   # prompts.json naming a file outside prompts/, a bad size, ...
            raise SamplingInputError(str(e)) from None
        if self.encoder_dir is None:
            raise SamplingInputError(f"prompt {text!r} is not in the dataset's prompt table and no --text-encoder "
                                     "was given to encode it")
        if self._encoder is None:
            self._encoder = TextEncoder(self.encoder_dir, device=self.device, max_tokens=self.max_tokens)
        self.used[text] = f"t5:{self._encoder.info.encoder_id}"
        emb = torch.from_numpy(self._encoder.encode([text]))
        check_finite(emb, f"prompt {text!r}: its T5 embedding from {self.encoder_dir}")
        return emb


def load_trajectory(spec: str | None) -> np.ndarray | None:
    """``--trajectory``: a candidate name (keep_lane, turn_left, …), a .npy file (8, 3), or JSON [[x, y, yaw], …]
    inline or in a .json file."""
    if spec is None:
        return None
    if spec in CANDIDATE_NAMES:
        return make_candidate(spec).trajectory
    p = Path(spec)
    if p.suffix.lower() == ".npy" and p.is_file():
        arr = np.load(p, allow_pickle=False)
    else:
        text = p.read_text() if p.suffix.lower() == ".json" and p.is_file() else spec   # a .json file or inline
        try:
            arr = np.asarray(json.loads(text), dtype=np.float32)
        except (json.JSONDecodeError, ValueError) as e:
            raise SamplingInputError(f"--trajectory {spec!r}: not a candidate name ({', '.join(CANDIDATE_NAMES)}), "
                                     f"a .npy file or JSON waypoints: {e}") from e
    arr = np.asarray(arr, dtype=np.float32)
    if arr.ndim != 2 or arr.shape[1] != 3 or not np.isfinite(arr).all():
        raise SamplingInputError(f"--trajectory {spec!r}: expected finite (num_waypoints, 3) [x m, y m, yaw rad], "
                                 f"got shape {arr.shape}")
    return arr


ENCODE_FILE = "data_encode.yaml"   # RUN/final/: the ``encode`` section of the training data's pipeline config


def _data_files(checkpoint: str | Path | None, shards: str | Path | None) -> list[Path]:
    """Where the training data's config is stated, first match wins: ``shards``' pipeline ``config.yaml``, then the
    world model's :data:`ENCODE_FILE` (in the export folder or the run's ``final/``)."""
    paths = [Path(shards) / "config.yaml"] if shards is not None else []
    if checkpoint is not None:
        paths += [d / ENCODE_FILE for d in (Path(shipped_model(checkpoint)), Path(shipped_model(checkpoint)) / "final")]
    return paths


def _read_data_config(path: Path) -> Any:
    """The parsed YAML of a pipeline config or :data:`ENCODE_FILE`; None when the file is absent."""
    if not path.is_file():
        return None
    try:
        d = safe_yaml(path.read_text())
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as e:
        raise SamplingInputError(f"{path}: unreadable ({e}); pass --vae") from None
    return d


def _encode_section(path: Path) -> dict | None:
    """The ``encode`` mapping of a pipeline config (``path`` = DATASET/config.yaml) or of ``RUN/final/`` +
    :data:`ENCODE_FILE`; None when the file is absent."""
    if not path.is_file():
        return None
    d = _read_data_config(path)
    enc = d.get("encode", d) if isinstance(d, dict) else None
    if not isinstance(enc, dict):
        raise SamplingInputError(f"{path}: no encode section; pass --vae")
    return enc


def trained_clip_fps_hz(checkpoint: str | Path | None = None, shards: str | Path | None = None) -> float | None:
    """The clip rate (Hz) the model's training clips were cut at (the ``clip`` section of :func:`_data_files`; the
    trainer records it in :data:`ENCODE_FILE`); None when none says (older runs: :func:`video_clip_fps_hz`)."""
    for path in _data_files(checkpoint, shards):
        d = _read_data_config(path)
        clip = d.get("clip") if isinstance(d, dict) else None
        fps = clip.get("fps_hz") if isinstance(clip, dict) else None
        if isinstance(fps, (int, float)) and not isinstance(fps, bool):
            if not (math.isfinite(fps) and fps > 0):
                raise SamplingInputError(f"{path}: clip.fps_hz must be a finite number > 0, got {fps!r}")
            return float(fps)
    return None


def trained_size_hw(checkpoint: str | Path | None = None, shards: str | Path | None = None) -> tuple[int, int] | None:
    """(H, W) pixels of the clips the latents were encoded from (``shards``' pipeline config, else the world
    model's ``final/data_encode.yaml``); None when neither says. A history video must be encoded at this size."""
    for path in _data_files(checkpoint, shards):
        enc = _encode_section(path)
        if enc is not None and isinstance(enc.get("height_px"), int) and isinstance(enc.get("width_px"), int):
            return int(enc["height_px"]), int(enc["width_px"])
    return None


def encoded_with(checkpoint: str | Path | None = None, shards: str | Path | None = None) -> Path:
    """The VAE folder the latents were encoded with: that of ``shards`` (its pipeline ``config.yaml``), else
    that of the world model's training data (``RUN/final/data_encode.yaml``, written at the end of training); an
    ``encode.vae`` of null there is the pipeline's default, the shipped placeholder. Neither file: an error, not a
    guess. Rollouts must be decoded by the VAE whose latents the model learnt."""
    files = _data_files(checkpoint, shards)
    enc = next((e for e in map(_encode_section, files) if e is not None), None)
    if enc is None:
        raise SamplingInputError(f"no file says which VAE encoded the model's latents (looked for "
                                 f"{', '.join(str(f) for f in files) or 'nothing: no checkpoint or shards'}); "
                                 "pass --vae with its folder")
    vae = enc.get("vae")
    path = shipped_model(vae) if vae else shipped_dir(PLACEHOLDER_VAE)
    if not Path(path).is_dir():
        raise SamplingInputError(f"the latents were encoded with the VAE {vae}, which is not on this machine; "
                                 "pass --vae with its folder")
    return Path(path)


def check_same_encoding(checkpoint: str | Path, shards: str | Path | None) -> None:
    """Refuse a dataset whose latents come from another VAE than the one the model learnt: its histories would be
    read in a latent space the model never saw, and its rollouts decoded by the wrong decoder. Checked where both
    the dataset (``config.yaml``) and the model (``data_encode.yaml``) name their VAE."""
    if shards is None:
        return
    data = _encode_section(Path(shards) / "config.yaml")
    model = next((e for e in map(_encode_section, _data_files(checkpoint, None)) if e is not None), None)
    dv, mv = (data or {}).get("vae"), (model or {}).get("vae")
    if dv and mv and Path(shipped_model(dv)).resolve() != Path(shipped_model(mv)).resolve():
        raise SamplingInputError(f"dataset {shards} was encoded with the VAE {dv}, the world model {checkpoint} "
                                 f"learnt the latents of {mv}: encode the dataset with {mv} (or evaluate a model "
                                 f"trained on {dv})")

