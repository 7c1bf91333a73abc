"""The settings of a sampling command beyond its inputs: what `resim sample`, `plan`, `simulate` and the rollout
`eval` commands take from ``--config FILE`` and ``--set SECTION.KEY=VALUE``, as `resim train` does.

The usage line keeps what most runs change: the inputs and outputs, ``--preset``, ``--steps``, ``--no-guidance``,
``--seed``, ``--vae`` and ``--device``. Everything else is a typed, validated config:

* ``rollout.*``: :class:`resim.sample.rollout.RolloutConfig` (``chunk_frames``, ``history_frames``,
  ``history_noise_level``, ``kv_cache``, ``guidance.scale_start``, ``guidance.schedule``, ...). Its defaults are
  the preset's, then a distilled student's own sampling section (its steps, no guidance), then ``--steps`` and
  ``--no-guidance``; the file and ``--set`` go over them.
* ``runtime.*``: :class:`RuntimeConfig`, how the command runs (text encoder, dtype, attention kernel, compile,
  batch size, per-frame actions from the trajectory).
* a command's own section where it has one (``quality.*``, ``commands.*``, ``closed_loop.*``, ...).

``--set`` applies after ``--config``, in order. The resolved settings are written with every output (rollout.yaml
and run.json, or the protocol of an eval report).

The CLIs register the two flags with ``resim.argtypes.add_settings_args`` (light: ``resim --help`` stays fast) and
import this module in their handlers.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional

from resim.config import ConfigError, apply_overrides, check_positive, from_dict, read_mapping, to_dict
from resim.diffusion.guidance import GUIDANCE_PRESETS, guidance_from_cli
from resim.sample.compile import COMPILE_CHOICES, COMPILE_MODES
from resim.sample.load import resolve_steps_and_guidance
from resim.sample.rollout import ROLLOUT_PRESETS, RolloutConfig
from resim.shipped import PLACEHOLDER_T5, shipped_dir

DEFAULT_TEXT_ENCODER = shipped_dir(PLACEHOLDER_T5)


@dataclass
class RuntimeConfig:
    """How a sampling command runs, beside what it samples (``--set runtime.KEY=VALUE``)."""
    text_encoder: Path = DEFAULT_TEXT_ENCODER   # local T5 folder for prompts not in a dataset's prompt table
    max_text_tokens: int = 226                  # T5 padding length of a prompt not in the table (CogVideoX: 226)
    size_hw: Optional[tuple[int, int]] = None   # a video history's size; None: the model's training clips'
    dtype: Literal["float32", "bfloat16", "float16"] = "float32"   # world-model weights and compute
    attention: Optional[Literal["sdpa", "flex"]] = None   # block-causal attention kernel; None: the checkpoint's
    compile: Literal[COMPILE_CHOICES] = "auto"            # torch.compile of the blocks; auto: on CUDA only
    compile_mode: Literal[COMPILE_MODES] = "default"      # reduce-overhead adds CUDA graphs
    batch_size: int = 4                         # clips rolled out together (the eval commands)
    actions_from_trajectory: bool = False       # also feed per-frame actions derived from the trajectory

    def __post_init__(self) -> None:
        check_positive("max_text_tokens", self.max_text_tokens)
        check_positive("batch_size", self.batch_size)
        if self.size_hw is not None and min(self.size_hw) < 1:
            raise ConfigError(f"size_hw={list(self.size_hw)}: both sides must be >= 1")
        if not Path(self.text_encoder).is_dir():
            raise ConfigError(f"text_encoder={self.text_encoder}: no such local folder (a T5 folder; "
                              "nothing is downloaded)")


@dataclass
class Settings:
    """A command's resolved settings: ``rollout`` and ``runtime``, its own ``sections`` (name → config), and
    ``origin``: where defaults other than the preset's came from (a distilled student's sampling section)."""
    rollout: RolloutConfig
    runtime: RuntimeConfig
    sections: dict[str, Any] = field(default_factory=dict)
    scale_start_given: bool = False   # the user set rollout.guidance.scale_start (callers with their own default)
    origin: str = ""

    def section(self, name: str) -> Any:
        return self.sections[name]

    def to_dict(self) -> dict:
        return {"rollout": to_dict(self.rollout), "runtime": to_dict(self.runtime),
                **{k: to_dict(v) for k, v in self.sections.items()}}


def read_user_settings(config: str | Path | None, overrides: list[str] | tuple[str, ...] = ()) -> dict:
    """The raw mapping of ``--config`` (optional) with ``--set`` applied; :class:`ConfigError` naming the file or
    the key for an unreadable file or a malformed override."""
    return apply_overrides(read_mapping(config) if config is not None else {}, overrides)


def rollout_config_for(checkpoint: str | Path, preset: str = "resim", steps: int | None = None,
                       no_guidance: bool = False, overrides: dict | None = None) -> tuple[RolloutConfig, str]:
    """The one way a rollout's :class:`RolloutConfig` is resolved: the preset's, then the export's own sampling
    section (a distilled student: its steps, no guidance, unless a guidance scale is given), then ``steps`` and
    ``no_guidance``, then ``overrides`` (a ``rollout`` mapping: ``{"chunk_frames": 1, "guidance": {...}}``).
    Returns (config, where defaults other than the preset's came from, or ""). Not yet checked against the run's
    noise schedule (``ddim_schedule``): that needs the loaded objective."""
    if preset not in ROLLOUT_PRESETS:
        raise ConfigError(f"unknown rollout preset {preset!r}; known: {', '.join(ROLLOUT_PRESETS)}")
    user = copy.deepcopy(dict(overrides or {}))
    g_user = user.get("guidance") or {}
    if not isinstance(g_user, dict):
        raise ConfigError(f"rollout.guidance: expected a mapping, got {g_user!r}")
    scale = g_user.get("scale_start")
    steps, guidance, origin = resolve_steps_and_guidance(checkpoint, steps, preset, no_guidance, scale)
    data: dict = dict(ROLLOUT_PRESETS[preset])
    if steps is not None:   # not `if steps`: 0 must not quietly mean the preset's 50
        data["num_steps"] = steps
    data["guidance"] = to_dict(guidance_from_cli(guidance))
    if scale is not None and guidance != "none" and GUIDANCE_PRESETS[guidance].get("schedule") == "constant":
        g_user.setdefault("scale_end", scale)   # a constant schedule keeps its scale at every step
    for k, v in user.items():
        if k == "guidance":
            data["guidance"].update(g_user)
        else:
            data[k] = v
    return from_dict(RolloutConfig, data, prefix="rollout"), origin


def resolve_settings(args: argparse.Namespace, sections: dict[str, type] | None = None) -> Settings:
    """``args``' settings: ``--preset``, ``--steps``, ``--no-guidance`` (where the command has them), ``--config``
    and ``--set``. ``sections``: the command's own sections, name → a config dataclass (built from the user's
    mapping, defaults elsewhere) or ``dict`` (the raw mapping, validated by the command). Raises
    :class:`ConfigError` (one line, naming the key) for an unknown section or key or a bad value."""
    sections = dict(sections or {})
    user = read_user_settings(getattr(args, "config", None), getattr(args, "overrides", ()))
    known = ("rollout", "runtime", *sections)
    for name, value in user.items():
        if name not in known:
            raise ConfigError(f"unknown settings section {name!r} (this command's: {', '.join(known)})")
        if not isinstance(value, dict):
            raise ConfigError(f"{name}: expected a mapping of keys, got {value!r} (--set {name}.KEY=VALUE)")
    rollout, origin = rollout_config_for(args.checkpoint, getattr(args, "preset", "resim"),
                                         getattr(args, "steps", None), getattr(args, "no_guidance", False),
                                         user.get("rollout"))
    runtime = from_dict(RuntimeConfig, user.get("runtime") or {}, prefix="runtime")
    built = {}
    for name, cls in sections.items():
        raw = user.get(name) or {}
        built[name] = dict(raw) if cls is dict else from_dict(cls, raw, prefix=name)
    given = "scale_start" in ((user.get("rollout") or {}).get("guidance") or {})
    return Settings(rollout=rollout, runtime=runtime, sections=built, scale_start_given=given, origin=origin)


def with_guidance_start(rollout: RolloutConfig, scale_start: float) -> RolloutConfig:
    """``rollout`` with another start guidance scale (a caller's own default, e.g. a closed loop's)."""
    g = rollout.guidance
    end = scale_start if g.schedule == "constant" else g.scale_end
    return dataclasses.replace(rollout, guidance=dataclasses.replace(g, scale_start=scale_start, scale_end=end))
