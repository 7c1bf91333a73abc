"""Install trained synthetic-world models as the shipped folders ``configs/models/synth-vae`` and ``synth-world``.

    python -m lab.export_synth --vae RUN_VAE/final/vae --world RUN_WORLD --out configs/models
    python -m lab.export_synth --world lab/runs/synth-world --out DIR     # a milestone folder (lab/milestone.py)

* ``synth-vae/``: the VAE run's exported diffusers folder (``config.json`` + ``diffusion_pytorch_model.safetensors``),
  loaded by ``AutoencoderKLCogVideoX.from_pretrained`` / ``resim.media.encoders.VideoVAE`` as CogVideoX-2B's is.
* ``synth-world/``: ``config.yaml`` (the run's resolved config), ``model.safetensors`` (the run's EMA weights when
  it kept an EMA, else its final weights: one file, to keep the repository small) and ``data_encode.yaml`` (the
  training data's encode section, naming the VAE ``synth-vae`` and the text encoder by their shipped names), so
  ``resim sample|plan|eval --checkpoint synth-world`` decode with the right VAE. Loaded by
  ``resim.sample.load.load_world_model`` like any run folder.
"""
from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import yaml

from resim.shipped import PLACEHOLDER_T5, SYNTH_VAE, SYNTH_WORLD


def install_vae(vae_dir: Path, out: Path) -> Path:
    dst = out / SYNTH_VAE
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("config.json", "diffusion_pytorch_model.safetensors"):
        shutil.copyfile(vae_dir / name, dst / name)
    return dst


def install_world(run: Path, out: Path, vae_name: str = SYNTH_VAE) -> Path:
    """``run``: a run folder (``config.yaml``, ``final/``) or a milestone folder of lab/milestone.py (``config.yaml``,
    ``ema.safetensors``, ``data_encode.yaml`` side by side)."""
    final = run / "final" if (run / "final").is_dir() else run
    dst = out / SYNTH_WORLD
    dst.mkdir(parents=True, exist_ok=True)
    weights = final / "ema.safetensors" if (final / "ema.safetensors").is_file() else final / "model.safetensors"
    shutil.copyfile(weights, dst / "model.safetensors")
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    cfg.setdefault("reference", {})["weights"] = f"{weights.name} of the run (see docs/models/synth-world.md)"
    cfg["data"]["shards"] = None   # a path on the training machine; data_encode.yaml keeps what sampling needs
    if cfg["model"].get("init_weights"):   # the earlier stage's weights are in model.safetensors already
        cfg["reference"]["initialised_from"] = Path(cfg["model"]["init_weights"]).name + " of the earlier stage"
        cfg["model"]["init_weights"] = None
    (dst / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    data = yaml.safe_load((final / "data_encode.yaml").read_text())
    enc = data["encode"]
    enc.update({"vae": vae_name, "text_encoder": enc.get("text_encoder") or PLACEHOLDER_T5})
    clip = {"clip": data["clip"]} if data.get("clip") else {}
    (dst / "data_encode.yaml").write_text(yaml.safe_dump({"encode": enc, **clip}, sort_keys=False))
    return dst


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--vae", type=Path, help="a `resim train vae` run's final/vae folder")
    p.add_argument("--world", type=Path, help="a `resim train world` run folder, or a lab/milestone.py folder")
    p.add_argument("--vae-name", default=SYNTH_VAE, help="the VAE the world's data_encode.yaml names (default "
                   "synth-vae): the shipped name of the VAE its data was encoded with")
    p.add_argument("--out", type=Path, default=Path("configs/models"))
    a = p.parse_args(argv)
    if a.vae:
        print(f"installed {install_vae(a.vae, a.out)}")
    if a.world:
        print(f"installed {install_world(a.world, a.out, a.vae_name)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
