"""A trained world model as one object: the network with everything a rollout needs, loaded in one call.

In the habit of diffusers' pipelines (``DiffusionPipeline.from_pretrained``): a run folder, its ``final/`` or a
shipped name (``synth-world``) gives

* ``model``: the network (eval mode, on the device);
* ``objective``: the diffusion objective the run trained with (its noise schedule is what DDIM steps over);
* ``vae``: the VAE that encoded the model's training clips (its ``final/data_encode.yaml``): rollouts are decoded
  by the VAE whose latents the model learnt, and a video history is encoded by it;
* ``prompts``: command → T5 embedding (the dataset's prompt table when a history comes from shards, else the
  text encoder);
* ``size_hw`` / ``clip_fps_hz``: the size and rate of the training clips, which a video history is resampled to;
* ``sampling``: the export's own sampling defaults (a distilled student: its steps, no guidance).

From Python::

    from resim.sample.bundle import WorldModelBundle
    wm = WorldModelBundle.from_pretrained("synth-world")
    out = wm.rollout("history.mp4", command="Turning left", seconds=2.0, steps=20)
    out.frames          # (T, H, W, 3) uint8: the history's frames, then the imagined future

``resim sample`` and ``resim plan`` build their set-up from this object (``resim.sample.cli``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from resim.media.encoders import MissingWeightsError, VideoVAE
from resim.sample.load import (History, PromptSource, SamplingInputError, check_same_encoding, encoded_with,
                               history_from_shard, history_from_video, load_world_model, run_objective,
                               trained_clip_fps_hz, trained_size_hw, video_clip_fps_hz)
from resim.sample.outputs import decode_rollout
from resim.sample.rollout import Condition, RolloutConfig, ddim_schedule, rollout, rollout_num_future_frames
from resim.sample.compile import maybe_compile
from resim.sample.settings import DEFAULT_TEXT_ENCODER, Settings, rollout_config_for
from resim.shards.schema import COMMANDS, pixel_frame_count


class BundleLoadError(SamplingInputError):
    """A part of the bundle that cannot be loaded; ``part`` names it ("checkpoint" or "vae") for the CLI's
    one-line error (``--checkpoint: ...``)."""

    def __init__(self, part: str, message: str):
        super().__init__(message)
        self.part = part


@dataclass
class Rollout:
    """What :meth:`WorldModelBundle.rollout` returns."""
    frames: np.ndarray           # (T_px, H, W, 3) uint8 RGB: the history's pixel frames, then the future's
    latents: torch.Tensor        # (T_lat, C, h, w) float32: history then generated latent frames
    num_history_frames_px: int   # the first frames of ``frames`` that are the given history
    fps_hz: float                # the frame rate of ``frames``
    labels: list[str]            # each round's condition, e.g. its command


class WorldModelBundle:
    """A world model and its encoding, sampling defaults and prompts; see the module docstring."""

    def __init__(self, model: Any, objective: Any, vae: VideoVAE, *, checkpoint: str, info: dict,
                 text_encoder: str | Path | None, size_hw: tuple[int, int], clip_fps_hz: float | None,
                 device: str, shards: str | Path | None = None):
        self.model, self.objective, self.vae = model, objective, vae
        self.checkpoint, self.info, self.device, self.shards = checkpoint, info, device, shards
        self.text_encoder, self.size_hw = text_encoder, size_hw
        # the rate the training clips were cut at; older runs only state their latent frame spacing
        self.clip_fps_hz = clip_fps_hz or video_clip_fps_hz(objective, vae.info.temporal_compression)

    @classmethod
    def from_pretrained(cls, name_or_path: str | Path, *, device: str = "cpu", dtype: torch.dtype = torch.float32,
                        vae: str | Path | None = None, text_encoder: str | Path | None = DEFAULT_TEXT_ENCODER,
                        shards: str | Path | None = None) -> "WorldModelBundle":
        """Load a run folder, its ``final/`` or a shipped name. ``vae``: another VAE folder than the one that
        encoded the training data (rarely right); ``shards``: a dataset whose histories and prompt table are used
        (its encoding decides the VAE); ``text_encoder``: a local T5 folder for prompts not in a table.
        Raises :class:`BundleLoadError` (one line, naming the part) for missing or broken files."""
        ck = str(name_or_path)
        try:
            model, info = load_world_model(ck, device, dtype)
            objective = run_objective(ck)
        except SamplingInputError as e:
            raise BundleLoadError("checkpoint", str(e)) from None
        try:
            check_same_encoding(ck, shards)
        except SamplingInputError as e:
            raise BundleLoadError("shards", str(e)) from None
        try:
            video_vae = VideoVAE(vae or encoded_with(ck, shards), device=device)
        except (SamplingInputError, MissingWeightsError) as e:
            raise BundleLoadError("vae", str(e)) from None
        mcfg = model.cfg
        sc = video_vae.info.spatial_compression
        size = trained_size_hw(ck, shards) or (mcfg.sample_height * sc, mcfg.sample_width * sc)
        return cls(model, objective, video_vae, checkpoint=ck, info=info, text_encoder=text_encoder,
                   size_hw=size, clip_fps_hz=trained_clip_fps_hz(ck, shards), device=device, shards=shards)

    @classmethod
    def for_rollout(cls, name_or_path: str | Path, settings: Settings, *, device: str,
                    vae: str | Path | None = None, shards: str | Path | None = None,
                    log: Callable[[str], None] | None = None) -> "WorldModelBundle":
        """The one rollout set-up of every command that samples (sample, plan, simulate, eval, the closed loop):
        the bundle loaded at ``settings.runtime``'s dtype and text encoder, its attention kernel and compile
        applied, ``settings.rollout`` checked against the run's noise schedule (:class:`ConfigError` naming the
        key), and ``info`` recording all of it. ``log`` hears where non-preset defaults came from (a distilled
        student's) and what was compiled."""
        rt = settings.runtime
        wm = cls.from_pretrained(name_or_path, device=device, dtype=getattr(torch, rt.dtype), vae=vae,
                                 text_encoder=rt.text_encoder, shards=shards)
        wm.check_rollout_config(settings.rollout)
        if settings.origin and log is not None:
            log(settings.origin)
        if rt.attention is not None:
            wm.model.set_attention_backend(rt.attention)
        wm.info = {**wm.info, "attention_backend": wm.model.cfg.attention_backend,
                   **maybe_compile(wm.model, rt.compile, device, mode=rt.compile_mode, log=log)}
        return wm

    # ------------------------------------------------------------------------------------------- inputs
    @property
    def latent_frame_dt_s(self) -> float:
        """Seconds between latent frames at the training clip rate (the VAE's temporal ratio / clip fps)."""
        return self.vae.info.temporal_compression / self.clip_fps_hz

    def history(self, source: str | Path, num_latent_frames: int = 3, size_hw: tuple[int, int] | None = None) -> History:
        """A video file (resampled to the clip rate, cover-resized to the training size, encoded by the VAE), or
        a sample key of ``shards`` given at load."""
        if Path(source).is_file():
            size = tuple(size_hw) if size_hw else self.size_hw
            return history_from_video(source, self.vae, num_latent_frames, size, self.clip_fps_hz)
        if self.shards is None:
            raise SamplingInputError(f"history {source!r}: not a file; a shard sample key needs the bundle loaded "
                                     "with shards=DATASET_DIR")
        return history_from_shard(self.shards, str(source), num_latent_frames)

    def prompts(self, history: History | None = None) -> PromptSource:
        """Command → ``(1, L, D)`` T5 embedding: the prompt table of the history's dataset (without a history: of
        the ``shards`` given at load) first, else the text encoder."""
        root = history.prompt_root if history is not None else self.shards
        return PromptSource(root, self.text_encoder, device=self.device, max_tokens=self.model.cfg.max_text_seq_length)

    def rollout_config(self, preset: str = "resim", steps: int | None = None, guidance_scale: float | None = None,
                       no_guidance: bool = False, guidance_schedule: str | None = None,
                       log: Callable[[str], None] | None = None, **overrides: Any) -> RolloutConfig:
        """The preset's :class:`RolloutConfig` under the given overrides (None: keep the preset's), with this
        export's own sampling defaults where the caller gives none (a distilled student: its steps, no guidance;
        ``log`` is told so); checked against the run's noise schedule. The same resolution as the CLIs'
        ``--set rollout.*`` (:func:`resim.sample.settings.rollout_config_for`)."""
        user: dict = {k: v for k, v in overrides.items() if v is not None}
        g = {k: v for k, v in (("scale_start", guidance_scale), ("schedule", guidance_schedule)) if v is not None}
        if g:
            user["guidance"] = g
        cfg, origin = rollout_config_for(self.checkpoint, preset, steps, no_guidance, user)
        if origin and log is not None:
            log(origin)
        return self.check_rollout_config(cfg)

    def check_rollout_config(self, cfg: RolloutConfig) -> RolloutConfig:
        """``cfg``'s steps and noise levels against this run's noise schedule (:class:`ConfigError` naming them);
        a config resolved elsewhere (the CLIs' settings) is checked here before any rollout starts."""
        ddim_schedule(cfg, self.objective.schedule)
        return cfg

    # ------------------------------------------------------------------------------------------- rollout
    def rollout(self, history: str | Path | History, command: str | None = None,
                trajectory: np.ndarray | None = None, *, seconds: float = 4.0, seed: int = 0,
                preset: str = "resim", steps: int | None = None, guidance_scale: float | None = None,
                no_guidance: bool = False, progress: Any = None) -> Rollout:
        """Imagine ``seconds`` after ``history`` under one command (``COMMANDS`` or None for the null prompt) and/or
        one trajectory ``(8, 3)`` (x m, y m, yaw rad in the ego frame), then decode it with the model's VAE."""
        if command is not None and command not in COMMANDS:
            raise SamplingInputError(f"command {command!r} is not one of {list(COMMANDS)}")
        cfg = self.rollout_config(preset, steps, guidance_scale, no_guidance)
        h = history if isinstance(history, History) else self.history(history, cfg.history_frames)
        prompts = self.prompts(h)
        traj = None if trajectory is None else torch.as_tensor(np.asarray(trajectory, np.float32))[None].to(self.device)
        cond = Condition(text=prompts(command).to(self.device), null_text=prompts(None).to(self.device),
                         trajectory=traj, label=command or "(no command)")
        num_future = rollout_num_future_frames(seconds, h.fps_hz, self.vae.info.temporal_compression)
        res = rollout(self.model, h.latents.to(self.device), cond, num_future, cfg, seed=seed, progress=progress,
                      schedule=self.objective.schedule)
        if not bool(torch.isfinite(res.latents).all()):
            raise FloatingPointError(f"the rollout holds NaN/inf values (finite history, prompts and weights: the "
                                     f"model {self.checkpoint} overflowed)")
        frames = decode_rollout(self.vae, res.latents, res.num_history_frames, cfg.frames_per_round,
                                cfg.history_frames)[0]
        return Rollout(frames=frames, latents=res.latents[0].cpu(),
                       num_history_frames_px=pixel_frame_count(res.num_history_frames, self.vae.info.temporal_compression),
                       fps_hz=h.fps_hz, labels=list(res.round_labels))
