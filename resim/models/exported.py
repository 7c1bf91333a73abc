"""A trained model as a run exports it, and the one loader for it.

The layout (docs/training.md, "Run folder")::

    RUN/
      config.yaml              the run's resolved config
      checkpoints/step_*/      DCP state for an exact resume (resim/train/checkpoint.py), not read here
      final/
        config.yaml            the run config form: ``model_name`` (a name in resim.models.registry) + ``model`` (its
                               builder's config) [+ the run's other sections, not read here]
        model.safetensors      the weights, loaded strictly into the model built from ``config.yaml``
        ema.safetensors        (optional) the EMA weights, a complete state dict like model.safetensors
        meta.json              (optional) what else a model needs beside its weights (the reward: its feature id)

The world model, the IDM and the reward model are all found, checked, built (through ``resim.models.registry``, the
same builder training used) and loaded here; each caller keeps its own error type by catching
:class:`ExportError`, whose message names the file and the reason in one line. Files of older formats load
through caller-supplied adapters: ``adapt_config(model_cfg, state)`` before the build (an IDM run written before
the odometry head) and ``adapt_state(state, model)`` after it (LoRA keys saved before peft).

The VAE's export is not this layout: ``final/vae/`` is a diffusers folder, so that it loads with diffusers'
``from_pretrained`` like a real CogVideoX VAE (resim/train/tasks/vae.py).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import torch
import yaml
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from resim.config import ConfigError, safe_yaml, save as save_config, to_dict
from resim.media.files import NotARegularFile, read_text
from resim.models import registry
from resim.shipped import shipped_model

FINAL = "final"
CONFIG_FILE = "config.yaml"
WEIGHTS_FILE = "model.safetensors"
EMA_FILE = "ema.safetensors"
META_FILE = "meta.json"

ConfigAdapter = Callable[[dict, Mapping[str, torch.Tensor]], dict]
StateAdapter = Callable[[dict, nn.Module], dict]


class ExportError(ValueError):
    """An exported model cannot be used: the message names the file and the reason, in one line."""


class ExportNotFoundError(ExportError):
    """Neither the folder nor its ``final/`` holds ``config.yaml`` + ``model.safetensors``."""


@dataclass(frozen=True)
class ExportedConfig:
    path: Path                  # the config.yaml read
    model_name: str
    model: dict[str, Any]       # the ``model`` section (a copy)
    raw: dict[str, Any]         # the whole file


@dataclass
class Exported:
    model: nn.Module            # built and loaded, on the CPU, in eval mode
    folder: Path                # the folder holding the files (RUN/final, or RUN itself)
    weights: Path               # the file the weights came from (model.safetensors or ema.safetensors)
    config: ExportedConfig

    @property
    def model_name(self) -> str:
        return self.config.model_name


def find_export(path: str | Path, *, shipped: bool = False) -> Path:
    """The folder holding ``config.yaml`` + ``model.safetensors``: ``path`` itself or ``path/final``.
    ``shipped``: a bare name of ``configs/models`` (``synth-world``) stands for that shipped folder."""
    p = Path(shipped_model(path)) if shipped else Path(path)
    for cand in (p, p / FINAL):
        if (cand / WEIGHTS_FILE).is_file() and (cand / CONFIG_FILE).is_file():
            return cand
    raise ExportNotFoundError(f"{p}: expected {CONFIG_FILE} + {WEIGHTS_FILE} in it or in {p / FINAL}")


def read_config(folder: str | Path, *, expect: str | None = None, label: str | None = None,
                default_name: str | None = None) -> ExportedConfig:
    """``folder/config.yaml`` (safe YAML), checked: a mapping, ``model_name`` a string (``default_name`` when the
    key is absent), equal to ``expect`` when given (else :class:`ExportError` "... not {label}"), ``model`` a
    mapping."""
    path = Path(folder) / CONFIG_FILE
    try:
        raw = safe_yaml(read_text(path))
    except NotARegularFile as e:
        raise ExportError(str(e)) from None
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as e:
        raise ExportError(f"{path}: invalid YAML ({' '.join(str(e).split())})") from None
    if raw is None:   # an empty file: the model it describes is unknown, and defaults would sample another one
        raise ExportError(f"{path}: empty; a model folder's config.yaml names its model (model_name, model)")
    if not isinstance(raw, dict):
        raise ExportError(f"{path}: expected a mapping with model_name and model, got {type(raw).__name__}")
    name = raw.get("model_name", default_name)
    if expect is not None and name != expect:
        raise ExportError(f"{path}: model_name is {name!r}, not {label or repr(expect)}")
    if not isinstance(name, str):
        raise ExportError(f"{path}: model_name must be a string naming a model of resim.models.registry, got {name!r}")
    model = raw.get("model") or {}
    if not isinstance(model, dict):
        raise ExportError(f"{path}: model must be a mapping (the model's config), got {type(model).__name__}")
    return ExportedConfig(path, name, dict(model), raw)


def read_weights(path: str | Path) -> dict[str, torch.Tensor]:
    """A safetensors file as a CPU state dict; :class:`ExportError` naming it when it cannot be read."""
    try:
        return load_file(str(path), device="cpu")
    except (SafetensorError, OSError) as e:
        raise ExportError(f"{path}: not a readable safetensors file ({e})") from None


def load_weights(model: nn.Module, state: Mapping[str, torch.Tensor], path: str | Path) -> None:
    """``model.load_state_dict(state, strict=True)``; :class:`ExportError` naming ``path`` when the tensors do not
    fit the model built from the config (missing / unexpected keys, other shapes)."""
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as e:   # torch's "Error(s) in loading state_dict ...", then the keys / shapes
        lines = [x.strip() for x in str(e).strip().splitlines()]
        raise ExportError(f"{path}: weights do not match {CONFIG_FILE} ({' '.join(lines[:2])[:300]})") from None


def load_exported(path: str | Path, *, expect: str | None = None, label: str | None = None,
                  default_name: str | None = None, shipped: bool = False, prefer_ema: bool = False,
                  adapt_config: ConfigAdapter | None = None, adapt_state: StateAdapter | None = None,
                  build_errors: tuple[type[BaseException], ...] = ()) -> Exported:
    """Find (:func:`find_export`), read and check (:func:`read_config`), build through ``resim.models.registry`` and
    load an exported model strictly. ``ema.safetensors`` is used instead of ``model.safetensors`` when
    ``prefer_ema`` and present. ``build_errors``: the builder's own exceptions for a bad model config (beside
    ``ConfigError``), reported as config.yaml errors. Every problem with the files is an :class:`ExportError`."""
    folder = find_export(path, shipped=shipped)
    cfg = read_config(folder, expect=expect, label=label, default_name=default_name)
    weights = folder / EMA_FILE if prefer_ema and (folder / EMA_FILE).is_file() else folder / WEIGHTS_FILE
    state = read_weights(weights)
    model_cfg = adapt_config(dict(cfg.model), state) if adapt_config else dict(cfg.model)
    if cfg.model_name not in registry.names():
        raise ExportError(f"{cfg.path}: model_name {cfg.model_name!r} has no builder in resim.models.registry "
                          f"(registered: {', '.join(registry.names())})")
    try:
        model = registry.build(cfg.model_name, model_cfg, device="cpu")
    except (ConfigError, *build_errors) as e:
        raise ExportError(f"{cfg.path}: {e}") from None
    if adapt_state is not None:
        state = adapt_state(state, model)
    load_weights(model, state, weights)
    return Exported(model.eval(), folder, weights, cfg)


def write_export(folder: str | Path, state: Mapping[str, torch.Tensor], config: Any,
                 ema: Mapping[str, torch.Tensor] | None = None) -> Path:
    """Write ``folder/model.safetensors`` (+ ``ema.safetensors``, a complete state dict too) and
    ``folder/config.yaml`` (``config``: a run config dataclass or a mapping with ``model_name`` + ``model``), each
    atomically (a reader never sees half a file). The Trainer's ``final/`` and the reward model's are written here."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    cfg = to_dict(config)   # a dataclass or a mapping
    if not isinstance(cfg.get("model_name"), str) or not isinstance(cfg.get("model"), Mapping):
        raise ValueError(f"an export's config needs model_name and model, got keys {sorted(cfg)}")   # our bug
    for name, sd in ((WEIGHTS_FILE, state), (EMA_FILE, ema)):
        if sd is None:
            continue
        tmp = out / (name + ".tmp")
        save_file({k: v.detach().contiguous().cpu() for k, v in sd.items()}, str(tmp))
        os.replace(tmp, out / name)
    save_config(cfg, out / CONFIG_FILE)   # atomic, the same YAML as every resolved config
    return out
