"""LoRA on the DiT's linears through ``peft`` (ReSim Table S.1: LoRA trains in stages 2 and 3, with the DiT frozen in
stage 2). The only file of ``training`` that imports peft.

``add_lora(model, targets, rank, alpha)`` injects adapters in place (``peft.inject_adapter_in_model``: no
``PeftModel`` wrapper, so the model keeps its ``forward``/``loss`` and the trainer sees the same module) into every
``nn.Linear`` of ``model.transformer_blocks`` whose name ends with one of ``targets`` (``to_q``, ``to_out.0``,
``ff.net.2``, ...: diffusers' CogVideoX module names). Each computes ``y = W x + b + (alpha / rank) B A x``, ``A``
kaiming-uniform, ``B`` zero, so the model's output is unchanged at the start. Which parameters train is the
caller's choice (``resim.train.tasks.world_model``'s ``trainable``; :func:`is_lora_param` tells the adapters apart).
``merge_lora(model)`` folds the adapters into the base weights (same outputs, plain ``nn.Linear`` again).

Checkpoint layout. In memory, and so in every state dict the trainer writes, names are peft's:
``...to_q.base_layer.weight``, ``...to_q.lora_A.default.weight`` (rank, in), ``...to_q.lora_B.default.weight``
(out, rank). The DCP checkpoints (model and optimizer state by parameter name, for exact resume), the EMA (by
parameter name) and ``final/*.safetensors`` (``get_model_state_dict``) all take the names of the live parameters;
keeping another layout on disk would mean renaming in each of them, in both directions, under FSDP. Instead a
weights file is put into this layout when it is loaded (:func:`to_peft_layout`): a stage-1 file (no adapters,
``...to_q.weight``) and a file written by the hand-written ``LoRALinear`` this module replaced (``...to_q.weight``,
``...to_q.lora_A``, ``...to_q.lora_B``, same shapes) both load. ``tests/data/lora-v1-world`` is such a file. A
DCP checkpoint of a run started before the switch resumes under the old names (:func:`pre_peft_name`, passed by
the trainer to ``resim.train.checkpoint.load``).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Mapping

import torch
from torch import nn

if TYPE_CHECKING:
    from peft.tuners.lora import LoraLayer

# peft is imported by the two functions that use it, not here: it pulls in transformers (measured: `import peft`
# after torch costs 1-2x torch's own import time on the 2-core CPU), and every process that imports the world model
# paid it, LoRA or not. (A process that loads the CogVideoX VAE still does: diffusers' autoencoders import peft.)
# The renaming helpers below are plain string work.

ADAPTER = "default"   # peft's adapter name: one adapter per model


def lora_targets(model: nn.Module, targets: tuple[str, ...]) -> list[str]:
    """Names (in ``model``) of the ``nn.Linear`` layers of the DiT blocks that ``targets`` select, in module order;
    only the blocks: the trajectory/action encoders train fully where they train at all."""
    return [f"transformer_blocks.{n}" for n, m in model.transformer_blocks.named_modules()
            if type(m) is nn.Linear and any(n == t or n.endswith("." + t) for t in targets)]


def add_lora(model: nn.Module, targets: tuple[str, ...], rank: int, alpha: float) -> list[str]:
    """Inject LoRA adapters (scale ``alpha / rank``) into the selected linears of the DiT blocks, in place;
    return the wrapped layers' names. Leaves ``requires_grad`` as peft sets it (adapters only): set it after."""
    if rank < 1:
        raise ValueError(f"LoRA rank must be >= 1, got {rank}")
    names = lora_targets(model, tuple(targets))
    if not names:
        raise ValueError(f"LoRA targets {tuple(targets)} match no nn.Linear in the transformer blocks of "
                         f"{type(model).__name__}")
    from peft import LoraConfig, inject_adapter_in_model   # heavy, LoRA only (above)

    weights = [model.get_submodule(n).weight for n in names]
    cuda = sorted({w.device.index or 0 for w in weights if w.is_cuda})
    # peft's own initialisation draws from the RNG in another order; it is undone (fork_rng) and the draws of the
    # replaced LoRALinear are made instead (_init_as_before), so a seeded run builds the same weights as before
    with torch.random.fork_rng(devices=cuda):
        inject_adapter_in_model(LoraConfig(r=rank, lora_alpha=alpha, lora_dropout=0.0, target_modules=names,
                                           init_lora_weights=True), model, adapter_name=ADAPTER)
    for n in names:
        _init_as_before(model.get_submodule(n))
    return names


@torch.no_grad()
def _init_as_before(layer: LoraLayer) -> None:
    """``A`` kaiming-uniform (``nn.Linear``'s default; Hu et al. 2021's LoRA code), ``B`` zero, with the random
    draws the hand-written ``LoRALinear`` made: its own ``nn.Linear.__init__`` first (a weight and a bias it then
    replaced by the base layer's), then ``A``."""
    base, a = layer.get_base_layer(), layer.lora_A[ADAPTER].weight
    layer.lora_B[ADAPTER].weight.zero_()
    if a.is_meta:
        return
    nn.Linear(base.in_features, base.out_features, bias=base.bias is not None, device=a.device, dtype=a.dtype)
    nn.init.kaiming_uniform_(a, a=math.sqrt(5))


def is_lora_param(name: str) -> bool:
    """Whether a parameter (or state-dict key) of a model with adapters is a LoRA weight."""
    return ".lora_A." in name or ".lora_B." in name


# peft's name → the name the hand-written LoRALinear gave the same tensor (it kept the base layer's own names)
_PRE_PEFT = ((".base_layer.weight", ".weight"), (".base_layer.bias", ".bias"),
             (f".lora_A.{ADAPTER}.weight", ".lora_A"), (f".lora_B.{ADAPTER}.weight", ".lora_B"))


def pre_peft_name(name: str) -> str:
    """The name a tensor of a LoRA layer had before peft (``...to_q.base_layer.weight`` → ``...to_q.weight``,
    ``...to_q.lora_A.default.weight`` → ``...to_q.lora_A``); any other name unchanged. Also what
    ``resim.train.checkpoint.load`` reads a pre-peft DCP checkpoint with (``TrainableWorldModel.legacy_param_name``)."""
    for new, old in _PRE_PEFT:
        if name.endswith(new):
            return name[: -len(new)] + old
    return name


def to_peft_layout(state: Mapping[str, torch.Tensor], model: nn.Module) -> dict[str, torch.Tensor]:
    """``state`` with the pre-peft names of ``model``'s LoRA-layer tensors renamed to peft's (``...to_q.weight`` →
    ``...to_q.base_layer.weight``, ``...to_q.lora_A`` → ``...to_q.lora_A.default.weight``): a stage-1 file or a
    pre-peft LoRA file loads into a model with adapters. Other keys, and files in peft's layout, pass unchanged."""
    current = {pre_peft_name(k): k for k in model.state_dict()}
    return {current.get(k, k): t for k, t in state.items()}


@torch.no_grad()
def merge_lora(model: nn.Module) -> nn.Module:
    """Fold every LoRA adapter into its base layer and put the base layer back (in place)."""
    from peft.tuners.lora import LoraLayer   # heavy, LoRA only (above)

    for name, mod in [(n, m) for n, m in model.named_modules() if isinstance(m, LoraLayer)]:
        mod.merge()
        parent_name, _, attr = name.rpartition(".")
        parent = model.get_submodule(parent_name) if parent_name else model
        setattr(parent, attr, mod.get_base_layer())
    return model
