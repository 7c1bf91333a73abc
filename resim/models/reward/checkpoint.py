"""Save / load a trained Video2Reward (safetensors + resolved config + metadata; no pickle).

A reward run's folder, in the layout every trained model shares (``resim.models.exported``, docs/training.md)::

    config.yaml              the run's resolved RewardTrainConfig
    final/config.yaml        model_name: reward + model: the RewardModelConfig (the run config form)
    final/model.safetensors  head weights (+ backbone weights when it was fine-tuned)
    final/meta.json          model.metadata() (the backbone feature id, ...) + metrics, placeholder flags

A frozen backbone is not stored: its weights come from ``model.backbone_dir`` (+ ``backbone_init_seed`` for a
placeholder), and meta.json's ``feature_id`` checks that they are the ones the head was trained on.

Runs written before this layout (``RUN/reward.safetensors`` beside a RewardTrainConfig ``config.yaml`` and
``meta.json``) still load: :func:`load_checkpoint` reads them as they were written.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml

from resim import config as rconfig
from resim.config import to_dict
from resim.models.exported import (FINAL, META_FILE, ExportError, ExportNotFoundError, load_exported, load_weights,
                               read_weights, write_export)
from resim.models.reward.backbone import BackboneError
from resim.models.reward.config import RewardModelConfig
from resim.models.reward.model import Video2Reward
from resim.shards.safejson import plain as _plain, write_json as _write_json

OLD_WEIGHTS = "reward.safetensors"   # the weights file of runs written before the shared layout


class CheckpointError(ValueError):
    """A folder is not a usable reward checkpoint (names the file and the reason)."""


def json_safe(o: Any) -> Any:
    """``o`` as plain JSON values with non-finite floats made ``None``.

    Metrics are nan when undefined (Spearman of one clip, AUC of one class); ``json.dumps`` would write a
    bare ``NaN``, which strict JSON parsers (and most non-Python readers) reject. ``None`` (null) says
    "undefined" in valid JSON (``resim.eval.report`` writes them as strings unless asked otherwise)."""
    return _plain(o, null_nonfinite=True)


def write_json(obj: Any, path: str | Path, indent: int = 2) -> Path:
    """Strict JSON, nan/inf as null (:func:`json_safe`), written atomically (``resim.eval.report.write_json``)."""
    return _write_json(obj, path, null_nonfinite=True, indent=indent)


def save_checkpoint(model: Video2Reward, out_dir: str | Path, train_cfg: Any,
                    extra_meta: dict | None = None, run_cfg: Any = None) -> Path:
    """Write the run's ``config.yaml`` (``train_cfg``, its resolved training config: a
    ``resim.train.tasks.reward.config.RewardTrainConfig``) and ``final/`` (module docstring). ``run_cfg``: the common
    trainer's resolved config of the run, saved as ``final/config.yaml`` like every trainer export; without it
    that file holds only ``model_name`` and ``model``, which is all a loader reads."""
    out = Path(out_dir)
    state = {f"head.{k}": v for k, v in model.head.state_dict().items()}
    if not model.cfg.freeze_backbone:
        state.update({f"backbone.{k}": v for k, v in model.backbone.state_dict().items()})
    final = write_export(out / FINAL, state, run_cfg if run_cfg is not None
                         else {"model_name": "reward", "model": to_dict(model.cfg)})
    rconfig.save(train_cfg, out / "config.yaml")
    write_json({**model.metadata(), **(extra_meta or {})}, final / META_FILE)
    return out


def _with_frozen_backbone(state: dict, model: Video2Reward) -> dict:
    """A frozen backbone is not saved: the built model's (from backbone_dir) completes the state dict."""
    if any(k.startswith("backbone.") for k in state):
        return state
    return {**{f"backbone.{k}": v for k, v in model.backbone.state_dict().items()}, **state}


def load_checkpoint(ckpt_dir: str | Path, device: str = "cpu") -> Video2Reward:
    """Load a reward run (its folder or its ``final/``), or a run of the older layout. Anything wrong with its files
    (missing, corrupt, not matching each other, a backbone folder that is gone) raises :class:`CheckpointError`
    naming the file and the reason."""
    d = Path(ckpt_dir)
    if not d.is_dir():
        raise CheckpointError(f"{d}: no such checkpoint folder")
    if (d / OLD_WEIGHTS).is_file():
        model, meta_p = _load_old(d), d / META_FILE
    else:
        try:
            ex = load_exported(d, expect="reward", label="a reward run", adapt_state=_with_frozen_backbone,
                               build_errors=(BackboneError,))
        except ExportNotFoundError:
            raise CheckpointError(f"{d} is not a reward checkpoint: no config.yaml + model.safetensors in it or "
                                  f"in {d / FINAL} (nor the {OLD_WEIGHTS} of an older run)") from None
        except ExportError as e:
            raise CheckpointError(str(e)) from None
        model, meta_p = ex.model, ex.folder / META_FILE
    _check_features(model, meta_p)
    return model.to(device).eval()


def _check_features(model: Video2Reward, meta_p: Path) -> None:
    """The head was trained on the features meta.json names: the backbone loaded now must give the same."""
    if not meta_p.is_file():
        return
    try:
        meta = json.loads(meta_p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{meta_p}: not valid JSON ({e})") from None
    saved_id = meta.get("feature_id") if isinstance(meta, dict) else None
    if saved_id and saved_id != model.feature_id:
        raise CheckpointError(f"{meta_p.parent}: trained with backbone features {saved_id!r}, the backbone loaded "
                              f"now gives {model.feature_id!r} (backbone folder or seed changed)")


def _load_old(d: Path) -> Video2Reward:
    """A run written before the shared layout: ``config.yaml`` a RewardTrainConfig, ``reward.safetensors``."""
    if not (d / "config.yaml").is_file():
        raise CheckpointError(f"{d} is not a reward checkpoint: config.yaml is missing")
    # Checkpoints saved before the head got its sigmoid (output_activation) were trained with a raw
    # linear output: a config.yaml without the key loads as "none", not as today's default.
    # Only its model section is read: the rest is how it was trained.
    try:
        raw = rconfig.safe_yaml((d / "config.yaml").read_text())
        section = raw.get("model") if isinstance(raw, dict) else None
        if not isinstance(section, dict):
            raise rconfig.ConfigError("no model section (a RewardTrainConfig has one)")
        mcfg = rconfig.from_dict(RewardModelConfig, {"output_activation": "none", **section}, prefix="model")
    except (rconfig.ConfigError, UnicodeDecodeError, yaml.YAMLError) as e:  # invalid values / YAML, not text
        raise CheckpointError(f"{d / 'config.yaml'}: {e}") from None
    try:
        model = Video2Reward(mcfg)
    except BackboneError as e:
        raise CheckpointError(f"{d / 'config.yaml'}: model.backbone_dir: {e}") from None
    try:
        state = read_weights(d / OLD_WEIGHTS)
        head = {k[5:]: v for k, v in state.items() if k.startswith("head.")}
        bb = {k[9:]: v for k, v in state.items() if k.startswith("backbone.")}
        load_weights(model.head, head, d / OLD_WEIGHTS)
        if bb:
            load_weights(model.backbone, bb, d / OLD_WEIGHTS)
    except ExportError as e:
        raise CheckpointError(str(e)) from None
    return model
