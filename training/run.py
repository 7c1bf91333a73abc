"""Build a run from a config and train it: what ``resim train NAME`` executes on every rank."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Iterable

from resim.config import ConfigError, load
from training.config import RunConfig


def resolve_config(model_name: str, preset: str, *, config_file: str | Path | None = None,
                   overrides: Iterable[str] = (), shards: str | Path | None = None, steps: int | None = None,
                   checkpoint_every: int | None = None) -> RunConfig:
    """Preset <- YAML file <- ``--set`` overrides <- the explicit flags (``--shards``, ``--steps``, ...)."""
    from training.presets import get_preset

    try:
        base = get_preset(model_name, preset)
    except KeyError as e:
        raise ConfigError(str(e.args[0])) from None
    extra = list(overrides)
    if shards is not None:
        extra.append(f"data.shards={shards}")
    if steps is not None:
        extra.append(f"trainer.steps={steps}")
    if checkpoint_every is not None:
        extra.append(f"trainer.checkpoint_every_steps={checkpoint_every}")
    cfg = load(RunConfig, config_file, overrides=extra, base=base)
    if cfg.model_name != model_name:
        raise ConfigError(f"model_name={cfg.model_name!r} but the command trains {model_name!r}")
    return cfg


def run_training(cfg: RunConfig, out: str | Path, *, resume: bool = False) -> dict:
    """Every rank: join the process group, build the model and the data stream, train, clean up."""
    import torch
    import torch.distributed as dist

    from training import registry
    from training.data import StreamLoader
    from training.distributed import init_distributed
    from training.trainer import Trainer

    env = init_distributed(force_group=cfg.trainer.parallel == "fsdp")
    try:
        torch.manual_seed(cfg.trainer.seed)  # identical initial weights on every rank (FSDP2 does not broadcast)
        model = registry.build(cfg.model_name, cfg.model, device="cpu")
        data = StreamLoader(cfg.data, rank=env.rank, world_size=env.world_size,
                            pin_memory=env.device.type == "cuda", verbose=env.is_main)
        summary = Trainer(model, cfg, out, resume=resume, env=env).fit(data)
        if env.is_main:
            print(f"[resim] done: steps {summary['start_step']} -> {summary['final_step']}, last loss "
                  f"{summary['last_loss']:.6g}, data skipped {summary.get('data_skipped', 0)}, "
                  f"{summary['wall_s']:.1f} s; checkpoint {summary['checkpoint']}; "
                  f"metrics {Path(out) / 'metrics.jsonl'}; curve {summary['loss_curve']}", file=sys.stderr)
        return summary
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
