import io
import os
import pickle

import numpy as np
import pytest

from resim.pipeline.sources.episode import SourceError
from resim.pipeline.sources.safe_pickle import load_restricted, loads_restricted


@pytest.mark.parametrize("protocol", [3, 4, 5])
def test_numpy_and_builtins_round_trip(protocol):
    data = {"a": np.arange(6.0).reshape(2, 3), "s": np.array(["x", "yy"]), "o": np.array([1, "a"], dtype=object),
            "f": np.float64(2.5), "i": np.int64(3), "l": [1, 2.0, None, True, "t", b"b"], "set": {1, 2},
            "f32": np.ones(3, np.float32)[::2]}
    out = loads_restricted(pickle.dumps(data, protocol=protocol))
    assert np.array_equal(out["a"], data["a"]) and out["a"].dtype == np.float64
    assert out["s"].tolist() == ["x", "yy"] and out["o"].tolist() == [1, "a"]
    assert out["f"] == 2.5 and out["i"] == 3 and out["l"] == data["l"] and out["set"] == {1, 2}


class Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


class Plain:
    pass


@pytest.mark.parametrize("obj,name", [(Evil(), "system"), (Plain(), "Plain"), (pickle.loads, "loads")])
def test_refuses_any_other_class_and_names_it(tmp_path, obj, name):
    p = tmp_path / "log.pkl"
    p.write_bytes(pickle.dumps([{"token": "t", "x": obj}]))
    with pytest.raises(SourceError) as ei:
        load_restricted(p)
    assert ei.value.item == str(p) and name in ei.value.reason and "refuses" in ei.value.reason


def test_protocol2_numpy_is_refused_because_it_needs_codecs(tmp_path):
    with pytest.raises(SourceError, match="_codecs.encode"):
        loads_restricted(pickle.dumps(np.arange(3), protocol=2), "p2")


def test_corrupt_and_missing(tmp_path):
    with pytest.raises(SourceError, match="corrupt pickle"):
        loads_restricted(pickle.dumps([1, 2, 3])[:-3], "trunc")
    with pytest.raises(SourceError, match="cannot read"):
        load_restricted(tmp_path / "nope.pkl")


def test_never_calls_pickle_load(monkeypatch):
    # belt and braces: the module must not fall back to pickle.load / pickle.loads
    monkeypatch.setattr(pickle, "load", lambda *a, **k: pytest.fail("pickle.load called"))
    monkeypatch.setattr(pickle, "loads", lambda *a, **k: pytest.fail("pickle.loads called"))
    assert loads_restricted(b"\x80\x04\x95\x05\x00\x00\x00\x00\x00\x00\x00]\x94K\x01a.") == [1]
    assert io  # keep import


class _Calls:
    def __init__(self, fn, args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


@pytest.mark.parametrize("fn,args", [(bytearray, (2 * 10**9,)), (np.ndarray, ((10**5, 10**5), "f8"))])
def test_a_tiny_pickle_cannot_allocate_gigabytes(fn, args):
    """A 37-byte pickle calling bytearray(2e9) used to allocate 1.9 GB; allowed callables are now bounded by
    the file's size (real logs carry their array data in the file)."""
    data = pickle.dumps([{"token": "t", "x": _Calls(fn, args)}], protocol=4)
    assert len(data) < 200
    with pytest.raises(SourceError, match="allocate .* bytes"):
        loads_restricted(data, "bomb")
    small = loads_restricted(pickle.dumps(_Calls(fn, (16,) if fn is bytearray else ((4, 4), "f8"))), "ok")
    assert len(small) in (16, 4)
