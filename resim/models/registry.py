"""Model registry: name -> builder, so `resim train <name>` and the launcher's dry run can build any
trainable model without importing every model package up front.

A builder is ``build(model_cfg: dict, *, device: str | torch.device = "cpu") -> nn.Module``; the
returned module has ``loss(batch) -> (loss, logs)``. ``device="meta"`` must work (the launcher's
``--dry-run`` counts parameters and estimates memory without allocating). Optional hooks the
trainer/launcher use when present: ``fsdp_units()``, ``set_activation_checkpointing(bool)``,
``tokens_per_sample(batch)``, ``flops_per_sample(batch)``, ``activation_bytes_per_sample(ac: bool)``.

Entries are ``"module:function"`` strings, imported on first use. To add a model (e.g. the reward
model) add one line to ``BUILDERS`` (or call ``register`` at import time of a plugin).
"""
from __future__ import annotations

import importlib
from typing import Any, Callable

BUILDERS: dict[str, str] = {
    "world": "resim.train.tasks.world_model:build_world",
    "vae": "resim.train.tasks.vae:build_vae",
    "reward": "resim.train.tasks.reward.train:build_reward",
    "idm": "resim.models.idm:build_idm",
    "policy": "resim.models.policy.model:build_policy",
    "distill": "resim.train.tasks.distill:build_distill",
}


def register(name: str, target: str | Callable[..., Any]) -> None:
    """Add a model builder (``"module:function"`` or a callable)."""
    BUILDERS[name] = target  # type: ignore[assignment]


def names() -> list[str]:
    return sorted(BUILDERS)


def get_builder(name: str) -> Callable[..., Any]:
    if name not in BUILDERS:
        raise KeyError(f"unknown model {name!r}; registered: {', '.join(names())}")
    target = BUILDERS[name]
    if callable(target):
        return target
    mod, _, fn = target.partition(":")
    return getattr(importlib.import_module(mod), fn)


def build(name: str, model_cfg: dict | None = None, **kwargs: Any):
    return get_builder(name)(dict(model_cfg or {}), **kwargs)
