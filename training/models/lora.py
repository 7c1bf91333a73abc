"""LoRA on the DiT's attention and MLP projections through ``peft`` (ReSim stage 2: frozen DiT, trainable LoRA +
trajectory encoder; Table S.1). The only file of ``training/models`` that imports peft.

``add_lora(model, rank, ...)`` injects adapters in place (``peft.inject_adapter_in_model``, no PeftModel wrapper,
so the model keeps its ``forward``/``loss``) and leaves ``requires_grad`` only on the LoRA weights and the new
modules (trajectory/action encoders). ``merge_lora(model)`` folds the adapters into the base weights and removes
them (same outputs, plain ``nn.Linear`` again). Target names equal diffusers' CogVideoX LoRA targets.
"""
from __future__ import annotations

from dataclasses import dataclass

from torch import nn

from training.models.dit import NEW_MODULE_PREFIXES, WorldModel

DEFAULT_TARGETS = ("to_q", "to_k", "to_v", "to_out.0", "ff.net.0.proj", "ff.net.2")


@dataclass
class LoraSettings:
    rank: int = 64
    alpha: float = 64.0
    dropout: float = 0.0
    target_modules: tuple[str, ...] = DEFAULT_TARGETS
    train_new_modules: bool = True   # trajectory / action encoders stay trainable (ReSim stage 2)


def add_lora(model: WorldModel, settings: LoraSettings | None = None, adapter_name: str = "default") -> WorldModel:
    """Inject LoRA adapters into the DiT blocks (in place) and freeze everything else but the new modules."""
    from peft import LoraConfig, inject_adapter_in_model

    s = settings or LoraSettings()
    # match only inside the transformer blocks (the trajectory encoder has its own, fully trained, layers)
    pattern = r"transformer_blocks\.\d+\.(attn1\.)?(" + "|".join(t.replace(".", r"\.") for t in s.target_modules) + r")"
    cfg = LoraConfig(r=s.rank, lora_alpha=s.alpha, lora_dropout=s.dropout, target_modules=pattern,
                     init_lora_weights=True)
    inject_adapter_in_model(cfg, model, adapter_name=adapter_name)
    for name, p in model.named_parameters():
        p.requires_grad = "lora_" in name or (s.train_new_modules and name.startswith(NEW_MODULE_PREFIXES))
    return model


def merge_lora(model: nn.Module) -> nn.Module:
    """Fold every LoRA adapter into its base layer and put the base layer back (in place)."""
    from peft.tuners.lora import LoraLayer

    targets = [(n, m) for n, m in model.named_modules() if isinstance(m, LoraLayer)]
    for name, mod in targets:
        mod.merge()
        parent_name, _, attr = name.rpartition(".")
        parent = model.get_submodule(parent_name) if parent_name else model
        setattr(parent, attr, mod.get_base_layer())
    return model


def lora_state_dict(model: nn.Module) -> dict:
    """Only the trainable tensors (LoRA + new modules): what a stage-2 checkpoint needs to store."""
    return {n: p.detach() for n, p in model.named_parameters() if p.requires_grad}
