"""Prompt table: stored once, exact (padded) embedding, idempotent and safe under concurrent adds."""
import multiprocessing as mp

import numpy as np
import pytest

from resim.shards.npy import float32_to_bf16_bits
from resim.shards.prompts import PromptConflictError, PromptTable
from resim.shards.schema import prompt_id, prompt_text


def _emb(seed, L=226, D=64):
    e = np.random.default_rng(seed).standard_normal((L, D)).astype(np.float32)
    e[20:] = np.random.default_rng(seed + 1).standard_normal((L - 20, D)) * 1e-3  # T5 pads are not zero
    return float32_to_bf16_bits(e)


def test_add_get_exact_and_idempotent(tmp_path):
    t = PromptTable(tmp_path)
    text = prompt_text("Turning left")
    e = _emb(0)
    pid = t.add(text, e, "command", "t5-test", dtype="bfloat16", num_tokens=20)
    assert pid == prompt_id(text)
    assert t.add(text, e.copy(), "command", "t5-test", dtype="bfloat16", num_tokens=20) == pid
    got = PromptTable(tmp_path).get(pid)
    assert got.dtype == np.uint16 and got.shape == (226, 64) and np.array_equal(got, e)  # never trimmed
    info = t.info(pid)
    assert info["role"] == "command" and info["command"] == "Turning left" and info["placeholder"] is False
    assert PromptTable(tmp_path).get(pid, as_float32=True).dtype == np.float32
    with pytest.raises(PromptConflictError, match="different embedding"):
        t.add(text, _emb(5), "command", "t5-test", dtype="bfloat16")
    with pytest.raises(PromptConflictError, match="encoder_id"):
        t.add(text, e, "command", "other-encoder", dtype="bfloat16", num_tokens=20)
    with pytest.raises(ValueError, match="role"):
        t.add("x", e, "cmd", "t5", dtype="bfloat16")
    with pytest.raises(KeyError, match="not in"):
        t.get("0" * 64)


def _worker(args):
    root, i = args
    t = PromptTable(root)
    ids = []
    for command in ("Turning left", "Moving forward", "Turning right", None):
        seed = {"Turning left": 1, "Moving forward": 2, "Turning right": 3, None: 4}[command]
        ids.append(t.add(prompt_text(command), _emb(seed, L=32, D=16), "null" if command is None else "command",
                         "t5-test", dtype="bfloat16"))
    ids.append(t.add(f"worker {i} private prompt", _emb(100 + i, L=32, D=16), "command", "t5-test",
                     dtype="bfloat16"))
    return ids


def test_concurrent_adds(tmp_path):
    ctx = mp.get_context("fork")
    with ctx.Pool(4) as pool:
        results = pool.map(_worker, [(str(tmp_path), i) for i in range(8)])
    t = PromptTable(tmp_path)
    assert len(t.ids()) == 4 + 8  # shared prompts once, every private prompt kept (no lost update)
    assert all(r[:4] == results[0][:4] for r in results)
    assert np.array_equal(t.get(results[0][0]), _emb(1, L=32, D=16))
    assert not [p for p in (tmp_path / "prompts").iterdir() if ".tmp-" in p.name]
