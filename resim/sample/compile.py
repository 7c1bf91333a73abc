"""``torch.compile`` of a model's blocks, applied from outside the model: for sampling (``runtime.compile``) and,
through
``compile_modules``, for training (``trainer.compile``).

Why per block (torchtitan's ``apply_compile``) rather than the whole forward: the blocks are where the time goes
(attention, the MLP and the AdaLN/gating elementwise work that the GPU profile found around them), they are
identical, so dynamo traces one and reuses the code for all of them, and the model's own Python (patch and
position embeddings, the block-causal mask, the KV cache bookkeeping, the rollout's DDIM and guidance loop) stays
eager, where graph breaks and shape changes would otherwise cost recompiles.

Shapes. A ReSim-preset rollout feeds every DDIM step the same shapes (a 10-frame chunk over a 3-frame history
cache), so its blocks compile once, static, and every later step and round reuses that code. Frame-by-frame
rollouts (Vid2World) grow the cache by one frame per chunk: torch's default ``dynamic=None`` compiles the first
shape static and, at the first change, once more with symbolic lengths, instead of once per length (dynamo's
recompile limit would otherwise send the later lengths back to eager). The compiled code lives on the module, so
it is reused by every rollout of the process (``resim eval`` rolls out hundreds).

``mode="reduce-overhead"`` adds CUDA graphs (recorded per static shape); it is offered, not the default, until it
is measured on a GPU (docs/benchmarks.md lists the command).

Where: ``resim sample``/``plan``/``simulate``/``eval`` take ``--set runtime.compile=auto|on|off`` (and
``runtime.compile_mode``; resim.sample.settings); ``auto`` (the default)
compiles on CUDA only. On the 2-core CPU the compile costs 13-20 s per process for 1.19-1.22x on a ReSim-chunk
rollout of the shipped synthetic-world model and 1.01-1.06x frame by frame (bench/compile_rollout.py,
docs/benchmarks.md), and it needs a C++ compiler and the Python headers.
"""
from __future__ import annotations

import time
from typing import Any

# no torch import here: the CLIs' settings (resim.sample.settings) import the choices below, and --help stays fast;
# the functions get torch modules and devices from their callers
COMPILE_CHOICES = ("auto", "on", "off")
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune")
_MARK = "_resim_compiled"


def wants_compile(flag: str, device: Any) -> bool:
    """``runtime.compile`` → whether to compile: ``auto`` = on CUDA only."""
    if flag not in COMPILE_CHOICES:
        raise ValueError(f"compile={flag!r}: expected one of {', '.join(COMPILE_CHOICES)}")
    if flag == "auto":
        return str(device).startswith("cuda")   # "cuda", "cuda:1" or a torch.device of either
    return flag == "on"


def compile_modules(modules: Any, *, mode: str = "default", dynamic: bool | None = None) -> int:
    """Compile each module's ``forward`` in place, the one way resim compiles blocks (here for sampling, and
    ``resim.train.distributed.compile_model`` for training). Only ``forward``: hooks registered on the module (FSDP2's
    all-gathers) stay eager around it, as in torchtitan, which compiles the block that ``fully_shard`` then wraps;
    parameter names and state dicts are unchanged, so checkpoints and EMA weights load as before. Identical blocks
    share one graph. Idempotent: modules compiled earlier are left as they are. Returns the number compiled by
    this call; compilation itself happens at each module's first call."""
    import torch   # here, not at the top: this module stays torch-free for the CLIs' --help (see the imports)

    if mode not in COMPILE_MODES:
        raise ValueError(f"compile mode {mode!r}: expected one of {', '.join(COMPILE_MODES)}")
    n = 0
    for m in modules:
        if getattr(m, _MARK, False):
            continue
        m.forward = torch.compile(m.forward, mode=None if mode == "default" else mode, dynamic=dynamic)
        setattr(m, _MARK, True)
        n += 1
    return n


def compile_blocks(model: Any, *, mode: str = "default", dynamic: bool | None = None) -> int:
    """:func:`compile_modules` on ``model.transformer_blocks`` (a world model's)."""
    blocks = getattr(model, "transformer_blocks", None)
    if blocks is None or len(blocks) == 0:
        raise TypeError(f"{type(model).__name__} has no transformer_blocks to compile")
    return compile_modules(blocks, mode=mode, dynamic=dynamic)


def is_compiled(model: Any) -> bool:
    blocks = getattr(model, "transformer_blocks", None) or []
    return len(blocks) > 0 and all(getattr(b, _MARK, False) for b in blocks)


def maybe_compile(model: Any, flag: str, device: Any, *, mode: str = "default",
                  log: Any = None) -> dict:
    """Apply ``runtime.compile`` to a loaded world model; returns what to record in an output's protocol."""
    on = wants_compile(flag, device)
    info = {"compile": on, "compile_flag": flag}
    if on:
        t0 = time.perf_counter()
        compile_blocks(model, mode=mode)
        info["compile_mode"] = mode
        if log is not None:
            log(f"torch.compile: {len(model.transformer_blocks)} blocks, mode {mode} (compiled at the first "
                f"step, {time.perf_counter() - t0:.1f} s set-up)")
    return info
