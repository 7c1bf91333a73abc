"""Save / load a trained Video2Reward (safetensors + resolved config + metadata; no pickle).

Layout of a checkpoint folder::

    config.yaml        resolved RewardTrainConfig (model config under `model`)
    reward.safetensors head weights (+ backbone weights when it was fine-tuned)
    meta.json          model.metadata() + metrics, placeholder flags
"""
from __future__ import annotations

import json
from pathlib import Path

from resim import config as rconfig
from training.reward.config import RewardTrainConfig
from training.reward.model import Video2Reward


class CheckpointError(ValueError):
    pass


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
    (out / "meta.json").write_text(json.dumps(meta, indent=2, default=float))
    return out


def load_checkpoint(ckpt_dir: str | Path, device: str = "cpu") -> Video2Reward:
    from safetensors.torch import load_file

    d = Path(ckpt_dir)
    for f in ("config.yaml", "reward.safetensors"):
        if not (d / f).is_file():
            raise CheckpointError(f"{d} is not a reward checkpoint: {f} is missing")
    # Checkpoints saved before the head got its sigmoid (output_activation) were trained with a raw
    # linear output: a config.yaml without the key loads as "none", not as today's default.
    cfg = rconfig.load(RewardTrainConfig, d / "config.yaml", base={"model": {"output_activation": "none"}})
    model = Video2Reward(cfg.model)
    state = load_file(str(d / "reward.safetensors"), device="cpu")
    head = {k[5:]: v for k, v in state.items() if k.startswith("head.")}
    model.head.load_state_dict(head, strict=True)
    bb = {k[9:]: v for k, v in state.items() if k.startswith("backbone.")}
    if bb:
        model.backbone.load_state_dict(bb, strict=True)
    meta_p = d / "meta.json"
    if meta_p.is_file():
        saved_id = json.loads(meta_p.read_text()).get("feature_id")
        if saved_id and saved_id != model.feature_id:
            raise CheckpointError(f"{d}: trained with backbone features {saved_id!r}, the backbone loaded now "
                                  f"gives {model.feature_id!r} (backbone folder or seed changed)")
    return model.to(device).eval()
