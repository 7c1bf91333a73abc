"""How ``tests/data/lora-v1-world/`` was made: a tiny world model with LoRA, written by the hand-written
``training.lora.LoRALinear`` that ``build_world`` used before LoRA moved to peft (run on commit c972fdd; it cannot
run once ``training/lora.py`` is gone, which is the point: the files keep the old format).

* ``config.yaml``: the run config's ``model_name`` + ``model`` section (what ``load_world_model`` reads).
* ``model.safetensors``: the model's ``state_dict()``, as the trainer exports ``final/model.safetensors``
  (old layout: base weights under their own names, ``...to_q.weight``; adapters ``...to_q.lora_A`` (rank, in)
  and ``...to_q.lora_B`` (out, rank)), every ``lora_B`` and the new modules' zero-initialised outputs set to
  seeded non-zero values so that the adapters change the output.
* ``reference.safetensors``: a fixed input (``x``, ``t``, ``text``, ``trajectory``, ``actions``) and the model's
  float32 CPU output ``v`` for it.

    .venv/bin/python tests/data/lora-v1-world/make_fixture.py
"""
from pathlib import Path

import torch
import yaml
from safetensors.torch import save_file

from resim.train.tasks.world_model import build_world

HERE = Path(__file__).parent
MODEL = {"preset": "tiny", "overrides": {"num_layers": 1}, "trainable": "lora+new", "lora_rank": 4,
         "lora_alpha": 8.0, "lora_targets": ["to_q", "to_k", "to_v", "to_out.0", "ff.net.2"]}


def main() -> None:
    torch.manual_seed(0)
    model = build_world(MODEL).eval()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for n, p in model.named_parameters():
            if n.endswith(".lora_B") or n.startswith(("trajectory_encoder.head", "action_encoder.proj_out")):
                p.copy_(torch.randn(p.shape, generator=g) * 0.05)
    g = torch.Generator().manual_seed(2)
    inputs = {"x": torch.randn(1, 3, 16, 8, 12, generator=g), "t": torch.tensor([[0, 500, 999]]),
              "text": torch.randn(1, 16, 64, generator=g), "trajectory": torch.randn(1, 8, 3, generator=g),
              "actions": torch.randn(1, 3, 3, generator=g)}
    with torch.no_grad():
        v = model(inputs["x"], inputs["t"], inputs["text"], inputs["trajectory"], inputs["actions"])
    save_file({k: t.contiguous() for k, t in model.state_dict().items()}, str(HERE / "model.safetensors"))
    save_file({**inputs, "v": v.contiguous()}, str(HERE / "reference.safetensors"))
    (HERE / "config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": MODEL}, sort_keys=False))


if __name__ == "__main__":
    main()
