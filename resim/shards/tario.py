"""A lean reader of shard tars for training streams: raw samples grouped by key, exactly as WebDataset groups them.

Why not ``tarfile``: in stream mode it reads a 750 KB member through ~20 small buffered reads, builds a
``TarInfo`` per member and checks every header field; on the 2-core CPU that alone cost more than reading
the bytes (``bench/loader_overhead.py``, docs/benchmarks.md ``## Training``). A shard tar is plain POSIX
tar (ustar, what ``resim.shards.writer`` writes; pax and GNU long-name headers are understood too), so a reader
needs one 512-byte header read and one data read per member. This one also

* **seeks** over members the consumer does not need (``skip_exts``, e.g. ``frames.mp4`` when the model
  trains on latents only) and over the records before ``start`` (resuming a data position), checking
  against the file size so a truncated shard is still an error, never a silently short one;
* **checks** every header's checksum and refuses a member in a code-executing format (``.pyd``,
  ``.pickle``, ...) from its header, before reading its bytes (:class:`ForbiddenMemberError`);
* is **stricter** than ``tarfile``, which ends a stream quietly at a corrupt header after the first:
  a bad checksum, a partial header or short member data raise :class:`ShardReadError` naming the shard
  and offset;
* marks a sample with a member that is a **link or device** instead of a regular file (``tarfile`` and
  WebDataset drop it silently, leaving a sample short of a member): the sample carries
  ``resim.shards.reader.BAD_MEMBER`` with the reason, and decoding it raises :class:`ShardReadError`. Its
  neighbours still read; a link's target is never followed.

Grouping follows ``webdataset.tariterators`` (``tar_file_iterator`` + ``group_by_keys``): regular files
only, names split with the same regex (``resim.shards.reader.split_member_name``), extension lower-cased,
``__*__`` metadata names skipped, consecutive members with the same key form one sample, a repeated
extension within a sample is an error. Anything else (URLs other than local paths, compressed tars)
goes through WebDataset's ``gopen`` + ``tarfile`` iterator with the same grouping (the slow, general path).
"""
from __future__ import annotations

import os
import re
from typing import BinaryIO, Iterator

from resim.shards.errors import BAD_MEMBER, ForbiddenMemberError, ShardReadError, split_member_name
from resim.shards.schema import FORBIDDEN_EXTENSIONS
from resim.shards.validate import is_forbidden_ext

BLOCK = 512
_REGULAR = (b"0", b"\0", b"7")            # regular file, old-style regular, contiguous file
_NO_DATA = (b"1", b"2", b"3", b"4", b"5", b"6")  # links, devices, directories, fifos: size field is ignored
# what a member of a sample can be instead of a regular file (directories are left out: writers name them
# "dir/", which is never a sample member)
_NOT_REGULAR = {b"1": "hard link", b"2": "symbolic link", b"3": "character device", b"4": "block device",
                b"6": "FIFO"}
_SKIP_META = re.compile(r"__[^/]*__($|/)")      # WebDataset's skip_meta
_COMPRESSED_MAGIC = (b"\x1f\x8b", b"BZh", b"\xfd7zXZ\x00", b"\x28\xb5\x2f\xfd")
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


class BadMember(str):
    """Why a member is unusable; yielded by :func:`iter_members` in place of its data."""


def local_path(url: str) -> str | None:
    """The filesystem path of ``url`` if it names a local file (a plain path or ``file:``), else None."""
    if url.startswith("file://"):
        return url[len("file://"):]
    if url.startswith("file:"):
        return url[len("file:"):]
    if url == "-" or _SCHEME.match(url):  # pipe:, http:, s3:, gs:, ... -> gopen
        return None
    return url


def _octal(field: bytes, what: str, where: str) -> int:
    if field[:1] and field[0] & 0x80:  # GNU base-256 for sizes >= 8 GiB
        n = int.from_bytes(field[1:], "big")
        return -n if field[0] & 0x40 else n
    s = field.split(b"\0", 1)[0].strip(b" ")
    try:
        return int(s or b"0", 8)
    except ValueError:
        raise ShardReadError(f"{where}: header field {what} is not a number: {field!r}") from None


def _pax_records(data: bytes, where: str) -> dict[str, str]:
    """``"%d %s=%s\\n"`` records of a pax extended header."""
    out, pos = {}, 0
    while pos < len(data) and data[pos:pos + 1] != b"\0":
        sp = data.find(b" ", pos)
        if sp < 0:
            raise ShardReadError(f"{where}: malformed pax header")
        try:
            n = int(data[pos:sp])
        except ValueError:
            raise ShardReadError(f"{where}: malformed pax record length") from None
        rec = data[sp + 1:pos + n - 1]  # without the trailing newline
        if n <= 0 or b"=" not in rec:
            raise ShardReadError(f"{where}: malformed pax record")
        k, v = rec.split(b"=", 1)
        out[k.decode("utf-8", "replace")] = v.decode("utf-8", "surrogateescape")
        pos += n
    return out


class _Source:
    """The byte stream of one tar: ``read`` exactly, ``skip`` by seeking when possible (size-checked)."""

    def __init__(self, f: BinaryIO, url: str, size: int | None):
        self.f, self.url, self.size = f, url, size
        self.pos = 0

    def read(self, n: int, what: str) -> bytes:
        data = self.f.read(n)
        if len(data) != n:
            raise ShardReadError(f"shard {self.url}: truncated: {what} at offset {self.pos} needs {n} bytes, "
                                 f"got {len(data)}")
        self.pos += n
        return data

    def skip(self, n: int, what: str, need: int) -> None:
        """Skip ``n`` bytes of which the first ``need`` must exist (member data; the rest is padding)."""
        if self.size is not None:
            if self.pos + need > self.size:
                raise ShardReadError(f"shard {self.url}: truncated: {what} at offset {self.pos} needs {need} "
                                     f"bytes, the file has {self.size - self.pos} left")
            self.f.seek(n, os.SEEK_CUR)
            self.pos += n
        else:
            self.read(need, what)
            self.f.read(n - need)
            self.pos += n - need


def iter_members(src: _Source, select) -> Iterator[tuple[str, str, bytes | None]]:
    """``(key, ext, data)`` of the regular members in order, for which ``select(name)`` returns
    ``(key, ext, read)`` (None: member ignored, data seeked over); ``data`` is None where ``read`` is
    false (seeked over), a :class:`BadMember` for a selected link or device member. Handles ustar
    prefixes, pax ``path``/``size``/``linkpath`` and GNU long names; stops at the first zero block (the
    end-of-archive marker). EOF before that marker is a truncated shard: a tar cut on a block boundary
    would otherwise end early and look whole, its last sample missing members."""
    long_name: str | None = None
    long_link: str | None = None
    pax: dict[str, str] = {}
    while True:
        where = f"shard {src.url} offset {src.pos}"
        hdr = src.f.read(BLOCK)
        if not hdr:
            # every tar writer (ours, tarfile, GNU tar) ends with zero blocks; their absence means the file was cut
            raise ShardReadError(f"{where}: truncated: the file ends without the tar end-of-archive marker")
        if len(hdr) != BLOCK:
            raise ShardReadError(f"{where}: truncated tar header ({len(hdr)} of {BLOCK} bytes)")
        src.pos += BLOCK
        if hdr.count(0) == BLOCK:
            return  # end-of-archive marker
        stored = _octal(hdr[148:156], "chksum", where)
        unsigned = sum(hdr) - sum(hdr[148:156]) + 256  # the checksum field counts as 8 spaces
        if stored != unsigned:
            high = sum(1 for b in hdr[:148] + hdr[156:] if b > 127)
            signed = unsigned - 256 * high  # some old tars summed signed chars
            if stored != signed:
                raise ShardReadError(f"{where}: not a tar header (checksum {stored} != {unsigned}); "
                                     "corrupt or not a tar")
        typ = hdr[156:157]
        size = _octal(hdr[124:136], "size", where)
        if size < 0:
            raise ShardReadError(f"{where}: negative member size")
        if typ in (b"x", b"g", b"L", b"K"):  # extended headers: their data describes the next member
            data = src.read(size, "extended header")
            src.skip(-size % BLOCK, "padding", 0)
            if typ == b"x":
                pax = _pax_records(data, where)
            elif typ == b"L":
                long_name = data.split(b"\0", 1)[0].decode("utf-8", "surrogateescape")
            elif typ == b"K":
                long_link = data.split(b"\0", 1)[0].decode("utf-8", "surrogateescape")
            continue  # global pax headers ('g') change nothing we use
        if hdr[257:263] == b"ustar\x00" and hdr[345:346] != b"\0":
            name = (hdr[345:500].split(b"\0", 1)[0] + b"/" + hdr[0:100].split(b"\0", 1)[0])
        else:
            name = hdr[0:100].split(b"\0", 1)[0]
        name = name.decode("utf-8", "surrogateescape")
        if long_name is not None:
            name, long_name = long_name, None
        if "path" in pax:
            name = pax["path"]
        if "size" in pax:
            try:
                size = int(pax["size"])
            except ValueError:
                raise ShardReadError(f"{where}: pax size {pax['size']!r} is not a number") from None
        link = pax.get("linkpath") or long_link or hdr[157:257].split(b"\0", 1)[0].decode("utf-8", "surrogateescape")
        pax, long_link = {}, None
        if typ in _NOT_REGULAR:
            sel = select(name)
            if sel is not None:   # a sample member, so the sample is bad, not quietly one member short
                to = f" to {link[:200]!r}" if typ in (b"1", b"2") else ""   # a dataset value: kept short
                yield sel[0], sel[1], BadMember(f"member {name!r} is a {_NOT_REGULAR[typ]}{to}, not a regular file")
            continue
        if typ in _NO_DATA:
            continue
        if typ == b"S":
            raise ShardReadError(f"{where}: member {name!r} is a GNU sparse file (not a shard member type)")
        padded = size + (-size % BLOCK)
        sel = select(name) if typ in _REGULAR else None  # unknown types: tarfile skips their data too
        if sel is None or not sel[2]:
            src.skip(padded, f"data of {name!r}", size)
            if sel is not None:
                yield sel[0], sel[1], None
            continue
        data = src.read(size, f"data of {name!r}")
        if padded != size:
            src.skip(padded - size, "padding", 0)
        yield sel[0], sel[1], data


def _split(name: str) -> tuple[str | None, str | None]:
    if "/" not in name and name.startswith("__") and name.endswith("__"):
        return None, None
    if _SKIP_META.match(name):
        return None, None
    key, ext = split_member_name(name)
    if key is None:
        return None, None
    return key, ext.lower()


def _forbidden(url: str, key: str, name: str) -> ForbiddenMemberError:
    return ForbiddenMemberError(
        f"shard {url}: sample {key!r} carries member '{name}', a code-executing format "
        f"(forbidden: {', '.join(FORBIDDEN_EXTENSIONS)}); refusing this shard")


def _group(members: Iterator[tuple[str, str, bytes | None]], url: str, start: int) -> Iterator[dict]:
    """Members -> samples ``{"__key__", "__url__", ext: bytes}`` from sample ``start`` on; members whose
    data is None (not read) are left out of the sample; the first :class:`BadMember` goes to ``BAD_MEMBER``."""
    cur: dict | None = None
    seen: set = set()
    index = -1  # index of the sample ``cur`` belongs to
    for key, ext, data in members:
        if is_forbidden_ext(ext):
            raise _forbidden(url, key, f"{key}.{ext}")
        if cur is None or key != cur["__key__"]:
            if cur is not None and index >= start:
                yield cur
            cur, seen, index = {"__key__": key, "__url__": url}, set(), index + 1
        if ext in seen:
            raise ShardReadError(f"shard {url}: {key}.{ext}: duplicate file name in tar file ({ext} of {key!r})")
        seen.add(ext)
        if isinstance(data, BadMember):
            cur.setdefault(BAD_MEMBER, str(data))
        elif data is not None:
            cur[ext] = data
    if cur is not None and index >= start:
        yield cur


def open_records(url: str, *, start: int = 0, skip_exts=()) -> Iterator[dict]:
    """Raw samples ``{"__key__", "__url__", ext: bytes}`` of the tar at ``url`` from sample ``start`` on.

    ``skip_exts``: member extensions whose bytes are not needed (left out of the samples; on a local file
    their data is seeked over, not read). Raises :class:`ShardReadError` (a ``ValueError``) or ``OSError``
    on an unreadable shard, :class:`ForbiddenMemberError` on a pickle-like member; never yields a partial
    sample of a truncated tar.
    """
    skip_exts = frozenset(e.lower() for e in skip_exts)
    path = local_path(url)
    if path is not None:
        f = open(path, "rb", buffering=BLOCK * 128)
        try:
            head = f.peek(6)[:6]
            if not any(head.startswith(m) for m in _COMPRESSED_MAGIC):
                src = _Source(f, url, os.fstat(f.fileno()).st_size)
                state = [-1, None]  # sample index and key of the latest member (same count as _group's)

                def select(name: str):
                    key, ext = _split(name)
                    if key is None:
                        return None
                    if key != state[1]:
                        state[0], state[1] = state[0] + 1, key
                    # records before ``start`` (resume), unused and forbidden members: headers only
                    return key, ext, not (state[0] < start or ext in skip_exts or is_forbidden_ext(ext))

                yield from _group(iter_members(src, select), url, start)
                return
        finally:
            f.close()
    yield from _general(url, start, skip_exts)


def count_records(path: str) -> int:
    """Number of samples in the local tar at ``path``, reading headers only (member data seeked over).

    Raises like :func:`open_records` on a corrupt header, a truncated file or a forbidden member, so a
    caller can refuse a shard before yielding any of its samples (``resim.shards.reader.iter_raw_shard``)."""
    with open(path, "rb", buffering=BLOCK * 128) as f:
        src = _Source(f, path, os.fstat(f.fileno()).st_size)

        def select(name: str):
            key, ext = _split(name)
            return None if key is None else (key, ext, False)

        return sum(1 for _ in _group(iter_members(src, select), path, 0))


def _general(url: str, start: int, skip_exts: frozenset) -> Iterator[dict]:
    """Any URL ``gopen`` opens, compressed tars: WebDataset's tar iterator (tarfile) and key grouping."""
    # webdataset imports torch, and shards must stay importable without it: only the training stream needs it
    from webdataset.gopen import gopen
    from webdataset.tariterators import group_by_keys, tar_file_iterator

    stream = gopen(url)
    try:
        files = ({**f, "__url__": url} for f in tar_file_iterator(stream))
        for i, raw in enumerate(group_by_keys(files)):
            if i < start:
                continue
            for ext in list(raw):
                if not ext.startswith("__") and is_forbidden_ext(ext):
                    raise _forbidden(url, raw["__key__"], f"{raw['__key__']}.{ext}")
                if ext in skip_exts:
                    del raw[ext]
            yield raw
    finally:
        stream.close()
