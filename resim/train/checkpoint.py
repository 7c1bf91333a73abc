"""Sharded, atomic, safely-loaded checkpoints (torch.distributed.checkpoint).

Layout of one checkpoint, ``RUN_DIR/checkpoints/step_00001000/``::

    .metadata, __*_*.distcp   DCP: model, optimizer and EMA state, sharded by the writing ranks
                              (FSDP2 DTensors stay sharded; DCP reshards on load to another world size)
    rank_<r>.json             per rank: RNG states (python, numpy, torch, cuda) and the data position
    meta.json                 step, scheduler state (the step: the LR is a pure function of it),
                              world size, resolved config, time; written last

Atomicity: everything is written to ``step_XXXXXXXX.tmp/``; after every rank is done, rank 0
renames it to ``step_XXXXXXXX/`` (one ``rename``, atomic on POSIX). A crash during a save leaves
only a ``.tmp`` folder, which ``latest_complete`` ignores and the next save removes, so the
previous checkpoint stays the latest usable one.

Safe loading: DCP reads its ``.metadata`` with plain ``pickle.load`` and non-tensor values with
``torch.load(weights_only=False)``. ``SafeFileSystemReader`` swaps in an unpickler that only admits
DCP's own metadata classes, and ``SafeLoadPlanner`` loads values with ``weights_only=True``.
The JSON files need no unpickling at all.
"""
from __future__ import annotations

import base64
import enum
import io
import json
import os
import pickle
import random
import shutil
import signal
import time
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.distributed.checkpoint as dcp
from torch.distributed.checkpoint import DefaultLoadPlanner, FileSystemReader, FileSystemWriter
# the keys DCP saves a state under, and the helper DCP's own planner sets a loaded value with
from torch.distributed.checkpoint._nested_dict import flatten_state_dict, set_element
from torch.distributed.checkpoint.api import CheckpointException
from torch.distributed.checkpoint.metadata import StorageMeta

from resim.media.files import NotARegularFile, check_regular, open_regular, read_text
from resim.shards.fsio import fsync_dir

CHECKPOINTS = "checkpoints"
_PREFIX = "step_"
_TMP = ".tmp"


class CheckpointError(RuntimeError):
    """A checkpoint is missing, incomplete, or holds something we refuse to load."""


# ---------------------------------------------------------------- safe unpickling of DCP metadata
# Checkpoints travel between people and clusters, so their pickled DCP ``.metadata`` is untrusted: only these
# exact (module, name) globals are resolved. A dotted name (``os.system`` under an allowed module, which
# ``find_class`` would walk) is never one of them.
_DCP_METADATA = "torch.distributed.checkpoint.metadata"
_ALLOWED_GLOBALS = {
    (_DCP_METADATA, n) for n in ("Metadata", "MetadataIndex", "StorageMeta", "TensorProperties",
                                 "TensorStorageMetadata", "BytesStorageMetadata", "ChunkStorageMetadata",
                                 "_MEM_FORMAT_ENCODING")
} | {
    ("torch.distributed.checkpoint.filesystem", "_StorageInfo"),
    ("torch", "Size"), ("torch", "device"), ("collections", "OrderedDict"), ("builtins", "set"),
    ("builtins", "frozenset"), ("builtins", "slice"), ("torch._utils", "_rebuild_tensor_v2"),
    ("torch.serialization", "_get_layout"), ("pathlib", "PosixPath"), ("pathlib", "PurePosixPath"),
    ("enum", "Enum"),
}


def _enum_member(cls: Any, name: Any):
    """What ``builtins.getattr`` may do in DCP metadata: name an allowed enum's member. Python 3.11.0-3.11.4
    pickle an enum member as ``getattr(EnumClass, 'NAME')`` (3.11.5+ as ``EnumClass(value)``), so the
    memory-format enum of ``TensorProperties`` arrives in that form from those interpreters."""
    if not (isinstance(cls, type) and issubclass(cls, enum.Enum)
            and (cls.__module__, cls.__qualname__) in _ALLOWED_GLOBALS and isinstance(name, str)
            and name in cls.__members__):
        raise CheckpointError(f"checkpoint metadata calls getattr({cls!r}, {name!r}); only members of the "
                              "allowed DCP enums may be named")
    return cls.__members__[name]


class _MetadataUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) == ("builtins", "getattr"):
            return _enum_member
        ok = (module, name) in _ALLOWED_GLOBALS
        # torch dtypes / layouts / memory formats pickle as ``torch.<name>`` attributes
        if (module == "torch" and "." not in name
                and isinstance(getattr(torch, name, None), (torch.dtype, torch.layout, torch.memory_format))):
            ok = True
        if not ok:
            raise CheckpointError(f"checkpoint metadata refers to {module}.{name}, which is not allowed "
                                  "(only torch.distributed.checkpoint metadata classes are unpickled)")
        return super().find_class(module, name)


class SafeFileSystemReader(FileSystemReader):
    """FileSystemReader whose metadata is unpickled with an allow-list."""

    def read_metadata(self, *args: Any, **kwargs: Any):
        rank = kwargs.get("rank")
        path = self._get_metadata_path(rank)
        try:
            f = open_regular(path)   # a FIFO named .metadata blocked --resume forever
        except NotARegularFile as e:
            raise CheckpointError(f"checkpoint metadata {e}") from None
        with f:
            try:
                metadata = _MetadataUnpickler(f).load()
            except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as e:
                raise CheckpointError(f"checkpoint metadata {path} is truncated or corrupt ({type(e).__name__}: "
                                      f"{e})") from None
        if getattr(metadata, "storage_meta", None) is None:
            metadata.storage_meta = StorageMeta()
        metadata.storage_meta.load_id = self.load_id
        return metadata


class SafeLoadPlanner(DefaultLoadPlanner):
    """Non-tensor values (optimizer hyper-parameters) are loaded with ``weights_only=True``."""

    def load_bytes(self, read_item, value: io.BytesIO) -> None:
        obj = torch.load(value, weights_only=True)
        if self.flatten_state_dict:
            set_element(self.original_state_dict, self.mappings[read_item.dest_index.fqn], obj)
        else:
            self.state_dict[read_item.dest_index.fqn] = obj


# ---------------------------------------------------------------- RNG states as JSON
def _b64(t: torch.Tensor) -> str:
    return base64.b64encode(t.cpu().numpy().tobytes()).decode()


def _unb64(s: str) -> torch.Tensor:
    return torch.from_numpy(np.frombuffer(base64.b64decode(s), dtype=np.uint8).copy())


def rng_state() -> dict:
    """This process's RNG states as JSON-able data."""
    ver, internal, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state()
    out = {
        "python": [ver, list(internal), gauss],
        "numpy": [name, keys.tolist(), int(pos), int(has_gauss), float(cached)],
        "torch": _b64(torch.get_rng_state()),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        out["cuda"] = [_b64(s) for s in torch.cuda.get_rng_state_all()]
    return out


def set_rng_state(state: dict) -> None:
    ver, internal, gauss = state["python"]
    random.setstate((ver, tuple(internal), gauss))
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(_unb64(state["torch"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([_unb64(s) for s in state["cuda"]])


# A CPU RNG stream of its own (python random, numpy, torch), swapped in and out of the global generators without
# JSON round trips on the hot path (the trainer's data stream for plain iterables); JSON only when checkpointed.
CpuRng = tuple  # (random.getstate(), np.random.get_state(), torch.get_rng_state())


def seeded_cpu_rng(seed: int) -> CpuRng:
    return (random.Random(seed).getstate(), np.random.RandomState(seed % 2**32).get_state(),
            torch.Generator().manual_seed(seed).get_state())


def get_cpu_rng() -> CpuRng:
    return random.getstate(), np.random.get_state(), torch.get_rng_state()


def set_cpu_rng(state: CpuRng) -> None:
    random.setstate(state[0])
    np.random.set_state(state[1])
    torch.set_rng_state(state[2])


def cpu_rng_to_json(state: CpuRng) -> dict:
    (ver, internal, gauss), (name, keys, pos, has_gauss, cached), t = state
    return {"python": [ver, list(internal), gauss], "numpy": [name, keys.tolist(), int(pos), int(has_gauss),
                                                              float(cached)], "torch": _b64(t)}


def cpu_rng_from_json(d: dict) -> CpuRng:
    ver, internal, gauss = d["python"]
    name, keys, pos, has_gauss, cached = d["numpy"]
    return ((ver, tuple(internal), gauss), (name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached),
            _unb64(d["torch"]))


# ---------------------------------------------------------------- finding checkpoints
def checkpoint_path(run_dir: str | Path, step: int) -> Path:
    return Path(run_dir) / CHECKPOINTS / f"{_PREFIX}{step:08d}"


def list_complete(run_dir: str | Path) -> list[tuple[int, Path]]:
    """Complete checkpoints (renamed into place and holding meta.json), oldest first."""
    root = Path(run_dir) / CHECKPOINTS
    out = []
    if root.is_dir():
        for p in root.iterdir():
            if p.is_dir() and p.name.startswith(_PREFIX) and not p.name.endswith(_TMP) and (p / "meta.json").is_file():
                try:
                    out.append((int(p.name[len(_PREFIX):]), p))
                except ValueError:
                    continue
    return sorted(out)


def latest_complete(run_dir: str | Path) -> Path | None:
    done = list_complete(run_dir)
    return done[-1][1] if done else None


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "w") as f:
        json.dump(obj, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


# ---------------------------------------------------------------- save / load
def save(run_dir: str | Path, step: int, state: dict[str, Any], *, rank_state: dict, meta: dict,
         rank: int, barrier, keep: int = 2) -> Path:
    """Write a checkpoint atomically. Collective: every rank calls it with its own ``rank_state``.

    ``state``: {"model": sd, "optim": sd, "ema": sd} of tensors / DTensors (from get_state_dict).
    ``barrier``: a no-arg callable (the process-group barrier, or a no-op).
    """
    final = checkpoint_path(run_dir, step)
    tmp = final.with_name(final.name + _TMP)
    if rank == 0:
        if tmp.exists():
            shutil.rmtree(tmp)  # left by a crash during an earlier save
        tmp.mkdir(parents=True)
    barrier()
    try:
        with warnings.catch_warnings():  # single-process runs: DCP warns that it saves without a process group
            warnings.filterwarnings("ignore", message="torch.distributed is disabled")
            dcp.save(state, storage_writer=FileSystemWriter(tmp))
        _write_json(tmp / f"rank_{rank}.json", rank_state)
    except OSError:   # a full disk: the half-written step must not go on filling it (the last good one stays)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    barrier()
    if rank == 0:
        if os.environ.get("RESIM_FAULT_KILL_IN_SAVE") == str(step):
            # fault injection for tests: die (SIGKILL, no clean-up) with the save half done
            os.kill(os.getpid(), signal.SIGKILL)
        _write_json(tmp / "meta.json", {**meta, "step": step, "saved_unix_s": time.time()})
        if final.exists():  # the same step saved again (a resumed run re-reaching it): replace
            shutil.rmtree(final)
        os.replace(tmp, final)
        fsync_dir(final.parent)
        for _, old in list_complete(run_dir)[:-keep]:
            shutil.rmtree(old, ignore_errors=True)
    barrier()
    return final


def load(path: str | Path, state: dict[str, Any], *, rank: int,
         legacy_name: Callable[[str], str] | None = None) -> tuple[dict, dict | None]:
    """Load ``state`` in place from checkpoint ``path``; return (meta, this rank's rank_state or None).

    ``rank_state`` is None when the checkpoint was written by fewer ranks than this run has
    (a resharded resume: weights and optimizer load, RNG / data position start fresh).
    ``legacy_name``: a parameter's name in checkpoints of an older version of the model (LoRA before peft:
    ``resim.models.world.lora.pre_peft_name``); such a checkpoint is read under those names.
    """
    p = Path(path)
    if not (p / "meta.json").is_file():
        raise CheckpointError(f"{p} is not a complete checkpoint (no meta.json)")
    for f in p.iterdir():   # DCP opens its shards by name: a FIFO or device among them would block or never end
        try:
            check_regular(f)
        except NotARegularFile as e:
            raise CheckpointError(f"checkpoint file {e}") from None
    reader = SafeFileSystemReader(p)
    saved = reader.read_metadata().state_dict_metadata  # refuse foreign pickles here, with our message
    target, back = state, {}
    if legacy_name is not None and not set(flatten_state_dict(state)[0]) <= set(saved):
        def to_old(name: str) -> str:
            back[legacy_name(name)] = name
            return legacy_name(name)
        old = _renamed(state, to_old)
        if set(flatten_state_dict(old)[0]) <= set(saved):
            target = old
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="torch.distributed is disabled")
        try:
            dcp.load(target, storage_reader=reader, planner=SafeLoadPlanner())
        except CheckpointError:
            raise
        except (CheckpointException, RuntimeError, ValueError, EOFError, OSError, pickle.UnpicklingError) as e:
            # torch's reader on a truncated .distcp: "PytorchStreamReader failed reading zip archive"; a tensor of
            # another shape than this model's: a size mismatch. The checkpoint's problem, said in one line (DCP
            # wraps each rank's error with its traceback: the underlying exception is what names the cause)
            if isinstance(e, CheckpointException) and e.failures:
                inner = next(iter(e.failures.values()))   # (exception, traceback) or a wrapper holding it
                inner = inner[0] if isinstance(inner, tuple) else inner
                e = getattr(inner, "exception", inner)
            why = " ".join(str(e).split())[:300]
            raise CheckpointError(f"checkpoint {p}: its tensors cannot be read into this model "
                                  f"({type(e).__name__}: {why})") from None
    if target is not state:   # tensors were filled in place; the optimizer's param_groups were replaced
        state.update(_renamed(target, lambda n: back.get(n, n)))
    meta = _read_json(p / "meta.json")
    named = p.name[len(_PREFIX):]
    if named.isdigit() and meta.get("step") != int(named):   # a step of 10^18 resumed as "done, nothing to do"
        raise CheckpointError(f"checkpoint {p / 'meta.json'}: step {meta.get('step')!r} is not the step in the "
                              f"folder's name ({int(named)}); the checkpoint was edited or is corrupt")
    rs_path = p / f"rank_{rank}.json"
    rank_state = _read_json(rs_path) if rs_path.is_file() else None
    return meta, rank_state


def _read_json(path: Path) -> dict:
    """A checkpoint's JSON object (``meta.json``, ``rank_<r>.json``); ``CheckpointError`` naming the file."""
    try:
        d = json.loads(read_text(path))
    except NotARegularFile as e:
        raise CheckpointError(f"checkpoint file {e}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"checkpoint file {path} is not valid JSON ({e})") from None
    if not isinstance(d, dict):
        raise CheckpointError(f"checkpoint file {path} holds {type(d).__name__}, not a JSON object")
    return d


def _renamed(obj: Any, name: Callable[[str], str]) -> Any:
    """``obj`` (nested dicts and lists) with every string key and every string in a list (the optimizer's
    ``param_groups[i]["params"]``) passed through ``name``; the same tensor objects."""
    if isinstance(obj, dict):
        return {(name(k) if isinstance(k, str) else k): _renamed(v, name) for k, v in obj.items()}
    if isinstance(obj, list):
        return [name(v) if isinstance(v, str) else _renamed(v, name) for v in obj]
    return obj
