"""Reassemble a run of a leased-GPU script (scripts/gpu_vae_sweep.sh, scripts/gpu_synth_round.sh) into a folder
the library loads:

    python scripts/gpu_unpack.py GPU_OUT RUN DEST      # e.g. OUT V runs/gpu/V,  OUT W runs/gpu/W

A leased machine returns at most 8 files of 16 MB, so the scripts bring each run's weights back as
``RUN.safetensors`` or ``RUN.part<i>.safetensors`` and its configs and logs in ``RUN.logs.tgz`` (the sweep: ``logs.tgz``).

* A VAE run (its logs hold the diffusers ``config.json``) becomes ``DEST/vae/`` (float32, loads with
  ``AutoencoderKLCogVideoX.from_pretrained`` and ``--vae DEST/vae``); its discriminator, when it came back, goes
  with the VAE's weights into ``DEST/init_with_discriminator.safetensors`` (``model.init_weights`` to continue the
  adversarial run).
* A world-model run becomes ``DEST/final/`` with the EMA weights as ``model.safetensors`` beside the run's
  ``config.yaml`` and ``data_encode.yaml`` (the layout of configs/models/synth-world: ``--checkpoint DEST``).
"""
from __future__ import annotations

import sys
import tarfile
from pathlib import Path

from safetensors.torch import load_file, save_file


def main(src: str, run: str, dest: str) -> None:
    src_dir, out = Path(src), Path(dest)
    parts = sorted(src_dir.glob(f"{run}.part*.safetensors")) or [src_dir / f"{run}.safetensors"]
    if not parts[0].is_file():
        raise SystemExit(f"{src_dir}: no weights of run {run!r}")
    state = {}
    for p in parts:
        state.update({k: v.float() for k, v in load_file(str(p)).items()})
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    tgz = src_dir / f"{run}.logs.tgz"          # gpu_synth_round.sh: one per run; gpu_vae_sweep.sh: one for all
    with tarfile.open(tgz if tgz.is_file() else src_dir / "logs.tgz") as tar:
        for m in tar.getmembers():
            if m.name.startswith(f"{run}/") and m.isfile():
                f = logs / Path(m.name).relative_to(run)
                f.parent.mkdir(parents=True, exist_ok=True)
                f.write_bytes(tar.extractfile(m).read())
    vae_config = next((p for p in (logs / "final/vae/config.json", logs / "config.json") if p.is_file()), None)
    if vae_config is not None:
        vae = out / "vae"
        vae.mkdir(exist_ok=True)
        (vae / "config.json").write_bytes(vae_config.read_bytes())
        weights = {k: v for k, v in state.items() if not k.startswith("discriminator.")}
        save_file(weights, str(vae / "diffusion_pytorch_model.safetensors"))
        if len(weights) < len(state):
            save_file(state, str(out / "init_with_discriminator.safetensors"))
        print(f"{vae}: a VAE of {sum(v.numel() for v in weights.values()):,} parameters from {len(parts)} file(s)")
        return
    final = out / "final"
    final.mkdir(exist_ok=True)
    for name in ("config.yaml", "data_encode.yaml"):
        if not (logs / "final" / name).is_file():
            raise SystemExit(f"{src_dir}: run {run!r} brought back no final/{name}")
        (final / name).write_bytes((logs / "final" / name).read_bytes())
    save_file(state, str(final / "model.safetensors"))
    print(f"{final}: a world model of {sum(v.numel() for v in state.values()):,} parameters (EMA) "
          f"from {len(parts)} file(s)")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    main(*sys.argv[1:])
