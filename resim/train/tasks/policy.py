"""Behaviour cloning of the driving policy on the shards' expert clips, held-out by episode.

``run_policy_training(roots, cfg, out)``: every clip with a trajectory, not hazardous (the CARLA-like
explorers' drives are what not to imitate), its command the trajectory command (``meta.command_trajectory``:
the turn the recorded future makes, the navigation command a route planner gives) → the policy's window of
history frames → split by episode → fit through the small-model harness (``resim.train.smallfit``: the common
Trainer, checkpoints, exact resume, metrics.jsonl) → held-out ADE/FDE per command beside constant velocity
→ ``OUT/final/`` (``model.safetensors`` + ``config.yaml``, loadable with :func:`load_policy`) and
``OUT/policy_report.json``.

Augmentation: a left-right mirror with probability ``hflip_prob`` (frames flipped, y and yaw negated, left
and right commands swapped): a mirrored drive is another valid drive of a mirrored world.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from resim.config import ConfigError, to_dict
from resim.models.exported import ExportNotFoundError, load_exported
from resim.models.policy.model import DrivingPolicy, PolicyConfig, command_index, policy_preset
from resim.shards import split as dataset_split
from resim.shards.errors import ShardReadError
from resim.shards.reader import iter_samples
from resim.shards.safejson import write_json
from resim.shards.schema import COMMANDS
from resim.train import smallfit
from resim.train.config import OptimConfig, RunConfig, SmallTrainConfig
from resim.train.smallfit import frames_to_tensor
from resim.train.tasks.idm import constant_velocity, resize_frames, trajectory_errors

MIRROR = {0: 2, 1: 1, 2: 0}   # command index under a left-right mirror


@dataclass
class PolicyTrainConfig(SmallTrainConfig):
    """The policy's training (`resim train policy`): epochs, batch, seed and ``optim`` as every small model's
    (:class:`resim.train.config.SmallTrainConfig`), then its network, split and augmentation."""
    preset: str = "tiny"
    overrides: dict[str, Any] = field(default_factory=dict)   # PolicyConfig fields
    batch_size_per_gpu: int = 32
    # AdamW with a warmup, then cosine to 5 %, clipping at 1
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=2e-3, weight_decay=0.01, warmup_steps=20,
                                                                   schedule="cosine", min_lr_ratio=0.05))
    hflip_prob: float = 0.5

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.hflip_prob <= 1.0:
            raise ConfigError(f"hflip_prob must be in [0, 1], got {self.hflip_prob}")

    def model_cfg(self) -> PolicyConfig:
        return policy_preset(self.preset, **self.overrides)


@dataclass
class PolicyClip:
    key: str
    item_id: str
    frames: np.ndarray        # (num_frames, h, w, 3) uint8: the policy's window, at its input size
    trajectory: np.ndarray    # (8, 3) float32
    command: int              # index into COMMANDS


class PolicyDataError(ValueError):
    """The shards give no usable training set (says why)."""


def clips_from_shards(roots: Sequence[str | Path], cfg: PolicyConfig) -> tuple[list[PolicyClip], dict]:
    """The expert clips of ``roots`` with a trajectory and a trajectory command; (clips, counts). The window is
    the last ``cfg.span_frames`` history frames, every ``frame_step``-th; clips whose history is shorter, or
    whose frames are not ``cfg.frame_hw``, are counted and left out."""
    clips: list[PolicyClip] = []
    counts = {"samples": 0, "without_trajectory": 0, "hazardous": 0, "short_history": 0, "other_size": 0}
    for root in roots:
        if not Path(root).is_dir():
            raise FileNotFoundError(f"dataset folder {root} does not exist")
        for s in iter_samples(root, decode_video=True, attach_prompts=False):
            counts["samples"] += 1
            meta = s["meta.json"]
            if "traj.npy" not in s or not meta.get("command_trajectory"):
                counts["without_trajectory"] += 1
                continue
            if meta.get("hazard"):
                counts["hazardous"] += 1
                continue
            nh = int(meta["num_history_frames"])
            if nh < cfg.span_frames:
                counts["short_history"] += 1
                continue
            frames = s["frames"]
            if tuple(frames.shape[1:3]) != tuple(cfg.frame_hw):
                counts["other_size"] += 1
                continue
            idx = list(range(nh - cfg.span_frames, nh, cfg.frame_step))
            clips.append(PolicyClip(key=s["__key__"], item_id=meta["item_id"],
                                    frames=resize_frames(frames[idx], cfg.input_hw),
                                    trajectory=np.asarray(s["traj.npy"], np.float32),
                                    command=command_index(meta["command_trajectory"])))
    return clips, counts


def collate(clips: Sequence[PolicyClip], flip: Sequence[bool] | None = None) -> dict:
    vids, trajs, cmds = [], [], []
    for i, c in enumerate(clips):
        f, t, k = c.frames, c.trajectory, c.command
        if flip is not None and flip[i]:
            f, t, k = f[:, :, ::-1], t * np.array([1.0, -1.0, -1.0], np.float32), MIRROR[k]
        vids.append(frames_to_tensor(f))
        trajs.append(t)
        cmds.append(k)
    return {"video": torch.stack(vids), "trajectory": torch.from_numpy(np.stack(trajs).astype(np.float32)),
            "command": torch.tensor(cmds, dtype=torch.long)}


def predict(model: DrivingPolicy, clips: Sequence[PolicyClip], batch_size: int = 64) -> np.ndarray:
    return smallfit.predict(model, clips, collate, lambda m, b: m(b["video"], b["command"]), batch_size,
                            empty_shape=(model.cfg.num_waypoints, 3))


def errors_by_command(model: DrivingPolicy, clips: Sequence[PolicyClip]) -> dict:
    """ADE/FDE of the policy and of constant velocity (oracle initial speed), overall and per command."""
    gt = np.stack([c.trajectory for c in clips])
    pred = predict(model, clips)
    cv = constant_velocity(gt)
    out = {"all": {"policy": trajectory_errors(pred, gt), "constant_velocity": trajectory_errors(cv, gt)}}
    cmd = np.array([c.command for c in clips])
    for i, name in enumerate(COMMANDS):
        m = cmd == i
        if m.any():
            out[name] = {"policy": trajectory_errors(pred[m], gt[m]),
                         "constant_velocity": trajectory_errors(cv[m], gt[m])}
    return out


def run_config(tcfg: PolicyTrainConfig, steps: int, progress: bool = False) -> RunConfig:
    return smallfit.run_config(
        "policy", to_dict(tcfg.model_cfg()), steps=steps, batch_size=tcfg.batch_size_per_gpu, seed=tcfg.seed,
        optim=tcfg.optim.for_steps(steps),
        save_final_weights=True, preset=f"policy-{tcfg.preset}", progress=progress, load_frames=True,
        reference={"cil": "Codevilla et al. 2018: command-branched imitation policy",
                   "vid2world": "policies of graded quality ranked inside the world model (Real2Sim)"})


def run_policy_training(roots: Sequence[str | Path], tcfg: PolicyTrainConfig, out_dir: str | Path,
                        progress: bool = False, clips: Sequence[PolicyClip] | None = None) -> dict:
    """Read, split by the datasets' own split (``resim.shards.split``), train, evaluate on the held-out episodes,
    write the report."""
    mcfg = tcfg.model_cfg()
    counts: dict = {}
    if clips is None:
        clips, counts = clips_from_shards(roots, mcfg)
    if len({c.item_id for c in clips}) < 2:
        raise PolicyDataError(f"{', '.join(map(str, roots))}: {len(clips)} usable expert clips in "
                              f"{len({c.item_id for c in clips})} episode(s) ({counts}); need clips of >= 2 episodes")
    try:
        split = dataset_split.read_all(roots)
        train, held = smallfit.split_clips(clips, split, "expert clip")
    except (ShardReadError, ValueError) as e:
        raise PolicyDataError(f"{', '.join(map(str, roots))}: {e}") from None
    torch.manual_seed(tcfg.seed)
    model = DrivingPolicy(mcfg)
    data = smallfit.EpochBatches(train, tcfg.batch_size_per_gpu, tcfg.seed, collate,
                                 augment=lambda rng, n: rng.random(n) < tcfg.hflip_prob)
    out = Path(out_dir)
    fitted = smallfit.fit(model, data, tcfg.epochs, lambda steps: run_config(tcfg, steps, progress), out)
    res = {
        "model": {"parameters": sum(p.numel() for p in model.parameters()), "config": to_dict(mcfg),
                  "preset": tcfg.preset},
        "heldout": errors_by_command(model, held),
        "train": errors_by_command(model, train)["all"],
        "protocol": {"datasets": [str(r) for r in roots], "clips_train": len(train), "clips_heldout": len(held),
                     "episodes_train": len({c.item_id for c in train}),
                     "episodes_heldout": len({c.item_id for c in held}),
                     "heldout_items": sorted({c.item_id for c in held}), "split": split.record("heldout"),
                     "commands_train": {n: sum(c.command == i for c in train)
                                                                        for i, n in enumerate(COMMANDS)},
                     "augmentation": f"left-right mirror with p={tcfg.hflip_prob} (y, yaw negated, turns swapped)",
                     "constant_velocity": "straight ahead at |waypoint_1| / 0.5 s (oracle initial speed)",
                     **counts},
        "training": {"steps": fitted["steps"], "seconds": fitted["seconds"], "epochs": tcfg.epochs,
                     "lr": tcfg.optim.lr, "batch_size": tcfg.batch_size_per_gpu, "seed": tcfg.seed},
        "checkpoint": str(out / "final"),
    }
    write_json(res, out / "policy_report.json")
    return res


def load_policy(run_dir: str | Path, device: str = "cpu") -> tuple[DrivingPolicy, dict]:
    """A trained policy from a run folder (or its ``final/``), or a shipped one by name (``synth-policy``);
    ``FileNotFoundError`` when neither holds one."""
    try:
        ex = load_exported(run_dir, expect="policy", label="a policy run", shipped=True)
    except ExportNotFoundError as e:
        raise FileNotFoundError(f"policy checkpoint {e} (written by `resim train policy`)") from None
    sha = hashlib.sha256(ex.weights.read_bytes()).hexdigest()
    return ex.model.to(device).eval().requires_grad_(False), {"checkpoint": str(ex.folder), "weights_sha256": sha}
