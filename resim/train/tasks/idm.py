"""Training and held-out evaluation of the inverse dynamics model (and its history-only planner twin).

``run_idm_training(dataset_root, cfg)``: clips with trajectories from the shards (pixel frames from
``frames.mp4`` through ``resim.shards.reader``, the trajectory from ``traj.npy``) → split by episode (``item_id``)
→ fit through the common ``resim.train.trainer.Trainer`` → held-out ADE/FDE next to the constant-velocity
baseline → ``OUT/final/`` (the trainer's export: ``model.safetensors`` + ``config.yaml``, loadable with
:func:`load_idm`), ``OUT/idm_report.json`` and ``OUT/idm_report.png``.

**Constant-velocity baseline** (CV): the shards carry no past poses, so CV takes the speed the car has over
the first 0.5 s of the recorded future (``|waypoint_1| / 0.5 s``) and drives straight ahead at that speed.
It uses a little of the future (an oracle initial speed), which makes it a *stronger* baseline than one
extrapolating from the past; it knows nothing of turns or later speed changes.

Clips are held in memory at the model's input resolution (uint8, ~0.2 MB per 49-frame clip at 48x80);
for datasets too large for that, ``resim train idm`` streams shards through the common data loader
(``InverseDynamicsModel.loss`` accepts a ``resim.train.data.Batch``).

The split by episode, the epoch batches, the trainer run and the batched prediction are the small-model
harness's (``resim.train.smallfit``, shared with Video2Reward); what is the IDM's own: its clips and targets, the
mirror augmentation, the optimiser (warmup + cosine), early stopping on validation ADE and the CV baseline.
"""
from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

from resim.config import ConfigError, to_dict
from resim.media.encoders import VideoVAE
from resim.models.exported import ExportNotFoundError, load_exported
from resim.models.idm import IDMConfig, InverseDynamicsModel, idm_preset, num_parameters, receptive_note
from resim.sample.outputs import decode_latents
from resim.shards.reader import iter_samples
from resim.shards import split as dataset_split
from resim.shards.safejson import write_json
from resim.shards.split import DatasetSplit
from resim.shipped import shipped_model
from resim.train import smallfit
from resim.train.config import OptimConfig, RunConfig, SmallTrainConfig
from resim.train.metrics import plot_bars
from resim.train.smallfit import frames_to_tensor


@dataclass
class IDMTrainConfig(SmallTrainConfig):
    """The IDM's training (`resim train idm`): epochs, batch, seed and ``optim`` as every small model's
    (:class:`resim.train.config.SmallTrainConfig`), then its network, split and augmentation."""
    preset: str = "small"
    overrides: dict[str, Any] = field(default_factory=dict)   # IDMConfig fields
    # AdamW with a warmup, then cosine to 5 %, clipping at 1
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=2e-3, weight_decay=0.01, warmup_steps=20,
                                                                   schedule="cosine", min_lr_ratio=0.05))
    # augmentation: mirror clips left-right (video flipped along W; trajectory y -> -y, yaw -> -yaw). Ego motion
    # is mirror-symmetric, so a mirrored clip is another valid clip (doubles the distinct training clips).
    hflip_prob: float = 0.5
    # augmentation: the clip as the VAE gives it back. With a VAE (folder or shipped name, e.g. "synth-vae"), each
    # clip's shard latents (latent.npy, what the world model was trained on) are decoded once, and an epoch shows a
    # clip's decoded frames instead of its recorded ones with probability ``decoded_prob``. The trajectory is the
    # recorded one either way. Why: Trajectory Difference reads *decoded* video (the world model's rollouts), and
    # an IDM that has only seen recorded frames reads decoded ones worse (on the synthetic world 2.26 -> 3.51 m;
    # with this augmentation 2.02 -> 2.53 m, docs/lab/2026-11-26-synth-world-stage-chain.md, 2026-11-30; the
    # shipped IDM's recipe: docs/models/synth-idm.md). ReSim's IDM-based metric assumes the IDM
    # reads generated and real video alike.
    decoded_vae: str | None = None
    decoded_prob: float = 0.5
    # early stopping: this share of the *training* episodes (never the held-out ones) is set aside; the weights
    # of the epoch with the lowest validation ADE are kept. 0 disables it; skipped (and said so) when the
    # training split has fewer than `min_episodes_for_validation` episodes.
    val_fraction: float = 0.15
    min_episodes_for_validation: int = 6

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.hflip_prob <= 1.0:
            raise ConfigError(f"hflip_prob must be in [0, 1], got {self.hflip_prob}")
        if not 0.0 <= self.decoded_prob <= 1.0:
            raise ConfigError(f"decoded_prob must be in [0, 1], got {self.decoded_prob}")
        if self.decoded_vae is not None and not shipped_model(self.decoded_vae).is_dir():
            raise ConfigError(f"decoded_vae={self.decoded_vae!r}: no such folder or shipped model (configs/models/NAME)")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ConfigError(f"val_fraction must be in [0, 1), got {self.val_fraction}")

    def model_cfg(self) -> IDMConfig:
        return idm_preset(self.preset, **self.overrides)


@dataclass
class TrajClip:
    key: str
    item_id: str
    frames: np.ndarray            # (T, h, w, 3) uint8 RGB, the whole clip, resized to the model's input
    trajectory: np.ndarray        # (N, 3) float32, ego frame at the last history frame
    num_history_frames: int
    fps_hz: float
    waypoint_dt_s: float = 0.5
    latents: np.ndarray | None = None   # (T_lat, C, h, w) float16, the shard's latent.npy (kept only to decode)
    decoded: np.ndarray | None = None   # like ``frames``: the latents decoded by the VAE (``attach_decoded``)


def resize_frames(frames: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """(T, H, W, 3) uint8 → (T, h, w, 3) uint8 (bilinear with antialias, as the model would resize)."""
    if tuple(frames.shape[1:3]) == tuple(size_hw):
        return frames
    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float()
    x = F.interpolate(x, size=tuple(size_hw), mode="bilinear", align_corners=False, antialias=True)
    return x.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()


def clips_from_dataset(root: str | Path, size_hw: tuple[int, int],
                       keep_latents: bool = False) -> tuple[list[TrajClip], dict]:
    """Clips with a trajectory from every committed shard of ``root``; returns (clips, counts). ``keep_latents``:
    keep each clip's ``latent.npy`` (for :func:`attach_decoded`)."""
    if not Path(root).is_dir():
        raise FileNotFoundError(f"dataset folder {root} does not exist")
    clips, counts = [], {"samples": 0, "without_trajectory": 0}
    for s in iter_samples(root, decode_video=True, attach_prompts=False):
        counts["samples"] += 1
        meta = s["meta.json"]
        if "traj.npy" not in s:
            counts["without_trajectory"] += 1
            continue
        clips.append(TrajClip(key=s["__key__"], item_id=meta["item_id"], frames=resize_frames(s["frames"], size_hw),
                              trajectory=np.asarray(s["traj.npy"], np.float32),
                              num_history_frames=int(meta["num_history_frames"]), fps_hz=float(meta["fps_hz"]),
                              latents=s.get("latent.npy") if keep_latents else None))
    return clips, counts


def attach_decoded(clips: Sequence[TrajClip], vae: str, size_hw: tuple[int, int], batch_size: int = 8,
                   log=None) -> None:
    """Set each clip's ``decoded`` frames: its shard latents decoded by ``vae`` (one VAE call per window, as
    ``resim eval`` decodes a rollout of one round: ``decode_latents``), resized to ``size_hw``; the latents are
    then dropped. ~0.5 s per 49-frame clip at 64 x 96 on a 2-core CPU."""
    missing = [c.key for c in clips if c.latents is None]
    if missing:
        raise IDMDataError(f"--decoded-vae needs latents (latent.npy) in the shards; clip {missing[0]} has none "
                           f"({len(missing)} of {len(clips)} clips): encode the dataset with a VAE")
    model = VideoVAE(shipped_model(vae))   # the one device resolver's choice (cuda where there is one)
    if log is not None:
        log(f"decoding {len(clips)} clips through {vae} (~0.5 s each on a 2-core CPU) ...")
    t0 = time.perf_counter()
    for i in range(0, len(clips), batch_size):
        part = clips[i:i + batch_size]
        shapes = {c.latents.shape for c in part}
        groups = [[c for c in part if c.latents.shape == sh] for sh in shapes]
        for g in groups:
            video = decode_latents(model, np.stack([c.latents.astype(np.float32) for c in g]), batch_size=len(g))
            for c, v in zip(g, video):
                if len(v) != len(c.frames):
                    raise IDMDataError(f"clip {c.key}: its latents decode to {len(v)} frames, its video has "
                                       f"{len(c.frames)}")
                c.decoded, c.latents = resize_frames(v, size_hw), None
        if log is not None and (i // batch_size) % 25 == 24:
            log(f"decoded {i + len(part)} of {len(clips)} clips through {vae}, {time.perf_counter() - t0:.0f} s")


def collate(clips: Sequence[TrajClip], cfg: IDMConfig, flip: Sequence[bool] | None = None,
            decoded: Sequence[bool] | None = None) -> dict:
    """``{"video": (B, T, 3, h, w) float [0, 1] (the model's window), "trajectory": (B, N, 3), "keys"}``.

    ``flip[i]``: mirror clip i left-right (frames along W; trajectory y and yaw negated: the mirrored world's
    ego motion, x forward / y left / yaw left +). ``decoded[i]``: clip i's frames as the VAE decodes them."""
    vids, trajs = [], []
    for i, c in enumerate(clips):
        idx = cfg.frame_indices(c.num_history_frames, len(c.frames))
        use_dec = decoded is not None and decoded[i]
        if use_dec and c.decoded is None:   # our bug: attach_decoded runs before any batch
            raise AssertionError(f"clip {c.key}: decoded frames asked for but never attached")
        f, t = (c.decoded if use_dec else c.frames)[idx], c.trajectory
        if flip is not None and flip[i]:
            f, t = f[:, :, ::-1], t * np.array([1.0, -1.0, -1.0], np.float32)
        vids.append(frames_to_tensor(f))
        trajs.append(t)
    return {"video": torch.stack(vids),
            "trajectory": torch.from_numpy(np.stack(trajs).astype(np.float32)),
            "keys": [c.key for c in clips]}


def predict(model: InverseDynamicsModel, clips: Sequence[TrajClip], batch_size: int = 32,
            decoded: bool = False) -> np.ndarray:
    """(N, num_waypoints, 3) predicted trajectories, in the order of ``clips`` (``decoded``: on their decoded
    frames)."""
    return smallfit.predict(model, clips, lambda cs: collate(cs, model.cfg, decoded=[decoded] * len(cs)),
                            lambda m, b: m(b["video"]), batch_size,
                            empty_shape=(model.cfg.num_waypoints, 3))


def constant_velocity(gt: np.ndarray, waypoint_dt_s: float = 0.5) -> np.ndarray:
    """CV baseline (see module docstring): straight ahead at the speed of the first recorded 0.5 s."""
    gt = np.asarray(gt, np.float64)
    v0 = np.linalg.norm(gt[:, 0, :2], axis=-1) / waypoint_dt_s                    # (B,)
    t = waypoint_dt_s * np.arange(1, gt.shape[1] + 1)                              # (N,)
    out = np.zeros_like(gt)
    out[..., 0] = v0[:, None] * t[None]
    return out


def trajectory_errors(pred: np.ndarray, gt: np.ndarray) -> dict:
    """ADE (mean L2 over waypoints), FDE (L2 at the last waypoint), both in metres, and the mean absolute
    yaw error in degrees; mean over clips, plus the number of clips."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"pred {pred.shape} and gt {gt.shape} must both be (B, N, 3)")
    d = np.linalg.norm(pred[..., :2] - gt[..., :2], axis=-1)                       # (B, N)
    dyaw = (pred[..., 2] - gt[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return {"ade_m": float(d.mean()), "fde_m": float(d[:, -1].mean()),
            "yaw_err_deg": float(np.rad2deg(np.abs(dyaw)).mean()), "n": int(len(pred))}


def run_config(tcfg: IDMTrainConfig, steps: int, progress: bool = False) -> RunConfig:
    """The common trainer's RunConfig for an IDM run (AdamW, warmup + cosine to 5 %, clipping at 1)."""
    return smallfit.run_config(
        # the resolved IDMConfig, not just the preset name: a run must load the same network after presets change
        "idm", to_dict(tcfg.model_cfg()), steps=steps, batch_size=tcfg.batch_size_per_gpu, seed=tcfg.seed,
        optim=tcfg.optim.for_steps(steps),
        save_final_weights=True, preset=f"idm-{tcfg.preset}", progress=progress, load_frames=True,
        reference={"resim": "IDM: video -> 8 waypoints at 2 Hz (XVO backbone there)"})


class BestOnValidation:
    """Early stopping without touching the trainer: after every epoch, the validation ADE; a copy of the
    weights of the best epoch so far (the model is small), restored at the end by :meth:`restore`. With decoded
    frames (``decoded_vae``) the ADE is the mean of the recorded and the decoded frames' (the IDM is for both)."""

    def __init__(self, model: InverseDynamicsModel, val: Sequence[TrajClip]):
        self.model, self.val = model, list(val)
        self.both = all(c.decoded is not None for c in self.val)
        self.gt = np.stack([c.trajectory for c in self.val])
        self.history: list[dict] = []
        self.best: tuple[float, int, dict] | None = None

    def __call__(self, epoch: int) -> None:
        was_training = self.model.training
        ade = trajectory_errors(predict(self.model, self.val), self.gt)["ade_m"]
        if self.both:
            ade = (ade + trajectory_errors(predict(self.model, self.val, decoded=True), self.gt)["ade_m"]) / 2
        self.model.train(was_training)
        self.history.append({"epoch": epoch, "val_ade_m": ade})
        if self.best is None or ade < self.best[0]:
            self.best = (ade, epoch, {k: v.detach().clone() for k, v in self.model.state_dict().items()})

    def restore(self) -> dict:
        ade, epoch, state = self.best
        self.model.load_state_dict(state)
        return {"best_epoch": epoch, "best_val_ade_m": ade, "epochs_evaluated": len(self.history),
                "val_ade_per_epoch": self.history}


def augment_draws(tcfg: IDMTrainConfig, rng: np.random.Generator, n: int) -> np.ndarray:
    """An epoch's per-clip augmentation, ``(n, 2)`` bool: mirror, decoded frames. The mirror flags are drawn
    first, so a run without decoded frames draws exactly what it drew before they existed (exact resume of
    older runs, the same batches)."""
    flip = rng.random(n) < tcfg.hflip_prob
    use_dec = tcfg.decoded_vae is not None and tcfg.decoded_prob > 0
    dec = rng.random(n) < tcfg.decoded_prob if use_dec else np.zeros(n, bool)
    return np.stack([flip, dec], axis=1)


def fit(model: InverseDynamicsModel, clips: Sequence[TrajClip], tcfg: IDMTrainConfig, run_dir: str | Path,
        progress: bool = False, val: Sequence[TrajClip] = ()) -> dict:
    """Train through the common Trainer (``resim.train.smallfit.fit``: epoch ``e`` shuffled with seed
    ``seed * 1000 + e``, the same RNG mirroring each clip with probability ``hflip_prob``); with ``val`` clips,
    keep the weights of the best validation epoch (and re-export them to ``run_dir/final``)."""
    stopper = BestOnValidation(model, val) if len(val) else None
    data = smallfit.EpochBatches(clips, tcfg.batch_size_per_gpu, tcfg.seed,
                                 lambda cs, d: collate(cs, model.cfg, d[:, 0], d[:, 1]),
                                 augment=lambda rng, n: augment_draws(tcfg, rng, n), on_epoch_end=stopper)
    out = smallfit.fit(model, data, tcfg.epochs, lambda steps: run_config(tcfg, steps, progress), run_dir)
    if stopper is not None:
        stopper(tcfg.epochs)           # the last epoch (the trainer stops without asking for another batch)
        out["early_stopping"] = stopper.restore()
        model.eval()
        if out["early_stopping"]["best_epoch"] != tcfg.epochs:
            save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
                      str(Path(run_dir) / "final" / "model.safetensors"))
    return out


def load_idm(run_dir: str | Path, device: str = "cpu") -> tuple[InverseDynamicsModel, dict]:
    """Load a trained IDM/planner from a run folder (or its ``final/``), or a shipped one by name (``synth-idm``),
    built through the registry (``resim.models.exported``). ``FileNotFoundError`` when neither holds the files; a
    ``ValueError`` naming the file for anything wrong in them (the CLI prints it in one line)."""
    try:
        ex = load_exported(run_dir, expect="idm", label="an IDM run", adapt_config=_head_of_old_runs,
                           shipped=True)
    except ExportNotFoundError as e:
        raise FileNotFoundError(f"IDM checkpoint {e} (written by `resim train idm`)") from None
    sha = hashlib.sha256(ex.weights.read_bytes()).hexdigest()
    return ex.model.to(device).eval().requires_grad_(False), {"checkpoint": str(ex.folder), "weights_sha256": sha}


def _head_of_old_runs(model_cfg: dict, state: Any) -> dict:
    """Runs written before the odometry head store only {"preset": ...}, and the presets' head changed since:
    their head is the one their weights hold."""
    if "head" in model_cfg:
        return model_cfg
    return {**model_cfg, "head": "odometry" if any(k.startswith("odometry.") for k in state) else "queries"}


class IDMDataError(ValueError):
    """The dataset gives no usable split for the IDM (says why: no samples, no trajectories, the window does
    not fit the clips, a single episode)."""


@dataclass
class IDMData:
    """The clips of a run, checked (:func:`prepare_idm_data`) before anything is trained."""

    train: list[TrajClip]
    held: list[TrajClip]
    skipped: list[dict]   # [{"key", "reason"}]: clips the model's window does not fit
    counts: dict          # {"samples", "without_trajectory"} when read from shards
    split: DatasetSplit   # the dataset's own (resim.shards.split)


def prepare_idm_data(root: str | Path, tcfg: IDMTrainConfig, clips: Sequence[TrajClip] | None = None) -> IDMData:
    """Read (unless ``clips`` are given) and check the clips, split them by the dataset's split (``root``'s
    split.json: ``resim.shards.split``), and with ``decoded_vae`` decode
    every usable clip's latents (:func:`attach_decoded`; the slow part, after every check has passed).
    ``FileNotFoundError`` when ``root`` does not exist, :class:`IDMDataError` naming the reason when no split can
    be made or a clip has no latents to decode."""
    mcfg = tcfg.model_cfg()
    counts: dict = {}
    if clips is None:
        clips, counts = clips_from_dataset(root, mcfg.input_hw, keep_latents=tcfg.decoded_vae is not None)
    usable, skipped = smallfit.usable(clips, lambda c: mcfg.frame_indices(c.num_history_frames, len(c.frames)),
                                      ValueError)
    if not usable:
        if skipped:   # the reason is the window, not the data: say so with the first clip's numbers
            raise IDMDataError(f"{root}: the model's window fits none of the {len(skipped)} clips with a trajectory "
                               f"(e.g. clip {skipped[0]['key']}: {skipped[0]['reason']}); change the window "
                               "(--set future_frames=... num_frames=..., --preset) or use longer clips")
        if counts.get("samples"):
            raise IDMDataError(f"{root}: none of its {counts['samples']} samples has a trajectory (traj.npy)")
        raise IDMDataError(f"{root}: no samples (no committed shards: DIR/shards/*.tar with DIR/index/*.json)")
    split = dataset_split.read(root)
    try:
        train, held = smallfit.split_clips(usable, split, "clip with a trajectory")
    except ValueError as e:   # a side of the split without a usable clip
        raise IDMDataError(f"{root}: {e}") from None
    if tcfg.decoded_vae is not None:   # held-out clips too: the report reads the IDM on both kinds of frames
        attach_decoded(usable, tcfg.decoded_vae, mcfg.input_hw,
                       log=lambda m: print(f"[idm] {m}", file=sys.stderr, flush=True))
    return IDMData(train, held, skipped, counts, split)


def run_idm_training(root: str | Path, tcfg: IDMTrainConfig, out_dir: str | Path, progress: bool = False,
                     clips: Sequence[TrajClip] | None = None, data: IDMData | None = None) -> dict:
    """Load, split by episode, train, evaluate held-out vs the CV baseline, write the report.

    ``data``: :func:`prepare_idm_data`'s result for the same root/config (callers that check the input
    first, e.g. the CLI, pass it on)."""
    mcfg = tcfg.model_cfg()
    if data is None:
        data = prepare_idm_data(root, tcfg, clips)
    train, held, skipped, counts = data.train, data.held, data.skipped, data.counts
    n_train_eps = len({c.item_id for c in train})
    fit_clips, val = train, []
    if tcfg.val_fraction > 0 and n_train_eps >= tcfg.min_episodes_for_validation:
        # a second seeded split, inside the training episodes only
        fit_clips, val = smallfit.split_by_episode(train, tcfg.val_fraction, tcfg.seed + 1)
        validation = (f"{len({c.item_id for c in val})} of the {n_train_eps} training episodes "
                      f"({len(val)} clips), best epoch kept")
    else:
        validation = ("none" if tcfg.val_fraction == 0 else
                      f"none: {n_train_eps} training episodes < min_episodes_for_validation "
                      f"{tcfg.min_episodes_for_validation}; the last epoch is kept")
    torch.manual_seed(tcfg.seed)
    model = InverseDynamicsModel(mcfg)
    out = Path(out_dir)
    fitted = fit(model, fit_clips, tcfg, out, progress, val=val)
    gt_h = np.stack([c.trajectory for c in held])
    gt_t = np.stack([c.trajectory for c in fit_clips])
    dt = held[0].waypoint_dt_s
    res = {
        "model": {"window": mcfg.window, "architecture": receptive_note(mcfg), "parameters": num_parameters(model),
                  "config": {"preset": tcfg.preset, **tcfg.overrides}},
        "heldout": {"idm" if mcfg.window == "future" else "planner": trajectory_errors(predict(model, held), gt_h),
                    "constant_velocity": trajectory_errors(constant_velocity(gt_h, dt), gt_h)},
        "train": {"model": trajectory_errors(predict(model, fit_clips), gt_t),
                  "constant_velocity": trajectory_errors(constant_velocity(gt_t, dt), gt_t)},
        "protocol": {"dataset": str(root), "clips_train": len(train), "clips_heldout": len(held),
                     "episodes_train": len({c.item_id for c in train}),
                     "episodes_heldout": len({c.item_id for c in held}),
                     "heldout_items": sorted({c.item_id for c in held}),
                     "train_items": sorted({c.item_id for c in train}), "split": data.split.record("heldout"),
                     "validation": validation, "clips_fit": len(fit_clips), "clips_validation": len(val),
                     "augmentation": f"left-right mirror with p={tcfg.hflip_prob} (y, yaw negated)" + (
                         f"; the shard latents decoded by {tcfg.decoded_vae} with p={tcfg.decoded_prob}"
                         if tcfg.decoded_vae is not None else ""),
                     "skipped": skipped, **counts,
                     "constant_velocity": "straight ahead at |waypoint_1| / 0.5 s (oracle initial speed)",
                     "ade": "mean L2 over the 8 waypoints (x, y), metres; fde: L2 at 4.0 s",
                     "device": str(next(model.parameters()).device)},
        "training": {k: fitted[k] for k in ("steps", "seconds", "early_stopping") if k in fitted},
        "checkpoint": str(out / "final"),
    }
    if tcfg.decoded_vae is not None:   # the same held-out clips, their latents decoded by the VAE
        res["heldout"]["idm_through_vae"] = trajectory_errors(predict(model, held, decoded=True), gt_h)
    if val:  # the split early stopping chose on: optimistic by construction, reported for completeness
        gt_v = np.stack([c.trajectory for c in val])
        res["validation"] = {"model": trajectory_errors(predict(model, val), gt_v),
                             "constant_velocity": trajectory_errors(constant_velocity(gt_v, dt), gt_v)}
    write_json(res, out / "idm_report.json")
    key = "idm" if mcfg.window == "future" else "planner"
    plot_bars({"held-out ADE": {key: res["heldout"][key]["ade_m"], "constant velocity":
                                res["heldout"]["constant_velocity"]["ade_m"]},
               "held-out FDE": {key: res["heldout"][key]["fde_m"], "constant velocity":
                                res["heldout"]["constant_velocity"]["fde_m"]}},
              out / "idm_report.png", title=f"{key} ({len(held)} held-out clips, {res['protocol']['episodes_heldout']}"
                                             " episodes)")
    (out / "train_config.json").write_text(json.dumps({"preset": tcfg.preset, "overrides": tcfg.overrides,
                                                        "epochs": tcfg.epochs, "lr": tcfg.optim.lr,
                                                        "batch_size_per_gpu": tcfg.batch_size_per_gpu,
                                                        "seed": tcfg.seed, "split": data.split.summary(),
                                                        "hflip_prob": tcfg.hflip_prob,
                                                        "decoded_vae": tcfg.decoded_vae,
                                                        "decoded_prob": tcfg.decoded_prob,
                                                        "val_fraction": tcfg.val_fraction},
                                                       indent=1))
    res["_model"] = model
    return res
