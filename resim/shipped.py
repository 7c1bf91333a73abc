"""The model folders shipped in ``configs/models/``: where they are, and names that stand for them.

Shipped folders load with the libraries' own ``from_pretrained`` like any downloaded model folder:
``synth-vae``, ``synth-world``, ``synth-policy`` and ``synth-idm`` are trained on the synthetic world (model
cards in docs/models/);
``placeholder-*`` hold only configs (random, deterministic weights, flagged as placeholders).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

REPO_ROOT = Path(__file__).resolve().parents[1]

SYNTH_VAE = "synth-vae"
SYNTH_WORLD = "synth-world"
SYNTH_POLICY = "synth-policy"    # the pixel driving policy of the closed loop (docs/closed_loop.md)
SYNTH_IDM = "synth-idm"          # the inverse dynamics model that reads a driven path off video
PLACEHOLDER_VAE = "placeholder-cogvideox-vae-tiny"
PLACEHOLDER_T5 = "placeholder-t5-tiny"


def configs_dir(*parts: str) -> Path:
    """``configs/<parts>`` of this checkout, else of the working dir (Ray jobs ship it there); where neither has
    it, this checkout's path, for the caller to report missing."""
    for base in (REPO_ROOT, Path.cwd()):
        p = base.joinpath("configs", *parts)
        if p.is_dir():
            return p
    return REPO_ROOT.joinpath("configs", *parts)


def shipped_dir(name: str) -> Path:
    """``configs/models/<name>``: a shipped model folder."""
    return configs_dir("models", name)


def shipped_model(p: Optional[str | Path]) -> Optional[Path]:
    """A bare folder name of ``configs/models`` (``synth-vae``, ``placeholder-t5-tiny``) that is not a folder of
    the working directory → that shipped folder, so a config can name it from anywhere; anything else as given."""
    if p is None:
        return None
    if len(Path(p).parts) != 1 or Path(p).exists():
        return Path(p)
    shipped = shipped_dir(str(p))
    return shipped if shipped.is_dir() else Path(p)
