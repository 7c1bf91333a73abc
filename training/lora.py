"""LoRA adapters applied from outside a model (ReSim Table S.1 trains LoRA in stages 2 and 3).

``apply_lora(model, targets, rank, alpha)`` replaces each ``nn.Linear`` whose name ends with one of
``targets`` by ``LoRALinear``: ``y = W x + b + (alpha / rank) * B(A(x))`` with ``B`` zero-initialised,
so the model's output is unchanged at the start. The base weight keeps its parameter name
(``...to_q.base.weight`` would break checkpoints, so the adapter stores the base layer's tensors
under the *same* names and adds ``lora_A`` / ``lora_B``): loading a stage-1 state dict into a LoRA
model needs only ``strict=False`` for the new ``lora_*`` keys.
"""
from __future__ import annotations

import math

import torch
from torch import nn


class LoRALinear(nn.Linear):
    """An ``nn.Linear`` (same parameter names) plus a low-rank update."""

    def __init__(self, base: nn.Linear, rank: int, alpha: float):
        super().__init__(base.in_features, base.out_features, bias=base.bias is not None,
                         device=base.weight.device, dtype=base.weight.dtype)
        self.weight = base.weight
        self.bias = base.bias
        self.rank, self.scale = rank, alpha / rank
        self.lora_A = nn.Parameter(torch.empty(rank, base.in_features, device=base.weight.device, dtype=base.weight.dtype))
        self.lora_B = nn.Parameter(torch.zeros(base.out_features, rank, device=base.weight.device, dtype=base.weight.dtype))
        if self.lora_A.device.type != "meta":
            nn.init.kaiming_uniform_(self.lora_A, a=math.sqrt(5))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = super().forward(x)
        return out + (x @ self.lora_A.t().to(x.dtype)) @ self.lora_B.t().to(x.dtype) * self.scale


def apply_lora(model: nn.Module, targets: tuple[str, ...], rank: int, alpha: float) -> int:
    """Wrap matching linears in place; return how many were wrapped (0 targets found is an error)."""
    if rank < 1:
        raise ValueError(f"LoRA rank must be >= 1, got {rank}")
    todo = [(n, m) for n, m in model.named_modules()
            if type(m) is nn.Linear and any(n == t or n.endswith("." + t) for t in targets)]
    if not todo:
        raise ValueError(f"LoRA targets {targets} match no nn.Linear in {type(model).__name__}")
    for name, lin in todo:
        parent_name, _, child = name.rpartition(".")
        parent = model.get_submodule(parent_name) if parent_name else model
        setattr(parent, child, LoRALinear(lin, rank, alpha))
    return len(todo)


def lora_parameters(model: nn.Module) -> list[nn.Parameter]:
    return [p for n, p in model.named_parameters() if n.rsplit(".", 1)[-1] in ("lora_A", "lora_B")]
