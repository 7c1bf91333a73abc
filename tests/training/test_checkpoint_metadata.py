"""DCP ``.metadata`` is unpickled with an exact allow-list: real metadata loads in both ways Pythons pickle its
memory-format enum (3.11.5+: ``EnumClass(value)``; 3.11.0-3.11.4, e.g. Debian's 3.11.2: ``getattr(EnumClass,
'NAME')``), and a hostile file runs nothing. Fixtures: tests/data/dcp_metadata/ (made by the real DCP; the
by-name file is the same metadata re-pickled in 3.11.2's form, see make_fixtures)."""
import io
import pickle
from pathlib import Path

import pytest
import torch
import torch.distributed.checkpoint as dcp
from torch.distributed.checkpoint.metadata import _MEM_FORMAT_ENCODING, TensorProperties

from resim.train.checkpoint import CheckpointError, _MetadataUnpickler

FIXTURES = Path(__file__).resolve().parents[1] / "data" / "dcp_metadata"


def _real_metadata(tmp_path) -> bytes:
    dcp.save({"w": torch.arange(6.0).reshape(2, 3), "lr": 0.5}, checkpoint_id=str(tmp_path / "ck"))
    return (tmp_path / "ck" / ".metadata").read_bytes()


class _ByNamePickler(pickle.Pickler):
    """Pickles enum members as Python 3.11.0-3.11.4 do: ``getattr(EnumClass, 'NAME')``."""

    def reducer_override(self, obj):
        if isinstance(obj, _MEM_FORMAT_ENCODING):
            return getattr, (type(obj), obj.name)
        return NotImplemented


def _by_name(raw: bytes) -> bytes:
    md = pickle.loads(raw)   # our own file, just written: trusted here
    buf = io.BytesIO()
    _ByNamePickler(buf, protocol=4).dump(md)
    return buf.getvalue()


def _load(raw: bytes):
    return _MetadataUnpickler(io.BytesIO(raw)).load()


def make_fixtures(tmp_path) -> None:
    """Rewrites the checked-in fixtures (run by hand when DCP's metadata format changes)."""
    raw = _real_metadata(tmp_path)
    FIXTURES.mkdir(parents=True, exist_ok=True)
    (FIXTURES / "enum_by_value.metadata").write_bytes(raw)
    (FIXTURES / "enum_by_name.metadata").write_bytes(_by_name(raw))


@pytest.mark.parametrize("name", ["enum_by_value.metadata", "enum_by_name.metadata"])
def test_checked_in_metadata_loads(name):
    md = _load((FIXTURES / name).read_bytes())
    props = md.state_dict_metadata["w"].properties
    assert props.memory_format == torch.contiguous_format and tuple(md.state_dict_metadata["w"].size) == (2, 3)


def test_both_enum_forms_of_fresh_metadata(tmp_path):
    raw = _real_metadata(tmp_path)
    by_name = _by_name(raw)
    assert b"getattr" in by_name   # (raw is in this interpreter's own form: by name on 3.11.0-3.11.4)
    a, b = _load(raw), _load(by_name)
    assert a.state_dict_metadata["w"].properties == b.state_dict_metadata["w"].properties


def _global(module: str, name: str, arg: str) -> bytes:
    """A protocol-4 pickle calling ``module.name(arg)`` through STACK_GLOBAL + REDUCE."""
    def s(x):
        b = x.encode()
        return b"\x8c" + bytes([len(b)]) + b
    return b"\x80\x04" + s(module) + s(name) + b"\x93" + s(arg) + b"\x85R."


@pytest.mark.parametrize("module,name", [
    ("torch.distributed.checkpoint.filesystem", "os.system"),   # dotted name under an allowed module
    ("torch.distributed.checkpoint.metadata", "torch.load"),
    ("os", "system"), ("builtins", "eval"), ("torch", "load"), ("torch", "ops.aten"),
])
def test_hostile_globals_are_refused_and_run_nothing(tmp_path, module, name):
    marker = tmp_path / "pwned"
    with pytest.raises(CheckpointError, match="not allowed"):
        _load(_global(module, name, f"touch {marker}"))
    assert not marker.exists()


class _Reduce:
    def __init__(self, fn, args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


@pytest.mark.parametrize("target,attr", [
    (_MEM_FORMAT_ENCODING, "__subclasses__"),                  # an allowed enum, not a member
    (TensorProperties, "create_from_tensor"),                   # an allowed class that is no enum
])
def test_getattr_only_names_members_of_allowed_enums(target, attr):
    with pytest.raises(CheckpointError, match="getattr"):
        _load(pickle.dumps(_Reduce(getattr, (target, attr)), protocol=4))
    member = _load(pickle.dumps(_Reduce(getattr, (_MEM_FORMAT_ENCODING, "TORCH_CONTIGUOUS_FORMAT")), protocol=4))
    assert member is _MEM_FORMAT_ENCODING.TORCH_CONTIGUOUS_FORMAT


def test_resume_from_a_hostile_checkpoint_is_one_line(world_dataset, tmp_path, capsys):
    """`resim train world --resume` on a run whose checkpoint metadata names os.system: refused in one line
    (exit 5), nothing executed."""
    from resim.cli import main

    run = tmp_path / "run"
    common = ["train", "world", "--preset", "tiny", "--shards", str(world_dataset), "--out", str(run),
              "--set", "trainer.progress_bar=false", "--set", "trainer.tensorboard=false",
              "--set", "trainer.loss_curve_png=false"]
    assert main([*common, "--steps", "1", "--checkpoint-every", "1"]) == 0
    meta = next(run.glob("checkpoints/step_*/.metadata"))
    marker = tmp_path / "pwned"
    meta.write_bytes(_global("torch.distributed.checkpoint.filesystem", "os.system", f"touch {marker}"))
    capsys.readouterr()
    assert main([*common, "--steps", "2", "--resume"]) == 5
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("resim train world: checkpoint error:") and "not allowed" in err[0]
    assert not marker.exists()
