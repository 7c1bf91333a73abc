"""Save / load a trained Video2Reward (safetensors + resolved config + metadata; no pickle).

Layout of a checkpoint folder::

    config.yaml        resolved RewardTrainConfig (model config under `model`)
    reward.safetensors head weights (+ backbone weights when it was fine-tuned)
    meta.json          model.metadata() + metrics, placeholder flags
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from resim import config as rconfig
from training.reward.config import RewardTrainConfig
from training.reward.model import Video2Reward


class CheckpointError(ValueError):
    """A folder is not a usable reward checkpoint (names the file and the reason)."""


def json_safe(o: Any) -> Any:
    """``o`` as plain JSON values with non-finite floats made ``None``.

    Metrics are nan when undefined (Spearman of one clip, AUC of one class); ``json.dumps`` would write a
    bare ``NaN``, which strict JSON parsers (and most non-Python readers) reject. ``None`` (null) says
    "undefined" in valid JSON (``training.eval.report`` writes them as strings unless asked otherwise)."""
    from training.eval.report import _plain

    return _plain(o, null_nonfinite=True)


def write_json(obj: Any, path: str | Path, indent: int = 2) -> Path:
    """Strict JSON, nan/inf as null (:func:`json_safe`), written atomically (``training.eval.report.write_json``)."""
    from training.eval.report import write_json as _write

    return _write(obj, path, null_nonfinite=True, indent=indent)


def save_checkpoint(model: Video2Reward, out_dir: str | Path, train_cfg: RewardTrainConfig,
                    extra_meta: dict | None = None) -> Path:
    from safetensors.torch import save_file

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    state = {f"head.{k}": v.detach().contiguous().cpu() for k, v in model.head.state_dict().items()}
    if not model.cfg.freeze_backbone:
        state.update({f"backbone.{k}": v.detach().contiguous().cpu() for k, v in model.backbone.state_dict().items()})
    tmp = out / "reward.safetensors.tmp"
    save_file(state, str(tmp))
    tmp.replace(out / "reward.safetensors")
    rconfig.save(train_cfg, out / "config.yaml")
    meta = {**model.metadata(), **(extra_meta or {})}
    write_json(meta, out / "meta.json")
    return out


def load_checkpoint(ckpt_dir: str | Path, device: str = "cpu") -> Video2Reward:
    """Load a checkpoint folder. Anything wrong with its files (missing, corrupt, not matching each other,
    a backbone folder that is gone) raises :class:`CheckpointError` naming the file and the reason."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from training.reward.backbone import BackboneError

    d = Path(ckpt_dir)
    if not d.is_dir():
        raise CheckpointError(f"{d}: no such checkpoint folder")
    for f in ("config.yaml", "reward.safetensors"):
        if not (d / f).is_file():
            raise CheckpointError(f"{d} is not a reward checkpoint: {f} is missing")
    # Checkpoints saved before the head got its sigmoid (output_activation) were trained with a raw
    # linear output: a config.yaml without the key loads as "none", not as today's default.
    try:
        cfg = rconfig.load(RewardTrainConfig, d / "config.yaml", base={"model": {"output_activation": "none"}})
    except (rconfig.ConfigError, UnicodeDecodeError) as e:  # invalid values / YAML, or not a text file
        raise CheckpointError(f"{d / 'config.yaml'}: {e}") from None
    try:
        model = Video2Reward(cfg.model)
    except BackboneError as e:
        raise CheckpointError(f"{d / 'config.yaml'}: model.backbone_dir: {e}") from None
    try:
        state = load_file(str(d / "reward.safetensors"), device="cpu")
    except SafetensorError as e:
        raise CheckpointError(f"{d / 'reward.safetensors'}: not a readable safetensors file ({e})") from None
    head = {k[5:]: v for k, v in state.items() if k.startswith("head.")}
    bb = {k[9:]: v for k, v in state.items() if k.startswith("backbone.")}
    try:
        model.head.load_state_dict(head, strict=True)
        if bb:
            model.backbone.load_state_dict(bb, strict=True)
    except RuntimeError as e:  # torch's missing/unexpected keys or shape mismatches: weights vs config.yaml
        first = str(e).strip().splitlines()
        raise CheckpointError(f"{d / 'reward.safetensors'}: weights do not match config.yaml "
                              f"({' '.join(x.strip() for x in first[:2])[:300]})") from None
    meta_p = d / "meta.json"
    if meta_p.is_file():
        try:
            meta = json.loads(meta_p.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CheckpointError(f"{meta_p}: not valid JSON ({e})") from None
        saved_id = meta.get("feature_id") if isinstance(meta, dict) else None
        if saved_id and saved_id != model.feature_id:
            raise CheckpointError(f"{d}: trained with backbone features {saved_id!r}, the backbone loaded now "
                                  f"gives {model.feature_id!r} (backbone folder or seed changed)")
    return model.to(device).eval()
