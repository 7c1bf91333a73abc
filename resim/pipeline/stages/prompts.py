"""Stage 6: encode every distinct prompt once with T5 into the dataset's prompt table.

ReSim conditions on the fixed CogVideoX prefix joined with the driving command, and drops the command
(prefix alone) for classifier-free guidance. So a dataset has exactly ``len(COMMANDS) + 1`` distinct
prompts, whatever its size: they are encoded once here (226 padded tokens, the full last hidden state)
and samples carry only ``prompt_id`` / ``null_prompt_id`` (sha256 of the text).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from resim.media.encoders import TextEncoder
from resim.pipeline.config import PipelineConfig, config_from_dict
from resim.shards.prompts import PromptTable
from resim.shards.schema import COMMANDS, prompt_id, prompt_text


def all_prompts() -> list[tuple[str, str]]:
    """(text, role) of every prompt a dataset can reference."""
    return [(prompt_text(c), "command") for c in COMMANDS] + [(prompt_text(None), "null")]


class PromptStage:
    """Callable over batches ``{"text": [...], "role": [...]}`` → ``{"prompt_id": [...]}``; writes the table."""

    name = "prompts"

    def __init__(self, cfg, device: str | None = None):
        # torch only here, in the actor: the driver imports this module (all_prompts) and stays torch-free
        import torch

        self.cfg = cfg if isinstance(cfg, PipelineConfig) else config_from_dict(cfg)
        e = self.cfg.encode
        torch.set_num_threads(e.torch_threads)
        self.encoder = TextEncoder(e.text_encoder_path, max_tokens=e.max_text_tokens,
                                   placeholder_seed=e.placeholder_seed, device=device)

    def __call__(self, batch: dict) -> dict:
        table = PromptTable(Path(self.cfg.out))
        have = set(table.ids())
        texts = [str(t) for t in batch["text"]]
        roles = [str(r) for r in batch["role"]]
        todo = [i for i, t in enumerate(texts) if prompt_id(t) not in have]
        if todo:
            emb, counts = self.encoder.encode_with_counts([texts[i] for i in todo])
            info = self.encoder.info
            for j, i in enumerate(todo):   # num_tokens: the prompt's own tokens (+ EOS), not the padded length
                table.add(texts[i], emb[j].astype(np.float16), roles[i], info.encoder_id,
                          placeholder=info.placeholder, num_tokens=counts[j])
        return {"prompt_id": np.array([prompt_id(t) for t in texts], dtype=object)}
