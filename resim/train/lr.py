"""Learning-rate schedule: linear warmup, then constant or cosine decay. A pure function of the step.

Because the rate is recomputed from the step alone, the scheduler's whole state is the
step counter, which the checkpoint holds (no LambdaLR pickles to restore).
"""
from __future__ import annotations

import math


def lr_at(step: int, *, base_lr: float, warmup_steps: int, total_steps: int,
          schedule: str = "constant", min_lr_ratio: float = 0.0) -> float:
    """Learning rate for optimizer step ``step`` (0-based: the step about to be taken).

    Warmup: ``base_lr * (step + 1) / warmup_steps`` for ``step < warmup_steps`` (so the first
    step is not wasted at lr 0). After it, ``constant`` keeps ``base_lr``; ``cosine`` goes
    from ``base_lr`` to ``base_lr * min_lr_ratio`` at ``step == total_steps - 1``.
    """
    if step < 0:
        raise ValueError(f"step must be >= 0, got {step}")
    if warmup_steps > 0 and step < warmup_steps:
        return base_lr * (step + 1) / warmup_steps
    if schedule == "constant":
        return base_lr
    if schedule == "cosine":
        span = max(1, total_steps - 1 - warmup_steps)
        progress = min(1.0, (step - warmup_steps) / span)
        floor = base_lr * min_lr_ratio
        return floor + (base_lr - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))
    raise ValueError(f"unknown schedule {schedule!r} (constant | cosine)")
