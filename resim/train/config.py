"""Typed configs of a training run: optimiser, trainer loop, data stream, the whole run.

A run config is ``RunConfig``: which registered model (``model_name``) with its own
config as a plain mapping (``model``, validated by the model's builder), plus the
data stream, the optimiser and the loop. Presets (``configs/train/<model>/<preset>.yaml``, loaded by ``resim/train/presets.py``) are
plain dicts of this shape; ``--set key=value`` overrides any leaf.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional

from resim.config import ConfigError, check_positive


@dataclass
class OptimConfig:
    """AdamW with linear warmup then a constant or cosine schedule (per optimizer step)."""

    lr: float = 1e-4
    weight_decay: float = 0.0
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    warmup_steps: int = 0
    schedule: Literal["constant", "cosine"] = "constant"
    min_lr_ratio: float = 0.0          # cosine decays to lr * min_lr_ratio at the last step
    grad_clip_norm: float = 1.0        # <= 0 disables clipping (the norm is still logged)
    # AdamW's kernel: auto = fused on CUDA (one kernel for all parameters, as torchtitan), the plain per-parameter
    # loop elsewhere (what every CPU run so far used, so their resumes stay bit-exact)
    implementation: Literal["auto", "for-loop", "foreach", "fused"] = "auto"

    def __post_init__(self):
        # finite: nan passes `<= 0` tests and would train to nan weights without a word
        check_positive("optim.lr", self.lr)
        check_positive("optim.weight_decay", self.weight_decay, allow_zero=True)
        if self.warmup_steps < 0:
            raise ConfigError(f"optim.warmup_steps must be >= 0, got {self.warmup_steps}")
        if not 0.0 <= self.min_lr_ratio <= 1.0:
            raise ConfigError(f"optim.min_lr_ratio must be in [0, 1], got {self.min_lr_ratio}")
        if not math.isfinite(self.grad_clip_norm):   # nan would quietly mean "no clipping"
            raise ConfigError(f"optim.grad_clip_norm must be a finite number (<= 0: no clipping), got "
                              f"{self.grad_clip_norm}")

    def for_steps(self, steps: int) -> "OptimConfig":
        """This optimiser for a run of ``steps`` steps: the warmup ends before the last step."""
        return dataclasses.replace(self, warmup_steps=min(self.warmup_steps, max(steps - 1, 0)))


@dataclass
class SmallTrainConfig:
    """How a small model is fitted in one process, over epochs of clips held in memory (``resim.train.smallfit``):
    Video2Reward, the inverse dynamics model and the driving policy. Each task's config extends it with its model,
    split and augmentation; the optimiser is the big trainer's :class:`OptimConfig` (``optim.lr``, ...)."""

    epochs: int = 30
    batch_size_per_gpu: int = 16
    seed: int = 0
    optim: OptimConfig = field(default_factory=OptimConfig)

    def __post_init__(self):
        if self.epochs < 1 or self.batch_size_per_gpu < 1:
            raise ConfigError(f"epochs and batch_size_per_gpu must be >= 1, got {self.epochs} and "
                              f"{self.batch_size_per_gpu}")
        if self.seed < 0:  # numpy's epoch RNG (seed * 1000 + epoch) refuses negative seeds
            raise ConfigError(f"seed must be >= 0, got {self.seed}")


@dataclass
class TrainerConfig:
    """The generic loop (``resim.train.trainer.Trainer``)."""

    steps: int = 100                       # optimizer steps in total (a resumed run continues to this)
    grad_accum_steps: int = 1              # micro-batches per optimizer step (ignored if global_batch_size set)
    global_batch_size: Optional[int] = None  # if set: accum = global / (batch_size_per_gpu * world); must divide
    precision: Literal["fp32", "bf16"] = "fp32"  # bf16 = autocast; falls back to fp32 where unsupported
    ema_decay: float = 0.0                 # 0 disables EMA; e.g. 0.9999
    # the decay of update n is min(ema_decay, (1 + n) / (10 + n)) (diffusers' EMAModel): the EMA follows the
    # weights early instead of keeping the initial ones for ~1 / (1 - ema_decay) steps (resim/train/ema.py)
    ema_warmup: bool = True
    activation_checkpointing: bool = False
    # selective activation checkpointing by block (torchtitan's "selective layer" AC): with the above on, only
    # every k-th block (index % k == 0) recomputes its activations; 1 = every block (full AC), 2 = half of them
    activation_checkpointing_every_blocks: int = 1
    compile: bool = False                  # torch.compile each block (the whole loss module for a model without blocks)
    parallel: Literal["auto", "none", "ddp", "fsdp"] = "auto"  # auto: DDP if world > 1 (FSDP for presets that say so)
    fsdp_reshard_after_forward: bool = True
    checkpoint_every_steps: int = 0        # 0: only at the end
    keep_checkpoints: int = 2              # complete checkpoints kept (older ones deleted)
    log_every_steps: int = 1               # metrics.jsonl gets every step; console/TensorBoard every N
    seed: int = 0
    tensorboard: bool = True
    progress_bar: bool = True
    loss_curve_png: bool = True
    peak_tflops_per_gpu: float = 989.0     # dense bf16 peak for MFU (H100 SXM); set for your GPU
    save_final_weights: bool = True        # final/model.safetensors (+ ema) consolidated on rank 0
    # a wall-clock budget for this invocation's steps (None: none). When it runs out the loop stops after the step
    # in flight, checkpoints and exports final/ as at the end; `--resume` later continues towards `steps`. For
    # leased GPUs and CI slots with a hard limit; use a constant (or warm-up only) schedule, since a cosine is
    # laid out over `steps` and would be cut off part-way
    max_wall_s: Optional[float] = None

    def __post_init__(self):
        if self.steps < 1:
            raise ConfigError(f"trainer.steps must be >= 1, got {self.steps}")
        if self.grad_accum_steps < 1:
            raise ConfigError(f"trainer.grad_accum_steps must be >= 1, got {self.grad_accum_steps}")
        if self.global_batch_size is not None and self.global_batch_size < 1:
            raise ConfigError(f"trainer.global_batch_size must be >= 1, got {self.global_batch_size}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ConfigError(f"trainer.ema_decay must be in [0, 1), got {self.ema_decay}")
        if self.checkpoint_every_steps < 0 or self.keep_checkpoints < 1:
            raise ConfigError("trainer.checkpoint_every_steps must be >= 0 and keep_checkpoints >= 1")
        if self.log_every_steps < 1:
            raise ConfigError("trainer.log_every_steps must be >= 1")
        if self.activation_checkpointing_every_blocks < 1:
            raise ConfigError("trainer.activation_checkpointing_every_blocks must be >= 1 (1: every block), got "
                              f"{self.activation_checkpointing_every_blocks}")
        if self.max_wall_s is not None and not self.max_wall_s >= 0:
            raise ConfigError(f"trainer.max_wall_s must be >= 0 seconds (or null), got {self.max_wall_s}")


@dataclass
class DataConfig:
    """The shard stream (``resim.train.data``). See docs/training.md for how ranks/workers split it."""

    shards: Optional[Path] = None          # dataset folder (with shards/, index/, manifest/, prompts/)
    urls: tuple[str, ...] = ()             # or explicit shard URLs (anything webdataset's gopen opens)
    # ``pipe:CMD`` URLs run CMD in a shell; since urls is reachable from ``--set`` and config files, they are
    # refused unless this is set (e.g. to stream with ``pipe:aws s3 cp ...``)
    allow_pipe_urls: bool = False
    batch_size_per_gpu: int = 1
    num_workers: int = 0                   # DataLoader workers per rank
    samples_per_epoch: Optional[int] = None  # global; None = number of samples in the dataset
    source_weights: dict[str, float] = field(default_factory=dict)  # e.g. {opendv: 1, navsim: 1}; {} = by count
    open_shards_per_worker: int = 4        # shards interleaved per worker (shuffling without a buffer)
    strict: bool = False                   # a corrupt sample / unreadable shard is an error instead of skipped
    max_consecutive_failures: int = 64     # unreadable draws in a row before giving up (every shard bad)
    max_shape_buckets: int = 16            # distinct sample geometries (latent shape, clip length, ...) per worker
    load_frames: bool = False              # decode frames.mp4 into Batch.frames (reward model)
    load_dino: bool = False                # Batch.dino from dino.npy (reward model)
    skip_duplicates: bool = True           # skip the clips OUT/dedup/duplicates.parquet lists (resim/pipeline/dedup.py)
    # which side of the dataset's train / held-out split (DIR/split.json, resim/shards/split.py) is streamed:
    # "train" leaves the held-out episodes to evaluation; "all" for a dataset held out whole elsewhere (a world
    # of another seed) or to reproduce a run made before the split
    split: Literal["train", "all"] = "train"
    # the shuffled-command control: each clip's command prompt replaced by the same prefix under a command drawn
    # from a hash of (seed, key), uniform over the commands the prompt table holds, fixed for the run and any
    # resume. A model trained so can learn no command; if the evaluation still reads one, it reads something else
    shuffle_commands: bool = False
    seed: int = 0
    prefetch_factor: int = 2

    def __post_init__(self):
        if self.batch_size_per_gpu < 1:
            raise ConfigError(f"data.batch_size_per_gpu must be >= 1, got {self.batch_size_per_gpu}")
        if self.num_workers < 0:
            raise ConfigError(f"data.num_workers must be >= 0, got {self.num_workers}")
        if self.samples_per_epoch is not None and self.samples_per_epoch < 1:
            raise ConfigError(f"data.samples_per_epoch must be >= 1, got {self.samples_per_epoch}")
        if self.open_shards_per_worker < 1:
            raise ConfigError("data.open_shards_per_worker must be >= 1")
        if self.max_shape_buckets < 1:
            raise ConfigError("data.max_shape_buckets must be >= 1")
        # any case and leading blanks: URL parsing (webdataset's gopen) lower-cases the scheme and strips blanks
        pipes = [u for u in self.urls if str(u).strip().lower().startswith("pipe:")]
        if pipes and not self.allow_pipe_urls:
            raise ConfigError(f"data.urls {pipes[0]!r} is a pipe: URL, a shell command; set data.allow_pipe_urls=true "
                              "to run it, or give shard paths / http(s) URLs")
        for k, v in self.source_weights.items():
            if v < 0:
                raise ConfigError(f"data.source_weights.{k} must be >= 0, got {v}")
        if self.source_weights and not any(v > 0 for v in self.source_weights.values()):
            raise ConfigError("data.source_weights: at least one weight must be > 0")


@dataclass
class RunConfig:
    """Everything a training run needs; saved resolved as RUN_DIR/config.yaml."""

    model_name: str = "world"              # a name in resim.models.registry
    model: dict[str, Any] = field(default_factory=dict)  # the model's own config (validated by its builder)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    preset: str = ""                       # which named preset this came from (informational)
    reference: dict[str, Any] = field(default_factory=dict)  # paper values the preset reproduces (informational)
