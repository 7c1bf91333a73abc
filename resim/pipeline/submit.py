"""Submit the pipeline to a running Ray cluster through the Ray Jobs API (``resim pipeline submit``).

What travels with the job (its runtime env):

* ``working_dir``: a small folder made here holding ``job_config.yaml`` (the resolved, validated config,
  with relative paths made absolute), the placeholder model configs (``configs/models/placeholder-*``) and the
  shipped models the config names (``encode.vae: synth-vae``),
  so the job runs exactly what was checked on the submitting machine;
* ``py_modules``: the ``resim`` package from this checkout or
  install — the cluster needs only the third-party dependencies (``pip install 'resim[pipeline]'``).

The job's entrypoint is ``python -m resim pipeline run job_config.yaml --no-progress``; inside a job
``ray.init()`` joins the cluster (``RAY_ADDRESS`` is set by the job supervisor).
"""
from __future__ import annotations

import asyncio
import importlib
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from resim.config import save
from resim.pipeline.config import PLACEHOLDER_T5, PLACEHOLDER_VAE, PipelineConfig, absolute_paths
from resim.shipped import shipped_dir, shipped_model

PACKAGES = ("resim",)
# No RAY_AUTH_* here: the job's processes take the cluster's own mode and token, and env_vars are shown by
# `ray job list`, so a token must never travel in them.
JOB_ENV = {"RAY_USAGE_STATS_ENABLED": "0", "HF_HUB_OFFLINE": "1",
           "TRANSFORMERS_OFFLINE": "1", "HF_HUB_DISABLE_PROGRESS_BARS": "1", "TOKENIZERS_PARALLELISM": "false"}
TERMINAL = ("SUCCEEDED", "FAILED", "STOPPED")


def absolutize(cfg: PipelineConfig) -> PipelineConfig:
    """Relative paths are relative to where the user typed the command, not to the job's working dir.

    The same :func:`resim.pipeline.config.absolute_paths` as a local run (no symlink followed), so a submitted job
    and a local run of one config have one data hash and may resume each other's OUT."""
    cfg = absolute_paths(cfg)
    return replace(cfg, ray=replace(cfg.ray, address=None, executor="ray"))


def package_dirs() -> list[str]:
    return [str(Path(importlib.import_module(p).__file__).resolve().parent) for p in PACKAGES]


def build_working_dir(cfg: PipelineConfig, dest: Path) -> Path:
    dest.mkdir(parents=True, exist_ok=True)
    save(absolutize(cfg), dest / "job_config.yaml")
    # the placeholders, and any shipped model the config names by its bare name (e.g. ``vae: synth-vae``)
    named = [shipped_dir(str(p)) for p in (cfg.encode.vae, cfg.encode.text_encoder)
             if p is not None and shipped_model(p) != Path(p)]
    for src in (PLACEHOLDER_VAE, PLACEHOLDER_T5, *named):
        shutil.copytree(src, dest / "configs" / "models" / src.name, dirs_exist_ok=True)
    return dest


def client(address: str):
    """The Ray Jobs client of ``address``; it sends the token Ray's own CLI would (``RAY_AUTH_MODE=token`` and
    ``RAY_AUTH_TOKEN`` / ``RAY_AUTH_TOKEN_PATH`` / ``~/.ray/auth_token``). A refused token is a one-line
    ``RuntimeError`` (the CLI's job errors), not Ray's multi-line ``AuthenticationError``."""
    from ray.exceptions import AuthenticationError
    from ray.job_submission import JobSubmissionClient   # ray takes seconds to import: only for a submission

    try:
        return JobSubmissionClient(address)
    except AuthenticationError as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else "refused"
        raise RuntimeError(f"{first}; the cluster uses token authentication: set RAY_AUTH_MODE=token and its token "
                           f"in RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH, as for Ray's own CLI (docs/security.md)") from None


def submit(cfg: PipelineConfig, address: str, job_id: str | None = None, agent_wait_s: float = 60.0) -> str:
    """Submit ``cfg`` as a Ray job; returns the job id (waits up to ``agent_wait_s`` for a fresh head's agent)."""
    with tempfile.TemporaryDirectory(prefix="resim-job-") as tmp:
        wd = build_working_dir(cfg, Path(tmp) / "job")
        runtime_env = {"working_dir": str(wd), "py_modules": package_dirs(),
                       "excludes": ["__pycache__", "*.pyc"], "env_vars": dict(JOB_ENV)}
        c = client(address)
        deadline = time.monotonic() + agent_wait_s
        while True:
            try:
                return c.submit_job(
                    entrypoint="python -m resim pipeline run job_config.yaml --no-progress",
                    runtime_env=runtime_env, submission_id=job_id,
                    metadata={"resim": "pipeline", "out": str(absolute_paths(cfg).out)})
            except RuntimeError as e:   # a head that just started has its dashboard up before its job agent
                if "No available agent" not in str(e) or time.monotonic() > deadline:
                    raise
                time.sleep(1.0)


def status(address: str, job_id: str) -> str:
    return str(client(address).get_job_status(job_id).value)


def logs(address: str, job_id: str) -> str:
    return client(address).get_job_logs(job_id)


def follow_logs(address: str, job_id: str) -> None:
    """Print the job's log lines as they arrive, until the job ends."""
    c = client(address)

    async def _tail():
        async for chunk in c.tail_job_logs(job_id):
            print(chunk, end="", flush=True)

    asyncio.run(_tail())


def wait(address: str, job_id: str, timeout_s: float | None = None, poll_s: float = 1.0) -> str:
    c = client(address)
    t0 = time.monotonic()
    while True:
        st = str(c.get_job_status(job_id).value)
        if st in TERMINAL or (timeout_s is not None and time.monotonic() - t0 > timeout_s):
            return st
        time.sleep(poll_s)
