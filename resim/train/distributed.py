"""Process group set-up and parallel wrapping, applied from outside the model code.

* ``init_distributed()`` reads torchrun's environment (RANK, WORLD_SIZE, LOCAL_RANK) and starts
  NCCL on GPUs, gloo on CPUs. A plain ``python`` run is world size 1 with no process group.
* ``LossModule`` makes ``model.loss(batch)`` the *forward* of a module, so DDP's gradient
  hooks and FSDP2's all-gather hooks fire: calling ``ddp.module.loss`` directly would bypass them.
* ``wrap_model`` applies activation checkpointing (all blocks or every k-th), then optionally
  ``torch.compile`` per block, then DDP or FSDP2 (``fully_shard`` per block, then the root).

FSDP2 units: ``model.fsdp_units()`` if the model defines it (the world model returns its
transformer blocks), else every child of every ``nn.ModuleList``.
"""
from __future__ import annotations

import datetime
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn
from torch.distributed.algorithms._checkpoint.checkpoint_wrapper import (
    CheckpointImpl, apply_activation_checkpointing as _apply, checkpoint_wrapper)
from torch.nn.parallel import DistributedDataParallel as DDP

from resim.sample.compile import compile_modules


@dataclass(frozen=True)
class DistEnv:
    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def init_distributed(device: str | None = None, timeout_s: float = 600.0, force_group: bool = False) -> DistEnv:
    """Join torchrun's process group if there is one; pick the device (cuda:LOCAL_RANK or cpu).

    ``force_group``: start a one-process group even without torchrun (FSDP2 needs a mesh).
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device is None:
        device = f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if force_group and world == 1 and not dist.is_initialized():
        os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
        os.environ.setdefault("MASTER_PORT", str(29500 + os.getpid() % 1000))
        os.environ.setdefault("RANK", "0")
        os.environ.setdefault("WORLD_SIZE", "1")
    if (world > 1 or force_group) and not dist.is_initialized():
        backend = "nccl" if dev.type == "cuda" else "gloo"
        dist.init_process_group(backend=backend, timeout=datetime.timedelta(seconds=timeout_s),
                                device_id=dev if dev.type == "cuda" else None)
    return DistEnv(rank=rank, world_size=world, local_rank=local_rank, device=dev)


def barrier(env: DistEnv) -> None:
    if env.distributed and dist.is_initialized():
        dist.barrier()


def all_reduce_sum(x: torch.Tensor, env: DistEnv) -> torch.Tensor:
    if env.distributed and dist.is_initialized():
        dist.all_reduce(x, op=dist.ReduceOp.SUM)
    return x


def broadcast_object(obj, env: DistEnv):
    """Rank 0's ``obj`` on every rank (small picklable objects built by our own code only)."""
    if not (env.distributed and dist.is_initialized()):
        return obj
    box = [obj if env.is_main else None]
    dist.broadcast_object_list(box, src=0)
    return box[0]


class LossModule(nn.Module):
    """``forward(batch) = model.loss(batch)``: the module DDP/FSDP/compile wrap."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, batch):
        return self.model.loss(batch)


def block_modules(model: nn.Module) -> list[nn.Module]:
    """The repeated blocks: ``model.fsdp_units()`` if defined, else children of every ModuleList."""
    if hasattr(model, "fsdp_units"):
        return list(model.fsdp_units())
    out: list[nn.Module] = []
    for m in model.modules():
        if isinstance(m, nn.ModuleList):
            out.extend(m.children())
    return out


def apply_activation_checkpointing(model: nn.Module, every_blocks: int = 1) -> str:
    """Recompute block activations in backward: all blocks, or only every k-th (``every_blocks`` = k, blocks
    i % k == 0: torchtitan's selective layer AC, memory traded for less recompute). Uses
    ``model.set_activation_checkpointing(True, every_blocks)`` if the model has it, else wraps the chosen blocks
    with torch's non-reentrant checkpoint wrapper."""
    if hasattr(model, "set_activation_checkpointing"):
        model.set_activation_checkpointing(True, every_blocks=every_blocks)
        return "model hook" + (f", every {every_blocks} blocks" if every_blocks > 1 else "")
    units = block_modules(model)
    if not units:
        raise ValueError(f"activation checkpointing: {type(model).__name__} has no ModuleList blocks "
                         "and no set_activation_checkpointing(); nothing to checkpoint")
    blocks = set(id(b) for i, b in enumerate(units) if i % every_blocks == 0)
    _apply(model, checkpoint_wrapper_fn=lambda m: checkpoint_wrapper(m, checkpoint_impl=CheckpointImpl.NO_REENTRANT),
           check_fn=lambda m: id(m) in blocks)
    return f"checkpoint_wrapper on {len(blocks)} of {len(units)} blocks"


def compile_model(model: nn.Module, lm: nn.Module) -> str:
    """``torch.compile`` each block (``resim.sample.compile.compile_modules``: the block's ``forward``, so
    FSDP2's hooks around it stay eager, as in torchtitan's ``apply_compile``). The loss's noise draws and
    condition dropout stay eager too, where they use torch's RNG exactly as without compile (a compiled RNG call
    draws other numbers), so a compiled step gives the eager step's loss. A model without blocks compiles its
    whole loss module."""
    units = block_modules(model)
    if not units:
        lm.compile()
        return "torch.compile (whole loss module)"
    compile_modules(units)
    return f"torch.compile on {len(units)} blocks"


def resolve_parallel(mode: str, env: DistEnv) -> str:
    if mode == "auto":
        return "ddp" if env.distributed else "none"
    if mode == "ddp" and not env.distributed:
        return "none"  # DDP over one process is a no-op; FSDP over one is not (bf16 params, sharding code path)
    return mode


def wrap_model(model: nn.Module, env: DistEnv, *, parallel: str = "auto", activation_checkpointing: bool = False,
               compile: bool = False, bf16_params: bool = False, reshard_after_forward: bool = True,
               checkpoint_every_blocks: int = 1) -> tuple[nn.Module, str]:
    """Return (loss module to call with a batch, description of the layout).

    Order matters (torchtitan's): activation checkpointing wraps blocks first, compile compiles each
    (wrapped) block, FSDP2 shards the blocks then the root.
    """
    notes = []
    if activation_checkpointing:
        notes.append("activation checkpointing: " + apply_activation_checkpointing(model, checkpoint_every_blocks))
    model.to(env.device)
    lm: nn.Module = LossModule(model)
    if compile:
        notes.append(compile_model(model, lm))
    mode = resolve_parallel(parallel, env)
    if mode == "ddp":
        lm = DDP(lm, device_ids=[env.device.index] if env.device.type == "cuda" else None,
                 find_unused_parameters=bool(getattr(model, "ddp_find_unused_parameters", False)))
        notes.append(f"DDP over {env.world_size} ranks")
    elif mode == "fsdp":
        # FSDP2 is in torch.distributed.fsdp from torch 2.6 on: imported only to shard, so an older torch
        # still trains on one device or with DDP
        from torch.distributed.fsdp import MixedPrecisionPolicy, fully_shard
        mp = MixedPrecisionPolicy(param_dtype=torch.bfloat16 if bf16_params else None, reduce_dtype=torch.float32)
        units = block_modules(model)
        for b in units:
            fully_shard(b, mp_policy=mp, reshard_after_forward=reshard_after_forward)
        fully_shard(lm, mp_policy=mp, reshard_after_forward=reshard_after_forward)
        notes.append(f"FSDP2 fully_shard on {len(units)} blocks + root over {env.world_size} ranks"
                     f" (params {'bf16' if bf16_params else 'fp32'}, reduce fp32)")
    else:
        notes.append("single process" if not env.distributed else "no wrapping")
    return lm, "; ".join(notes)
