"""The lean tar reader of training streams (resim/shards/tario.py) against WebDataset's tarfile-based grouping,
and the zero-copy npy decoder."""
import gzip
import io
import tarfile

import numpy as np
import pytest

from resim.shards.npy import NpyError, decode_npy, decode_npy_view, encode_npy
from resim.shards.reader import ForbiddenMemberError, ShardReadError
from resim.shards.tario import _general, open_records


def _tar(path, members, fmt=tarfile.USTAR_FORMAT, dirs=()):
    with tarfile.open(path, "w", format=fmt) as t:
        for d in dirs:
            ti = tarfile.TarInfo(d)
            ti.type = tarfile.DIRTYPE
            t.addfile(ti)
        for name, data in members:
            ti = tarfile.TarInfo(name)
            ti.size = len(data)
            t.addfile(ti, io.BytesIO(data))
    return str(path)


def _members(n=5, prefix=""):
    out = []
    for i in range(n):
        key = f"{prefix}s{i:03d}"
        out += [(f"{key}.meta.json", b'{"i": %d}' % i), (f"{key}.latent.npy", encode_npy(np.full((3, i + 1), i, np.float16))),
                (f"{key}.frames.mp4", bytes(range(256)) * (i + 1)), (f"{key}.TRAJ.npy", encode_npy(np.zeros((8, 3))))]
    return out


@pytest.mark.parametrize("fmt", [tarfile.USTAR_FORMAT, tarfile.GNU_FORMAT, tarfile.PAX_FORMAT])
def test_same_samples_as_webdataset(tmp_path, fmt):
    long = "d" * 120 + "/"  # > 100 chars: ustar prefix field, GNU long name or pax path
    members = _members(prefix=long) + [("__info__", b"{}")] + _members(3, prefix="x/")
    path = _tar(tmp_path / "a.tar", members, fmt, dirs=("x",))
    want = list(_general(path, 0, frozenset()))
    assert len(want) == 8 and want[0]["__key__"] == long + "s000" and "traj.npy" in want[0]  # ext lower-cased
    assert list(open_records(path)) == want
    assert list(open_records("file://" + path)) == [{**w, "__url__": "file://" + path} for w in want]
    for start in (1, 4, 8, 9):
        assert list(open_records(path, start=start)) == want[start:]
    got = list(open_records(path, skip_exts=("frames.mp4",)))
    assert got == [{k: v for k, v in w.items() if k != "frames.mp4"} for w in want]


def test_compressed_tar_goes_through_the_general_reader(tmp_path):
    path = _tar(tmp_path / "a.tar", _members())
    gz = tmp_path / "a.tar.gz"
    gz.write_bytes(gzip.compress(open(path, "rb").read()))
    assert list(open_records(str(gz), start=2)) == [{**r, "__url__": str(gz)} for r in open_records(path, start=2)]


def test_truncated_shard_is_an_error_also_where_data_is_skipped(tmp_path):
    path = _tar(tmp_path / "a.tar", _members())
    raw = open(path, "rb").read()
    cut = tmp_path / "cut.tar"
    cut.write_bytes(raw[: len(raw) // 2 + 100])  # not on a block boundary
    with pytest.raises(ShardReadError, match="truncated"):
        list(open_records(str(cut)))
    with pytest.raises(ShardReadError, match="truncated"):  # seeking over records on resume still checks
        list(open_records(str(cut), start=5))
    with pytest.raises(ShardReadError, match="truncated"):  # and over skipped members
        list(open_records(str(cut), skip_exts=("frames.mp4", "traj.npy")))


def test_corrupt_header_is_an_error_not_a_short_shard(tmp_path):
    path = _tar(tmp_path / "a.tar", _members())
    raw = bytearray(open(path, "rb").read())
    first = list(open_records(path))[0]
    off = 512 * (4 + sum(-(-len(first[e]) // 512) for e in ("meta.json", "latent.npy", "frames.mp4", "traj.npy")))
    raw[off + 10] ^= 0xFF  # the name field of the 2nd sample's first header
    bad = tmp_path / "bad.tar"
    bad.write_bytes(bytes(raw))
    assert len(list(_general(str(bad), 0, frozenset()))) == 1  # tarfile ends quietly at the bad header
    with pytest.raises(ShardReadError, match="checksum"):
        list(open_records(str(bad)))
    (tmp_path / "junk.tar").write_bytes(b"not a tar at all" * 10)
    with pytest.raises(ShardReadError):
        list(open_records(str(tmp_path / "junk.tar")))


def test_forbidden_member_refused_from_its_header(tmp_path):
    members = _members(2) + [("s002.meta.json", b"{}"), ("s002.data.PICKLE", b"\x80\x04 never read")]
    path = _tar(tmp_path / "a.tar", members)
    it = open_records(path)
    assert next(it)["__key__"] == "s000"
    with pytest.raises(ForbiddenMemberError, match="s002.data.pickle"):
        list(it)
    with pytest.raises(ForbiddenMemberError):
        list(open_records(path, start=3))  # also among records seeked over


def test_duplicate_member_is_an_error(tmp_path):
    path = _tar(tmp_path / "a.tar", _members(1) + [("s000.meta.json", b"{}")])
    with pytest.raises(ShardReadError, match="duplicate"):
        list(open_records(path))


@pytest.mark.parametrize("arr", [np.arange(24, dtype=np.float16).reshape(2, 3, 4), np.zeros((0, 5), np.float32),
                                 np.asfortranarray(np.arange(6.0).reshape(2, 3)), np.array(7, np.int64),
                                 np.arange(5, dtype=">i4"), np.array([True, False])])
def test_npy_view_equals_np_load(arr):
    buf = io.BytesIO()
    np.save(buf, arr)
    data = buf.getvalue()
    v = decode_npy_view(data)
    ref = decode_npy(data)
    assert v.dtype == ref.dtype and v.shape == ref.shape and np.array_equal(v, ref)
    assert not v.flags.writeable  # a view of the (immutable) member bytes
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, version=(2, 0))
    assert np.array_equal(decode_npy_view(buf.getvalue()), arr)


def test_npy_view_refuses_pickles_and_bad_payloads():
    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(NpyError, match="pickle"):
        decode_npy_view(buf.getvalue())
    good = encode_npy(np.arange(4, dtype=np.int32))
    for bad in (b"", b"\x93NUMPY", good[:-1], good + b"\0", b"\x93NUMPY\x09\x00" + good[8:],
                good.replace(b"'descr'", b"'descx'")):
        with pytest.raises(NpyError):
            decode_npy_view(bad)
