"""Memory traffic of a piece of eager PyTorch code, counted op by op: a device-independent measure.

Elementwise kernels (norms, casts, copies, AdaLN modulation and gating) are bound by the bytes they write and
read, not by FLOPs; on a GPU they took half a training step's kernel time (docs/benchmarks.md, "GPU"). Their
cost can be counted on any device: ``Traffic`` is a ``TorchDispatchMode`` that sees every aten op of a forward
and backward run under it and adds up the bytes of its outputs, split into matmul/attention and the rest;
``SavedActivations`` adds up what autograd keeps for the backward. Used by bench/block_elementwise.py and the
block's tests (tests/models/test_block_traffic.py).

    saved = SavedActivations(model.parameters())
    with Traffic() as t, torch.autograd.graph.saved_tensors_hooks(*saved.hooks()):
        loss(model(x)).backward()
    t.bytes["other"], t.ops["other"], saved.bytes
"""
from __future__ import annotations

from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

# aten op names (before the overload) that run a matmul or an attention kernel
_MATMUL = ("mm", "addmm", "bmm", "baddbmm", "matmul", "linear", "_scaled_dot_product", "scaled_dot_product",
           "_flash_attention", "_efficient_attention", "_cudnn_attention", "flex_attention")
# ops that return a view of their input: they write no bytes
_VIEWS = frozenset({"view", "_unsafe_view", "expand", "t", "transpose", "unsqueeze", "slice", "select", "split",
                    "split_with_sizes", "chunk", "unflatten", "permute", "detach", "alias", "as_strided", "squeeze",
                    "_reshape_alias", "unbind", "narrow", "view_as"})


class Traffic(TorchDispatchMode):
    """Counts aten ops and the bytes their outputs take: ``ops`` and ``bytes`` are Counters keyed by
    ``"matmul"`` (matmuls and attention), ``"other"`` (everything that writes memory besides them) and
    ``"view"`` (ops that return views: counted, 0 bytes). ``by_op`` gives the bytes per aten op name."""

    def __init__(self):
        super().__init__()
        self.ops: Counter = Counter()
        self.bytes: Counter = Counter()
        self.by_op: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = func.__name__.split(".")[0]
        if name in _VIEWS:
            self.ops["view"] += 1
            return out
        kind = "matmul" if name.startswith(_MATMUL) else "other"
        self.ops[kind] += 1
        n = sum(t.numel() * t.element_size() for t in (out if isinstance(out, (tuple, list)) else (out,))
                if isinstance(t, torch.Tensor))
        self.bytes[kind] += n
        self.by_op[name] += n
        return out


class SavedActivations:
    """Bytes autograd keeps for the backward: distinct storages, the given parameters' own storages excluded
    (a weight saved for its gradient is not an activation). ``hooks()`` goes to
    ``torch.autograd.graph.saved_tensors_hooks``."""

    def __init__(self, params=()):
        self._params = {p.untyped_storage().data_ptr() for p in params}
        self._seen: dict[int, int] = {}

    def hooks(self):
        def pack(t):
            ptr = t.untyped_storage().data_ptr()
            if ptr not in self._params:
                self._seen[ptr] = t.untyped_storage().nbytes()
            return t
        return pack, (lambda t: t)

    @property
    def bytes(self) -> int:
        return sum(self._seen.values())
