"""The one training loop: trains any ``nn.Module`` exposing ``loss(batch) -> (loss, logs)``.

``Trainer(model, cfg, run_dir).fit(data)`` does AdamW with warmup + constant/cosine LR, gradient
accumulation and clipping, bf16 autocast (fp32 where bf16 is unsupported), EMA, activation
checkpointing, optional ``torch.compile``, DDP/FSDP2 from outside the model, sharded atomic
checkpoints with exact resume, and rank-0 logging (metrics.jsonl, TensorBoard, tqdm, loss PNG).

``data`` is any iterable of batches (a ``Batch``, a dict of tensors, ...). If it has
``state_dict()`` / ``load_state_dict()`` (``resim.train.data.StreamLoader`` does) its position is
checkpointed; otherwise the trainer counts batches and, on resume, re-iterates and skips them.
When an iterator ends, a new epoch starts with ``iter(data)`` again.

Exact resume: every input of step k+1 is restored from the checkpoint
at step k: weights, optimizer moments, EMA, the step (the LR is a pure function of it), each
rank's python/numpy/torch RNG, and the data position. On a fixed dataset and world size, a run
killed and resumed logs bitwise-identical losses on CPU in float32 (tests/training/test_resume.py).
"""
from __future__ import annotations

import contextlib
import math
import os
import random
import signal
import time
import warnings
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np
import torch
from torch import nn
from torch.distributed.checkpoint.state_dict import (StateDictOptions, get_model_state_dict, get_state_dict,
                                                     set_state_dict)

from resim.config import save as save_config, to_dict
from resim.models.exported import write_export
from resim.train import checkpoint as ckpt
from resim.train.config import RunConfig
from resim.train.distributed import DistEnv, all_reduce_sum, barrier, init_distributed, resolve_parallel, wrap_model
from resim.train.ema import EMA
from resim.train.lr import lr_at
from resim.train.metrics import MetricsLogger, truncate_after


class _Console:
    def __init__(self, enabled: bool):
        self.enabled = enabled

    def message(self, text: str) -> None:
        if self.enabled:
            print(text, flush=True)

    def close(self, loss_curve: bool = True) -> None:
        return None


class NonFiniteLossError(RuntimeError):
    """The loss or gradient norm became NaN/inf; the message names the last good checkpoint."""


class _CountingData:
    """Position tracking for plain iterables: (epoch, batches consumed in the epoch); resume re-iterates and skips.

    Iterating the data may draw from the *global* RNGs: a torch DataLoader draws its workers' base seed and its
    RandomSampler's seed from torch's global generator when its iterator is made / first advanced, and an
    in-process dataset or collate_fn may call random/numpy. Those draws run on an RNG stream of the data's own,
    swapped in around every ``iter``/``next`` of the underlying iterator (not around the trainer's code between
    batches), so (1) the model's noise (the global stream, checkpointed per rank) is the same whether or not the
    data was re-iterated and batches replayed on resume, and (2) the data stream's state at the start of the
    epoch is checkpointed, so the replay draws the same seeds (same shuffle order) as the uninterrupted run.
    Before this, a resumed shuffled DataLoader saw another order and shifted the model's noise (review 2026-12).
    """

    def __init__(self, data: Iterable, seed: int):
        self.data = data
        self.epoch = 0
        self.index = 0
        self._skip = 0
        self._rng = ckpt.seeded_cpu_rng(seed)   # the data stream's current state
        self._epoch_rng = self._rng              # its state when this epoch's iterator was made

    @contextlib.contextmanager
    def _data_rng(self):
        outer = ckpt.get_cpu_rng()
        ckpt.set_cpu_rng(self._rng)
        try:
            yield
        finally:
            self._rng = ckpt.get_cpu_rng()
            ckpt.set_cpu_rng(outer)

    def __iter__(self) -> Iterator:
        skip, self._skip = self._skip, 0
        self._epoch_rng = self._rng   # on resume: the checkpointed epoch-start state (load_state_dict)
        with self._data_rng():
            it = iter(self.data)
            for _ in range(skip):  # resume: replay the consumed part of the epoch
                next(it)
        self.index = skip
        while True:
            with self._data_rng():
                try:
                    b = next(it)
                except StopIteration:
                    break
            self.index += 1
            yield b
        self.epoch += 1
        self.index = 0

    def state_dict(self) -> dict:
        return {"epoch": self.epoch, "index": self.index, "epoch_rng": ckpt.cpu_rng_to_json(self._epoch_rng)}

    def load_state_dict(self, d: dict) -> None:
        self.epoch, self._skip = int(d["epoch"]), int(d["index"])
        if "epoch_rng" in d:
            self._rng = self._epoch_rng = ckpt.cpu_rng_from_json(d["epoch_rng"])
        else:
            warnings.warn("checkpoint from before the data RNG stream was saved: a shuffled loader may replay "
                          "its epoch in another order on this resume")


# the data stream of a plain iterable starts from (trainer seed per rank) + this, distinct from the model's
# stream (seed_all(seed)) so the shuffle seeds and the model's noise are not the same numbers
_DATA_RNG_SEED_OFFSET = 0x5EED_DA7A


def adamw_kernel(implementation: str, device: torch.device) -> dict:
    """``optim.implementation`` → AdamW's keyword: ``auto`` = fused on CUDA (one kernel over all parameters:
    torchtitan's default; the GPU profile found the optimizer's many small kernels among the non-matmul time),
    the per-parameter loop elsewhere."""
    if implementation == "auto":
        implementation = "fused" if device.type == "cuda" else "for-loop"
    return {"fused": {"fused": True}, "foreach": {"foreach": True},
            "for-loop": {"foreach": False, "fused": False}}[implementation]


def seed_all(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def to_device(batch: Any, device: torch.device) -> Any:
    if hasattr(batch, "to") and not isinstance(batch, torch.Tensor):
        return batch.to(device)
    if isinstance(batch, torch.Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, dict):
        return {k: to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)):
        return type(batch)(to_device(v, device) for v in batch)
    return batch


def batch_size_of(batch: Any) -> int:
    if hasattr(batch, "__len__") and not isinstance(batch, (dict, list, tuple, torch.Tensor)):
        return len(batch)
    if isinstance(batch, torch.Tensor):
        return batch.shape[0]
    if isinstance(batch, dict):
        for v in batch.values():
            if isinstance(v, torch.Tensor) and v.ndim:
                return v.shape[0]
    if isinstance(batch, (list, tuple)) and batch:
        return batch_size_of(batch[0])
    return 1


def _scalar(v: Any) -> float | None:
    if isinstance(v, torch.Tensor):
        if v.numel() != 1:
            return None
        v = v.detach()
        if hasattr(v, "full_tensor"):
            v = v.full_tensor()
        return float(v.float().cpu())
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return float(v)
    return None


def _clean_name(name: str) -> str:
    """Parameter name without wrapper tokens (DDP, activation checkpointing, compile)."""
    if name.startswith("module."):
        name = name[len("module."):]
    for token in ("_checkpoint_wrapped_module.", "_orig_mod.", "_fsdp_wrapped_module."):
        name = name.replace(token, "")
    return name


class Trainer:
    """Train ``model`` (anything with ``loss(batch) -> (loss, logs)``) under ``cfg`` into ``run_dir``."""

    def __init__(self, model: nn.Module, cfg: RunConfig, run_dir: str | Path, *, resume: bool = False,
                 env: DistEnv | None = None):
        if not hasattr(model, "loss"):
            raise TypeError(f"{type(model).__name__} has no loss(batch) -> (loss, logs) method")
        self.cfg = cfg
        self.tc = cfg.trainer
        self.run_dir = Path(run_dir)
        self.resume = resume
        mode = self.tc.parallel
        self.env = env or init_distributed(force_group=(mode == "fsdp"))
        self.parallel = resolve_parallel(mode, self.env)
        self.model = model
        self.accum = self._grad_accum_steps()
        self.precision = self._resolve_precision()

    # ------------------------------------------------------------------ set-up
    def _grad_accum_steps(self) -> int:
        gbs = self.tc.global_batch_size
        if gbs is None:
            return self.tc.grad_accum_steps
        per_step = self.cfg.data.batch_size_per_gpu * self.env.world_size
        if gbs % per_step:
            raise ValueError(f"trainer.global_batch_size={gbs} is not a multiple of batch_size_per_gpu "
                             f"({self.cfg.data.batch_size_per_gpu}) x world size ({self.env.world_size}) = {per_step}")
        return gbs // per_step

    def _resolve_precision(self) -> str:
        if self.tc.precision != "bf16":
            return "fp32"
        dev = self.env.device
        if dev.type == "cuda" and not torch.cuda.is_bf16_supported():
            warnings.warn(f"bf16 is not supported on {torch.cuda.get_device_name(dev)}; training in fp32")
            return "fp32"
        return "bf16"

    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast(device_type=self.env.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def global_batch_size(self) -> int:
        return self.cfg.data.batch_size_per_gpu * self.env.world_size * self.accum

    # ------------------------------------------------------------------ state
    def _state(self) -> dict:
        msd, osd = get_state_dict(self.lm, self.optimizer)
        return {"model": msd, "optim": osd, "ema": self.ema.state_dict() if self.ema else {}}

    def _save(self, step: int, data) -> Path:
        rank_state = {"rng": ckpt.rng_state(), "data": data.state_dict(), "rank": self.env.rank}
        meta = {"world_size": self.env.world_size, "scheduler": {"step": step}, "precision": self.precision,
                "grad_accum_steps": self.accum, "config": to_dict(self.cfg), "last_loss": self._last_loss}
        path = ckpt.save(self.run_dir, step, self._state(), rank_state=rank_state, meta=meta,
                         rank=self.env.rank, barrier=lambda: barrier(self.env), keep=self.tc.keep_checkpoints)
        self._last_good = path
        return path

    def _load(self, path: Path, data) -> int:
        state = self._state()
        meta, rank_state = ckpt.load(path, state, rank=self.env.rank,
                                     legacy_name=getattr(self.model, "legacy_param_name", None))
        set_state_dict(self.lm, self.optimizer, model_state_dict=state["model"], optim_state_dict=state["optim"])
        if self.ema:
            self.ema.load_state_dict(state["ema"])
        if meta["world_size"] == self.env.world_size and rank_state is not None:
            ckpt.set_rng_state(rank_state["rng"])
            data.load_state_dict(rank_state["data"])
        else:
            self.log.message(f"[resim] resharded resume: checkpoint written by {meta['world_size']} ranks, this run "
                             f"has {self.env.world_size}; weights/optimizer/EMA restored, data order and RNG restart")
        self._last_good = path
        return int(meta["step"])

    # ------------------------------------------------------------------ loop
    def fit(self, data: Iterable) -> dict:
        tc, env = self.tc, self.env
        if not (hasattr(data, "state_dict") and hasattr(data, "load_state_dict")):
            data = _CountingData(data, seed=tc.seed + 1_000_003 * env.rank + _DATA_RNG_SEED_OFFSET)
        seed_all(tc.seed + 1_000_003 * env.rank)  # different noise per rank, reproducible per rank
        self.lm, layout = wrap_model(
            self.model, env, parallel=self.parallel, activation_checkpointing=tc.activation_checkpointing,
            compile=tc.compile, bf16_params=(self.precision == "bf16"),
            reshard_after_forward=tc.fsdp_reshard_after_forward,
            checkpoint_every_blocks=tc.activation_checkpointing_every_blocks)
        params = [p for p in self.lm.parameters() if p.requires_grad]
        if not params:
            raise ValueError(f"{type(self.model).__name__} has no trainable parameters")
        oc = self.cfg.optim
        self.optimizer = torch.optim.AdamW(params, lr=oc.lr, betas=oc.betas, eps=oc.eps, weight_decay=oc.weight_decay,
                                           **adamw_kernel(oc.implementation, env.device))
        self.ema = None
        if tc.ema_decay > 0:
            self.ema = EMA(self.lm, tc.ema_decay, warmup=tc.ema_warmup)
            self.ema.params = {_clean_name(n): p for n, p in self.ema.params.items()}
            self.ema.shadow = {_clean_name(n): t for n, t in self.ema.shadow.items()}
        self._last_good: Path | None = None
        self._last_loss: float | None = None

        start = 0
        latest = ckpt.latest_complete(self.run_dir) if self.resume else None
        if env.is_main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        barrier(env)
        self.log = _Console(env.is_main)  # messages while loading; the metrics logger opens after truncation
        if latest is not None:
            start = self._load(latest, data)
        elif self.resume and env.is_main:
            print(f"[resim] --resume: no complete checkpoint in {self.run_dir / ckpt.CHECKPOINTS}; starting fresh")
        if env.is_main:
            if start:
                truncate_after(self.run_dir, start)
            elif (self.run_dir / "metrics.jsonl").exists():
                (self.run_dir / "metrics.jsonl").unlink()  # a fresh run into an old folder
            save_config(self.cfg, self.run_dir / "config.yaml")
        self.log = MetricsLogger(self.run_dir, enabled=env.is_main, total_steps=tc.steps, start_step=start,
                                 tensorboard=tc.tensorboard, progress_bar=tc.progress_bar, log_every=tc.log_every_steps)
        n_train = sum(p.numel() for p in params)
        self.log.message(f"[resim] {type(self.model).__name__}: {n_train:,} trainable parameters; {layout}; "
                         f"precision {self.precision}; global batch {self.global_batch_size()} "
                         f"({self.cfg.data.batch_size_per_gpu}/gpu x {env.world_size} x accum {self.accum}); "
                         + (f"resumed at step {start} from {latest}" if start else "fresh start"))

        kill_at = os.environ.get("RESIM_FAULT_KILL_AT_STEP")
        it = iter(data)
        step = start
        saved_at = start if latest is not None else -1
        t_start = time.perf_counter()
        stopped_early = 0   # the step at which trainer.max_wall_s stopped the loop
        for step in range(start, tc.steps):
            t0 = time.perf_counter()
            lr = lr_at(step, base_lr=oc.lr, warmup_steps=oc.warmup_steps, total_steps=tc.steps,
                       schedule=oc.schedule, min_lr_ratio=oc.min_lr_ratio)
            for g in self.optimizer.param_groups:
                g["lr"] = lr
            loss_sum = torch.zeros((), dtype=torch.float64, device=env.device)
            logs_sum: dict[str, float] = {}
            logs_n: dict[str, int] = {}   # micro-batches that reported each key (some logs, e.g. loss_t_high, are
            n_samples = 0                 # only present when such a sample was drawn: average over those only)
            flops = 0.0
            tokens = 0
            for micro in range(self.accum):
                try:
                    batch = next(it)
                except StopIteration:
                    it = iter(data)
                    batch = next(it)
                batch = to_device(batch, env.device)
                bs = batch_size_of(batch)
                n_samples += bs
                if hasattr(self.model, "tokens_per_sample"):
                    tokens += int(self.model.tokens_per_sample(batch)) * bs
                if hasattr(self.model, "flops_per_sample"):
                    flops += float(self.model.flops_per_sample(batch)) * bs
                sync = micro == self.accum - 1 or not hasattr(self.lm, "no_sync")
                if hasattr(self.lm, "set_requires_gradient_sync"):  # FSDP2: reduce-scatter on the last micro only
                    self.lm.set_requires_gradient_sync(micro == self.accum - 1)
                with (contextlib.nullcontext() if sync else self.lm.no_sync()), self._autocast():
                    loss, logs = self.lm(batch)
                (loss.float() / self.accum).backward()
                loss_sum += loss.detach().to(torch.float64)
                for k, v in (logs or {}).items():
                    f = _scalar(v)
                    if f is not None:
                        logs_sum[k] = logs_sum.get(k, 0.0) + f
                        logs_n[k] = logs_n.get(k, 0) + 1
            max_norm = oc.grad_clip_norm if oc.grad_clip_norm > 0 else float("inf")
            grad_norm = torch.nn.utils.clip_grad_norm_(params, max_norm)
            if hasattr(grad_norm, "full_tensor"):
                grad_norm = grad_norm.full_tensor()
            # every rank agrees on (mean loss, finite?) so none steps while another stops
            stats = torch.stack([loss_sum / self.accum, grad_norm.detach().to(torch.float64).reshape(()),
                                 torch.tensor(float(n_samples), dtype=torch.float64, device=env.device)])
            finite = torch.isfinite(stats).all().to(torch.float64).reshape(1)
            # every rank also agrees on whether the wall-clock budget is spent, so all stop after the same step
            out_of_time = float(tc.max_wall_s is not None and time.perf_counter() - t_start >= tc.max_wall_s)
            red = all_reduce_sum(torch.cat([torch.nan_to_num(stats, nan=0.0, posinf=0.0, neginf=0.0), 1 - finite,
                                            torch.tensor([out_of_time], dtype=torch.float64, device=env.device)]), env)
            if red[3] > 0 or not bool(finite):
                self._nonfinite(step, float(stats[0]), float(stats[1]))
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)
            done = step + 1
            if self.ema:
                self.ema.update(done)
            mean_loss = float(red[0]) / env.world_size
            self._last_loss = mean_loss
            dt = time.perf_counter() - t0
            rec = {"step": done, "loss": mean_loss, "lr": lr, "grad_norm": float(grad_norm),
                   "samples_per_s": float(red[2]) / dt, "step_time_s": dt}
            if env.device.type == "cuda":
                if tokens:
                    rec["tokens_per_s"] = tokens * env.world_size / dt
                if flops:
                    rec["mfu"] = flops / dt / (tc.peak_tflops_per_gpu * 1e12)
                rec["max_mem_gib"] = torch.cuda.max_memory_allocated(env.device) / 2**30
            if hasattr(data, "skipped"):
                rec["data_skipped"] = int(data.skipped)
            rec.update({k: v / logs_n[k] for k, v in logs_sum.items() if k not in rec})
            self.log.log(rec)
            if tc.checkpoint_every_steps and done % tc.checkpoint_every_steps == 0 and done < tc.steps:
                self._save(done, data)
                saved_at = done
            if kill_at is not None and done == int(kill_at) and env.is_main:
                os.kill(os.getpid(), signal.SIGKILL)  # fault injection for tests: a real kill, no clean-up
            if red[4] > 0 and done < tc.steps:
                stopped_early = done
                self.log.message(f"[resim] trainer.max_wall_s={tc.max_wall_s:g} s spent: stopped at step {done} of "
                                 f"{tc.steps}; `--resume` continues from here")
                break
        final_step = stopped_early or (tc.steps if tc.steps > start else start)
        if saved_at != final_step:
            self._save(final_step, data)
        if tc.save_final_weights:
            self._export_final()
        png = self.log.close(loss_curve=tc.loss_curve_png)
        wall = time.perf_counter() - t_start
        summary = {"run_dir": str(self.run_dir), "start_step": start, "final_step": final_step,
                   "stopped_by_max_wall_s": bool(stopped_early),
                   "last_loss": self._last_loss, "checkpoint": str(self._last_good), "wall_s": wall,
                   "global_batch_size": self.global_batch_size(), "layout": layout, "loss_curve": str(png) if png else None}
        if hasattr(data, "skipped"):
            summary["data_skipped"] = int(data.skipped)
        return summary

    def _nonfinite(self, step: int, loss: float, grad_norm: float) -> None:
        last = self._last_good
        where = (f"the last good checkpoint is {last}" if last is not None
                 else "there is no checkpoint of this run yet")
        hint = (" CogVideoX-2B is known to overflow in bf16 for some users: resume in fp32 with "
                "`--resume --set trainer.precision=fp32`." if self.precision == "bf16"
                else " Lower optim.lr or raise optim.warmup_steps, then resume with `--resume`.")
        msg = (f"non-finite loss/gradient at step {step + 1} (loss={loss}, grad_norm={grad_norm}, "
               f"precision {self.precision}); stopped without taking the step; {where}.{hint}")
        self.log.message("[resim] " + msg)
        self.log.close(loss_curve=self.tc.loss_curve_png)
        raise NonFiniteLossError(msg)

    def _export_final(self) -> None:
        """RUN_DIR/final/model.safetensors (+ ema.safetensors): full weights for sampling, rank 0 writes.

        ``ema.safetensors`` is a complete state dict like ``model.safetensors``: the EMA only tracks the trainable
        parameters, so with a partly frozen model (``model.trainable=lora+new|dit|new``, ReSim stage 2) the frozen
        tensors and buffers come from the model and the EMA values are laid over the rest. Sampling
        (``resim.sample.load``) and ``model.init_weights`` load either file strictly."""
        opts = StateDictOptions(full_state_dict=True, cpu_offload=True)
        sd = get_model_state_dict(self.lm, options=opts)
        ema_full = {}
        if self.ema:
            for n, t in self.ema.shadow.items():  # full_tensor() is a collective: every rank gathers
                ema_full[n] = t.full_tensor() if hasattr(t, "full_tensor") else t
        if not self.env.is_main:
            return
        strip = lambda n: n[len("model."):] if n.startswith("model.") else n  # noqa: E731  (LossModule prefix)
        full = {strip(_clean_name(k)): v.detach().cpu().contiguous() for k, v in sd.items()}
        ema_sd = None
        if ema_full:
            ema_sd = dict(full)
            for n, t in ema_full.items():
                k = strip(n)
                if k not in full:  # our bug: EMA names and state-dict names must agree
                    raise RuntimeError(f"EMA tensor {n!r} has no counterpart in the model state dict "
                                       f"(e.g. {sorted(full)[:3]})")
                ema_sd[k] = t.detach().cpu().contiguous()   # float32, as the EMA keeps it
        write_export(self.run_dir / "final", full, self.cfg, ema=ema_sd)   # the one layout (resim.models.exported)
