"""Reading CogVideoX transformer weights: from a diffusers model instance or a local ``save_pretrained`` folder.

Only torch and (for ``*.safetensors``) the ``safetensors`` package are used: no diffusers import, no network.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file


def _folder(src: Path) -> Path:
    if (src / "config.json").is_file():
        return src
    if (src / "transformer" / "config.json").is_file():  # a whole pipeline folder
        return src / "transformer"
    raise FileNotFoundError(f"{src}: no config.json (nor transformer/config.json): not a diffusers model folder")


def _read_weights(folder: Path) -> dict[str, torch.Tensor]:
    index = sorted(folder.glob("*.safetensors.index.json"))
    singles = sorted(folder.glob("*.safetensors"))
    if index or singles:
        files = singles
        if index:
            names = sorted(set(json.loads(index[0].read_text())["weight_map"].values()))
            files = [folder / n for n in names]
        state: dict[str, torch.Tensor] = {}
        for f in files:
            state.update(load_file(str(f)))
        return state
    bins = sorted(folder.glob("*.bin"))
    if bins:
        state = {}
        for f in bins:
            state.update(torch.load(f, map_location="cpu", weights_only=True))
        return state
    raise FileNotFoundError(f"{folder}: no *.safetensors or *.bin weights")


def cogvideox_num_train_timesteps(src: Any) -> int | None:
    """``num_train_timesteps`` of the scheduler saved with a CogVideoX transformer folder (a pipeline folder's
    ``scheduler/scheduler_config.json``, diffusers' default 1000 where the key is absent), or None where there is
    none (a bare transformer folder, or a model instance)."""
    if not isinstance(src, (str, Path)):
        return None
    folder = _folder(Path(src))
    root = folder.parent if folder.name == "transformer" else folder
    path = root / "scheduler" / "scheduler_config.json"
    if not path.is_file():
        return None
    return int(json.loads(path.read_text()).get("num_train_timesteps", 1000))


def load_cogvideox_state(src: Any) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """``(config dict, state dict)`` of a CogVideoX transformer given as an instance or a folder path."""
    if isinstance(src, (str, Path)):
        folder = _folder(Path(src))
        config = json.loads((folder / "config.json").read_text())
        if config.get("_class_name", "CogVideoXTransformer3DModel") != "CogVideoXTransformer3DModel":
            raise ValueError(f"{folder}: _class_name is {config['_class_name']!r}, expected CogVideoXTransformer3DModel")
        return config, _read_weights(folder)
    if hasattr(src, "config") and hasattr(src, "state_dict"):
        return dict(src.config), src.state_dict()
    raise TypeError(f"from_cogvideox expects a CogVideoXTransformer3DModel or a folder path, got {type(src).__name__}")
