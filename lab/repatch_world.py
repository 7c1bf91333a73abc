"""Resize a world model's 2 x 2 patches to 1 x 1 (FlexiViT-style weight transfer) for the finer-tokens probe
(docs/lab/2026-11-26-synth-world-stage-chain.md, runs KP and KP2).

    python lab/repatch_world.py configs/models/synth-world/model.safetensors OUT.safetensors
    resim train world ... --set model.init_weights=OUT.safetensors \
        --set model.overrides.patch_size=1 --set model.overrides.spatial_interpolation_scale=3.75

* ``patch_embed.proj`` (D, C, 2, 2) -> (D, C, 1, 1), the 2 x 2 taps summed: a fine token of a latent whose 2 x 2 block
  is uniform embeds as the coarse token of that block did (FlexiViT resizes by a pseudo-inverse; for an exact halving
  the sum is that map restricted to constant blocks, and needs no solver).
* ``proj_out`` (p*p*C rows, ordered (C, p, p) as ``dit.py``'s unpatchify reads them) -> C rows, the four
  sub-positions averaged: each fine token predicts the mean of what its coarse token predicted for its block.
* Positions are sin-cos and recomputed (``dit.py``); doubling ``spatial_interpolation_scale`` makes the 8 x 12 grid
  span the range the 4 x 6 one did. Every other tensor is copied as it is.
"""
import argparse

from safetensors.torch import load_file, save_file


def repatch(sd: dict) -> dict:
    sd = dict(sd)
    w = sd["patch_embed.proj.weight"]
    if tuple(w.shape[-2:]) != (2, 2):
        raise SystemExit(f"patch_embed.proj.weight has patches of {tuple(w.shape[-2:])}, expected (2, 2)")
    sd["patch_embed.proj.weight"] = w.sum(dim=(2, 3), keepdim=True).contiguous()
    wo, bo = sd["proj_out.weight"], sd["proj_out.bias"]
    c = wo.shape[0] // 4
    sd["proj_out.weight"] = wo.reshape(c, 4, -1).mean(1).contiguous()
    sd["proj_out.bias"] = bo.reshape(c, 4).mean(1).contiguous()
    return sd


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", help="a 2 x 2-patch world model's weights (model.safetensors or a run's ema.safetensors)")
    ap.add_argument("dst", help="where to write the 1 x 1-patch weights")
    a = ap.parse_args()
    sd = repatch(load_file(a.src))
    save_file(sd, a.dst)
    print(f"wrote {a.dst}: patch_embed.proj {tuple(sd['patch_embed.proj.weight'].shape)}, "
          f"proj_out {tuple(sd['proj_out.weight'].shape)}")


if __name__ == "__main__":
    main()
