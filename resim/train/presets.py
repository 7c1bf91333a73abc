"""The shipped training recipes: ``configs/train/<model>/<preset>.yaml``, one run config each.

``PRESETS[model_name][preset]`` is the recipe's dict, which `resim train NAME --preset P` resolves into a
``RunConfig`` (``--set`` on top; the resolved config is saved with the run). Each file says in its header what it
is for and where it starts from. The world model's ReSim stages follow Table S.1 of arXiv 2506.09981; the
synthetic world's recipes are documented in docs/models/.
"""
from __future__ import annotations

import copy
from pathlib import Path

from resim.config import ConfigError, safe_yaml
from resim.shipped import configs_dir

MODELS = ("world", "vae", "distill")   # `resim train NAME` for these; reward and policy have their own data paths
DEFAULT = {"world": "tiny", "vae": "synth", "distill": "synth"}   # `--preset` when none is given: listed first


def recipes_dir() -> Path:
    """``configs/train`` of this checkout, else of the working dir (as the shipped model folders)."""
    return configs_dir("train")


def load_recipes(root: Path) -> dict[str, dict[str, dict]]:
    """Every ``root/<model>/<preset>.yaml``, checked: a mapping whose ``model_name`` is its folder and whose
    ``preset`` is its name (a copied file that was not renamed inside would train under the wrong name)."""
    out: dict[str, dict[str, dict]] = {m: {} for m in MODELS}
    for model in MODELS:
        for f in sorted((root / model).glob("*.yaml"), key=lambda f: f.stem):
            d = safe_yaml(f.read_text())
            if not isinstance(d, dict):
                raise ConfigError(f"{f}: a training recipe must be a mapping, got {type(d).__name__}")
            if d.get("model_name") != model or d.get("preset") != f.stem:
                raise ConfigError(f"{f}: model_name {d.get('model_name')!r} and preset {d.get('preset')!r} must be "
                                  f"{model!r} and {f.stem!r} (its folder and file name)")
            out[model][f.stem] = d
        if DEFAULT[model] in out[model]:
            out[model] = {DEFAULT[model]: out[model].pop(DEFAULT[model]), **out[model]}
    return out


# model name -> its presets; `resim train NAME` exists for every name here (the reward model adds "reward")
PRESETS: dict[str, dict[str, dict]] = load_recipes(recipes_dir())
WORLD_PRESETS, VAE_PRESETS, DISTILL_PRESETS = PRESETS["world"], PRESETS["vae"], PRESETS["distill"]


def get_preset(model_name: str, preset: str) -> dict:
    if model_name not in PRESETS:
        raise KeyError(f"no presets for model {model_name!r}; known: {sorted(PRESETS)}")
    table = PRESETS[model_name]
    if not table:
        raise KeyError(f"no training recipes for {model_name}: {recipes_dir()} is missing (run from a checkout of "
                       "resim, where configs/train/ holds them)")
    if preset not in table:
        raise KeyError(f"unknown preset {preset!r} for {model_name}; known: {', '.join(table)}")
    return copy.deepcopy(table[preset])
