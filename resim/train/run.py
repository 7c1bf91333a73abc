"""Build a run from a config and train it: what ``resim train NAME`` executes on every rank."""
from __future__ import annotations

import json
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import yaml

from resim.config import ConfigError, load, safe_yaml
from resim.models import registry
from resim.shipped import REPO_ROOT
from resim.train.config import RunConfig
from resim.train.presets import get_preset


def resolve_config(model_name: str, preset: str, *, config_file: str | Path | None = None,
                   overrides: Iterable[str] = (), shards: str | Path | None = None, steps: int | None = None,
                   checkpoint_every: int | None = None) -> RunConfig:
    """Preset <- YAML file <- ``--set`` overrides <- the explicit flags (``--shards``, ``--steps``, ...)."""
    try:
        base = get_preset(model_name, preset)
    except KeyError as e:
        raise ConfigError(str(e.args[0])) from None
    extra = list(overrides)
    if shards is not None:
        extra.append(f"data.shards={shards}")
    if steps is not None:
        extra.append(f"trainer.steps={steps}")
    if checkpoint_every is not None:
        extra.append(f"trainer.checkpoint_every_steps={checkpoint_every}")
    cfg = load(RunConfig, config_file, overrides=extra, base=base)
    if cfg.model_name != model_name:
        raise ConfigError(f"model_name={cfg.model_name!r} but the command trains {model_name!r}")
    return cfg


class RunFolderError(Exception):
    """``--out`` cannot be used as asked (it holds another run, or another kind of run); one line, exit 2."""


@dataclass(frozen=True)
class HeldRun:
    kind: str        # "world", "reward", "idm", ... (a config's model_name), or "shard dataset" / "unknown"
    evidence: str    # the file or folder that shows it, relative to the run folder


# what a `resim train` run writes into its folder: --overwrite removes these (and nothing else)
TRAINER_RUN_FILES = ("checkpoints", "final", "metrics.jsonl", "tensorboard", "loss_curve.png", "config.yaml")
# a reward run: final/ (resim.models.exported's layout) + its own outputs; reward.safetensors and meta.json are
# what runs written before that layout hold in their place
REWARD_RUN_FILES = ("trainer", "final", "config.yaml", "heldout_predictions.json", "history.json",
                    "heldout_pred_vs_true.png", "reward.safetensors", "meta.json")


def _config_kind(path: Path) -> str | None:
    """model_name of a run's config.yaml; "reward" for a RewardTrainConfig (no model_name); None if unreadable."""
    try:
        d = safe_yaml(path.read_text())
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        return None
    if not isinstance(d, dict):
        return None
    if isinstance(d.get("model_name"), str):
        return d["model_name"]
    if "epochs" in d and "model" in d:
        return "reward"
    return None


def _checkpoints(folder: Path) -> list[Path]:
    """Complete trainer checkpoints (step_XXXXXXXX/ holding meta.json), oldest first; no torch import."""
    root = folder / "checkpoints"
    if not root.is_dir():
        return []
    return sorted(p for p in root.glob("step_*") if p.is_dir() and not p.name.endswith(".tmp")
                  and (p / "meta.json").is_file())


def describe_run(out: str | Path) -> HeldRun | None:
    """The run (or dataset) a folder already holds, or None for a missing, empty or unrelated folder.

    A run is what would be lost or mixed up by training into the folder: trainer checkpoints or final weights
    (world, idm, reward, ...; the kind is config.yaml's model_name, else final/config.yaml's), a Video2Reward run
    of the older layout (reward.safetensors) or one still training (the checkpoints of its trainer/ folder), or a
    shard dataset. A folder with only a config.yaml or a partial
    metrics.jsonl (a run stopped before its first checkpoint) holds nothing to resume and is not a run."""
    out = Path(out)
    if not out.is_dir():
        return None
    cfg_kind = _config_kind(out / "config.yaml") if (out / "config.yaml").is_file() else None
    if (out / "reward.safetensors").is_file():
        return HeldRun("reward", "reward.safetensors")
    inner = _checkpoints(out / "trainer")
    if inner and cfg_kind in (None, "reward"):
        return HeldRun("reward", str(inner[-1].relative_to(out)))
    done = _checkpoints(out)
    final = out / "final" / "model.safetensors"
    if done or final.is_file():
        kind = cfg_kind or (_config_kind(final.parent / "config.yaml") if final.is_file() else None)
        if kind is None and done:
            try:
                kind = json.loads((done[-1] / "meta.json").read_text())["config"]["model_name"]
            except (OSError, ValueError, KeyError, TypeError):
                kind = None
        return HeldRun(kind or "unknown", str((done[-1] if done else final).relative_to(out)))
    if (out / "shards").is_dir() and (out / "index").is_dir():
        return HeldRun("shard dataset", "shards/")
    return None


def check_out_dir(kind: str, out: str | Path, *, resume: bool = False, overwrite: bool = False,
                  can_resume: bool = True) -> HeldRun | None:
    """Refuse an ``--out`` that would mix two runs; returns the run it holds (None: nothing there).

    * a folder holding another kind of run (or a dataset): refused, whatever the flags;
    * a folder holding a run of this kind: refused unless ``resume`` (continue it) or ``overwrite``
      (start over: see :func:`remove_run`); both at once are refused too.
    Raises :class:`RunFolderError` with a one-line message."""
    out = Path(out)
    if resume and overwrite:
        raise RunFolderError("--resume continues the run in --out and --overwrite deletes it: give one of them")
    if out.exists() and not out.is_dir():
        raise RunFolderError(f"--out {out} is a file, not a folder")
    held = describe_run(out)
    if held is None:
        return None
    if held.kind != kind:
        what = {"shard dataset": "a shard dataset", "unknown": "a run of unknown kind"}.get(held.kind,
                                                                                          f"a {held.kind} run")
        raise RunFolderError(f"{out} holds {what} ({held.evidence}), not a {kind} run; choose a new --out")
    if not (resume or overwrite):
        hint = ("use --resume to continue it, --overwrite to start over, or choose a new --out" if can_resume
                else "use --overwrite to replace it or choose a new --out")
        raise RunFolderError(f"{out} holds a {kind} run ({held.evidence}); {hint}")
    return held


def remove_run(out: str | Path, names: Iterable[str] = TRAINER_RUN_FILES) -> list[str]:
    """``--overwrite``: delete what an earlier run wrote into ``out`` (only ``names``; other files stay).
    Rank 0 only under torchrun (the other ranks write nothing before the process group is up)."""
    if os.environ.get("RANK", "0") != "0":
        return []
    removed = []
    for name in names:
        p = Path(out) / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
        else:
            continue
        removed.append(name)
    return removed


def finished_step(out: str | Path) -> int | None:
    """The step of the newest complete checkpoint in ``out`` (None: no checkpoint), from its name (step_XXXXXXXX,
    as ``resim.train.checkpoint.list_complete`` reads it; that module imports torch, this one must not)."""
    done = _checkpoints(Path(out))
    try:
        return int(done[-1].name[len("step_"):]) if done else None
    except ValueError:
        return None


def save_data_encoding(cfg: RunConfig, out: str | Path, split: dict | None = None) -> Path | None:
    """``RUN/final/data_encode.yaml``: the ``encode`` section (VAE, text encoder, sizes) of the training data's
    pipeline config, so a sampler decodes with the VAE the model learnt the latents of, at their size; its
    ``clip`` geometry (rate and frames), so a video history is resampled to the rate the model learnt motion at;
    and the side of the dataset's split it trained on (``split``: ``StreamLoader.split``)."""
    if cfg.data.shards is None or not (Path(cfg.data.shards) / "config.yaml").is_file():
        return None
    try:
        data_cfg = safe_yaml((Path(cfg.data.shards) / "config.yaml").read_text()) or {}
        enc, clip = data_cfg.get("encode"), data_cfg.get("clip")
    except (OSError, yaml.YAMLError, AttributeError):
        return None
    if not isinstance(enc, dict):
        return None

    models = (REPO_ROOT / "configs" / "models").resolve()
    for k in ("vae", "text_encoder"):   # a shipped model by its name: the file stays valid in another checkout
        if isinstance(enc.get(k), str) and Path(enc[k]).resolve().parent == models:
            enc[k] = Path(enc[k]).name
    path = Path(out) / "final" / "data_encode.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    clip = {k: clip[k] for k in ("fps_hz", "num_history_frames", "num_future_frames")
            if k in clip} if isinstance(clip, dict) else None
    path.write_text(yaml.safe_dump({"shards": str(cfg.data.shards), "encode": enc,
                                    **({"clip": clip} if clip else {}), **({"split": split} if split else {})},
                                   sort_keys=False))
    return path


def run_training(cfg: RunConfig, out: str | Path, *, resume: bool = False) -> dict:
    """Every rank: join the process group, build the model and the data stream, train, clean up."""
    # torch and the trainer only here: resolve_config and the run-folder checks answer `resim train` (its
    # --print-config, a bad config or --out) before torch loads
    import torch
    import torch.distributed as dist

    from resim.train.data import StreamLoader
    from resim.train.distributed import init_distributed
    from resim.train.trainer import Trainer

    env = init_distributed(force_group=cfg.trainer.parallel == "fsdp")
    try:
        torch.manual_seed(cfg.trainer.seed)  # identical initial weights on every rank (FSDP2 does not broadcast)
        model = registry.build(cfg.model_name, cfg.model, device="cpu")
        data = StreamLoader(cfg.data, rank=env.rank, world_size=env.world_size,
                            pin_memory=env.device.type == "cuda", verbose=env.is_main)
        summary = Trainer(model, cfg, out, resume=resume, env=env).fit(data)
        if env.is_main:
            save_data_encoding(cfg, out, data.split)
        if env.is_main and hasattr(model, "export_run"):   # e.g. the VAE's diffusers folder, final/vae/
            exported = model.export_run(out, StreamLoader(cfg.data, rank=0, world_size=1, verbose=False))
            print(f"[resim] exported {exported}", file=sys.stderr)
        if env.is_main:
            loss = summary.get("last_loss")
            print(f"[resim] done: steps {summary['start_step']} -> {summary['final_step']}, last loss "
                  f"{'n/a (no step taken)' if loss is None else format(loss, '.6g')}, data skipped {summary.get('data_skipped', 0)}, "
                  f"{summary['wall_s']:.1f} s; checkpoint {summary['checkpoint']}; "
                  f"metrics {Path(out) / 'metrics.jsonl'}; curve {summary['loss_curve']}", file=sys.stderr)
        return summary
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
