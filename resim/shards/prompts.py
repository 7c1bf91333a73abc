"""The prompt table: each distinct text embedding stored once per dataset.

ReSim has only a handful of prompts (a fixed prefix + one of three commands, and
the prefix alone as the classifier-free-guidance null prompt), while one padded
CogVideoX T5 embedding is 226 x 4096 values (1.85 MB in bf16) — often more than a
latent. So samples store only ``meta.prompt_id`` / ``meta.null_prompt_id`` and the
reader attaches the embedding.

Files::

    DIR/prompts/prompts.json   {"version": 1, "prompts": {id: entry}}
    DIR/prompts/<id>.npy       the embedding exactly as the encoder produced it (padded, never trimmed)

``id = sha256(text)`` (``resim.shards.schema.prompt_id``). An entry: ``text``, ``role``
(``command`` | ``null``), ``command`` (or null), ``encoder_id``, ``placeholder``
(random-init encoder), ``shape``, ``dtype`` (``float16``/``float32``/``bfloat16``;
bfloat16 is stored as uint16 bits), ``num_tokens`` (tokens before padding, or
null), ``file``, ``npy_sha256``, ``bytes``.

Concurrency: many workers may ``add`` the same prompt at once. The ``.npy`` is
put in place with a no-clobber link (identical bytes from another worker are
fine, different bytes are a :class:`PromptConflictError`); ``prompts.json`` is
updated under an exclusive ``fcntl.flock`` on ``prompts/.lock`` and replaced
atomically. (flock needs a local filesystem or NFSv4.)
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from resim.media.files import NotARegularFile, open_regular
from resim.shards import layout, safejson
from resim.shards.confine import UnsafePathError, confined
from resim.shards.errors import ShardReadError
from resim.shards.fsio import atomic_write_bytes, link_no_clobber, tmp_name
from resim.shards.npy import NpyError, decode_npy, encode_npy, stored_to_float32
from resim.shards.schema import COMMANDS, prompt_id

ROLES = ("command", "null")
EMBED_DTYPES = {"float16": np.dtype("float16"), "float32": np.dtype("float32"), "bfloat16": np.dtype("uint16")}
TABLE_VERSION = 1
# An .npy file is its header (magic, version, length, a dict padded to a multiple of 64 bytes; v1 allows a
# 65535-byte dict) plus the data. The declared size must fit the declared shape within that, so a table cannot
# make a reader take a much larger file for a small embedding.
MAX_NPY_HEADER_BYTES = 65535 + 10
# CogVideoX's padded T5 embedding is 226 x 4096 float32 = 3.7 MB: an entry declaring more than this is refused
# before its file is opened (a sparse file of matching size would otherwise be read whole).
MAX_EMBEDDING_BYTES = 256 << 20


class PromptConflictError(ValueError):
    """The same prompt id is being added with a different embedding or encoder."""


class PromptTableError(ShardReadError):
    """The prompt table cannot be used: prompts.json unreadable or malformed, or an entry whose file lies outside
    ``prompts/``, is not a regular file, or differs from the size, dtype and shape the entry declares."""


class PromptTable:
    """``DIR/prompts``: add/get text embeddings by ``sha256(text)``."""

    def __init__(self, root):
        self.root = Path(root)
        self.dir = layout.prompts_dir(root)
        self._cache: dict[str, np.ndarray] = {}
        self._entries: dict[str, dict] | None = None

    # ---- reading ---------------------------------------------------------------------------------
    @property
    def json_path(self) -> Path:
        return self.dir / "prompts.json"

    def entries(self, reload: bool = False) -> dict[str, dict]:
        """id -> entry (empty when the table does not exist)."""
        if self._entries is None or reload:
            if self.json_path.is_file():
                try:
                    data = safejson.load_file(self.json_path)   # size and nesting limits (a JSON bomb)
                except ValueError as e:
                    raise PromptTableError(f"prompt table {self.json_path}: unreadable: {e}") from e
                if not isinstance(data, dict) or not isinstance(data.get("prompts"), dict):
                    raise PromptTableError(f"prompt table {self.json_path}: not an object with a 'prompts' object")
                if data.get("version") != TABLE_VERSION:
                    raise PromptTableError(f"{self.json_path}: unknown prompt table version {data.get('version')!r}")
                for pid, e in data["prompts"].items():
                    if not isinstance(e, dict):
                        raise PromptTableError(f"prompt table {self.json_path}: prompt {pid}: entry is a JSON "
                                               f"{type(e).__name__}, not an object")
                self._entries = data["prompts"]
            else:
                self._entries = {}
        return self._entries

    def ids(self) -> list[str]:
        return sorted(self.entries())

    def info(self, pid: str) -> dict:
        try:
            return self.entries()[pid]
        except KeyError:
            self.entries(reload=True)  # another worker may have added it since
            if pid not in self._entries:
                raise KeyError(f"prompt id {pid} is not in {self.json_path}") from None
            return self._entries[pid]

    def file_path(self, pid: str) -> Path:
        """The embedding file of ``pid``: its entry's ``file``, which must name a file inside ``prompts/``
        (prompts.json is dataset input: ``"file": "/dev/zero"`` or ``"../../x"`` is a :class:`PromptTableError`)."""
        try:
            return confined(self.dir, self.info(pid).get("file", f"{pid}.npy"), f"prompt {pid}: file")
        except UnsafePathError as e:
            raise PromptTableError(str(e)) from None

    def declared_bytes(self, pid: str) -> int:
        """The size ``pid``'s entry declares for its file (``bytes``), checked to fit its ``shape`` and ``dtype``
        (an .npy of exactly that data plus a header) and :data:`MAX_EMBEDDING_BYTES`; :class:`PromptTableError`."""
        info = self.info(pid)
        shape, dtype, nbytes = info.get("shape"), info.get("dtype"), info.get("bytes")
        if dtype not in EMBED_DTYPES:
            raise PromptTableError(f"prompt {pid}: dtype {dtype!r} is not one of {list(EMBED_DTYPES)}")
        if not (isinstance(shape, list) and len(shape) == 2
                and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
            raise PromptTableError(f"prompt {pid}: shape {shape!r} is not [L, D] (two non-negative integers)")
        data = shape[0] * shape[1] * EMBED_DTYPES[dtype].itemsize
        if not isinstance(nbytes, int) or isinstance(nbytes, bool) or not data < nbytes <= data + MAX_NPY_HEADER_BYTES:
            raise PromptTableError(f"prompt {pid}: bytes {nbytes!r} does not fit shape {shape} of {dtype} (an .npy "
                                   f"file of {data} data bytes plus its header)")
        if nbytes > MAX_EMBEDDING_BYTES:
            raise PromptTableError(f"prompt {pid}: declares a {nbytes}-byte embedding, more than the limit of "
                                   f"{MAX_EMBEDDING_BYTES}")
        return nbytes

    def read_file(self, pid: str) -> bytes:
        """The bytes of ``pid``'s embedding file: confined to ``prompts/`` (:meth:`file_path`), a regular file (a
        FIFO or device is refused before reading), of the declared size (:meth:`declared_bytes`); never more than
        that is read. :class:`PromptTableError` (OSError where the file is missing or unreadable)."""
        path = self.file_path(pid)
        nbytes = self.declared_bytes(pid)
        try:
            fh = open_regular(path)
        except NotARegularFile as e:   # missing or unreadable stays an OSError, as the docstring says
            err = PromptTableError if e.reason.startswith("is ") else OSError
            raise err(f"prompt {pid}: file {e}") from None
        with fh:
            st = os.fstat(fh.fileno())
            if st.st_size != nbytes:
                raise PromptTableError(f"prompt {pid}: file {path} holds {st.st_size} bytes, prompts.json says "
                                       f"{nbytes}")
            data = fh.read(nbytes + 1)
        if len(data) != nbytes:
            raise PromptTableError(f"prompt {pid}: file {path} changed size while read ({len(data)} bytes, "
                                   f"prompts.json says {nbytes})")
        return data

    def get(self, pid: str, as_float32: bool = False) -> np.ndarray:
        """The stored embedding (bfloat16 as uint16 bits), read-only and cached; ``as_float32`` widens exactly."""
        arr = self._cache.get(pid)
        if arr is None:
            info = self.info(pid)
            try:
                arr = decode_npy(self.read_file(pid))
            except NpyError as e:
                raise PromptTableError(f"prompt {pid}: file {self.file_path(pid)}: {e}") from e
            want = EMBED_DTYPES[info["dtype"]]
            if arr.dtype != want or list(arr.shape) != list(info["shape"]):
                raise PromptTableError(f"prompt {pid}: file holds {arr.dtype}{list(arr.shape)}, table says "
                                       f"{info['dtype']}{info['shape']}")
            arr.setflags(write=False)
            self._cache[pid] = arr
        if as_float32:
            if pid + ":f32" not in self._cache:
                f = stored_to_float32(arr, self.info(pid)["dtype"])
                f.setflags(write=False)
                self._cache[pid + ":f32"] = f
            return self._cache[pid + ":f32"]
        return arr

    def total_bytes(self) -> int:
        """Bytes of all embedding files plus prompts.json."""
        n = sum(e["bytes"] for e in self.entries().values())
        return n + (self.json_path.stat().st_size if self.json_path.exists() else 0)

    # ---- writing ---------------------------------------------------------------------------------
    @contextmanager
    def _locked(self):
        self.dir.mkdir(parents=True, exist_ok=True)
        with open(self.dir / ".lock", "a+") as lock:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(lock.fileno(), fcntl.LOCK_UN)

    def add(self, text: str, embedding: np.ndarray, role: str, encoder_id: str, *, dtype: str | None = None,
            placeholder: bool = False, num_tokens: int | None = None) -> str:
        """Store ``embedding`` for ``text`` once; return its id. Idempotent for identical data.

        ``embedding`` is the encoder's exact padded output, (L, D): float16/float32, or
        uint16 bits with ``dtype="bfloat16"``.
        """
        if role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {role!r}")
        embedding = np.asarray(embedding)
        dtype = dtype or embedding.dtype.name
        if dtype not in EMBED_DTYPES or embedding.dtype != EMBED_DTYPES[dtype]:
            raise ValueError(f"embedding dtype {embedding.dtype} with declared dtype {dtype!r} is not one of "
                             f"{ {k: v.name for k, v in EMBED_DTYPES.items()} }")
        if embedding.ndim != 2:
            raise ValueError(f"embedding must be (L, D), got shape {embedding.shape}")
        if dtype != "bfloat16" and not np.isfinite(embedding).all():
            raise ValueError(f"embedding of {text!r} holds non-finite values")
        pid = prompt_id(text)
        data = encode_npy(embedding)
        digest = hashlib.sha256(data).hexdigest()
        command = next((c for c in COMMANDS if text.rstrip(".").endswith(c)), None) if role == "command" else None
        entry = {
            "text": text, "role": role, "command": command, "encoder_id": encoder_id,
            "placeholder": bool(placeholder), "shape": list(embedding.shape), "dtype": dtype,
            "num_tokens": num_tokens, "file": f"{pid}.npy", "npy_sha256": digest, "bytes": len(data),
        }
        self.dir.mkdir(parents=True, exist_ok=True)
        final = self.dir / entry["file"]
        tmp = tmp_name(final)
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        if not link_no_clobber(tmp, final):
            tmp.unlink()
            with open(final, "rb") as fh:
                if hashlib.sha256(fh.read()).hexdigest() != digest:
                    raise PromptConflictError(f"prompt {pid} ({text!r}) already stored with a different "
                                              f"embedding in {final}")
        with self._locked():
            entries = dict(self.entries(reload=True))
            old = entries.get(pid)
            if old is not None:
                if old != entry:
                    diff = sorted(k for k in entry if old.get(k) != entry[k])
                    raise PromptConflictError(f"prompt {pid} ({text!r}) already in the table with different {diff}")
                return pid
            entries[pid] = entry
            payload = json.dumps({"version": TABLE_VERSION, "prompts": dict(sorted(entries.items()))}, indent=1)
            atomic_write_bytes(self.json_path, (payload + "\n").encode())
            self._entries = entries
        return pid
