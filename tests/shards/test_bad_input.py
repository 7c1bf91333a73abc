"""Damaged datasets and malformed samples: every reader reports the item and the reason, nothing is silently short.

Each case came from a review that found the old behaviour: a tar cut on a block boundary read as a shorter
whole shard, tarfile ended quietly at a corrupt header, a flipped shape byte became a 416-TiB allocation, a
list in meta.json crashed verify, a corrupt index crashed ls/stats with a bare traceback.
"""
import io
import json
import tarfile

import numpy as np
import pytest

from resim.cli import main
from shards import layout
from shards.npy import NpyError, decode_npy, encode_npy
from shards.reader import ShardReadError, decode_sample, iter_raw_shard, iter_samples
from shards.tario import open_records
from shards.testing import make_dummy_sample
from shards.validate import sample_problems, meta_problems
from shards.verify import verify

SHARD = "unitA-00000.tar"


def _member_offsets(path):
    with tarfile.open(path) as t:
        return [(m.name, m.offset) for m in t.getmembers()]


def test_a_tar_cut_on_a_member_boundary_is_an_error_for_every_reader(dataset):
    path = layout.shards_dir(dataset) / SHARD
    offsets = _member_offsets(path)
    # cut at the header of the second sample's second member: what is left is a valid tar prefix, 512-aligned
    second_key = offsets[-1][0].split(".", 1)[0]
    cut = [o for n, o in offsets if n.startswith(second_key)][1]
    assert cut % 512 == 0
    path.write_bytes(path.read_bytes()[:cut])
    with pytest.raises(ShardReadError, match="truncated.*end-of-archive"):
        list(open_records(str(path)))
    with pytest.raises(ShardReadError, match="truncated"):
        list(iter_raw_shard(path))
    with pytest.raises(ShardReadError, match=SHARD):
        list(iter_samples(dataset, attach_prompts=False))
    assert any(SHARD in str(p) and "end-of-archive" in str(p) for p in verify(dataset, decode_video=False))


def test_a_corrupt_header_after_the_first_member_is_not_a_short_shard(dataset):
    path = layout.shards_dir(dataset) / SHARD
    name, off = _member_offsets(path)[-1]   # the last member's header
    data = bytearray(path.read_bytes())
    data[off + 5] ^= 0x20                    # a byte of its name: the header checksum no longer matches
    path.write_bytes(bytes(data))
    with pytest.raises(ShardReadError, match="checksum"):
        list(iter_raw_shard(path))


def test_decode_npy_checks_the_header_against_the_payload_before_allocating():
    good = encode_npy(np.zeros((2, 3), np.float16))
    bad = good.replace(b"(2, 3)", b"(2, 1099511627776)")    # same header length, an absurd shape
    with pytest.raises(NpyError, match="data bytes for shape"):
        decode_npy(bad)
    assert decode_npy(good).flags.writeable


def test_decode_sample_refuses_a_latent_stored_with_another_dtype_than_meta_says():
    s = make_dummy_sample(latent_dtype="float16")
    raw = {"__key__": s["__key__"], "__url__": "x.tar", "meta.json": json.dumps(s["meta.json"]).encode(),
           "latent.npy": encode_npy(s["latent.npy"].view(np.uint16))}   # bfloat16-style bits, meta says float16
    with pytest.raises(ShardReadError, match="stored as uint16 but meta.latent_dtype is 'float16'"):
        decode_sample(raw)
    raw["meta.json"] = b"[1, 2]"
    with pytest.raises(ShardReadError, match="meta.json is a JSON list"):
        decode_sample(raw)


def test_verify_reports_meta_fields_of_the_wrong_type_instead_of_crashing(dataset):
    path = layout.shards_dir(dataset) / SHARD
    with tarfile.open(path) as tin:
        members = [(ti, tin.extractfile(ti).read()) for ti in tin.getmembers()]
    with tarfile.open(path, "w", format=tarfile.USTAR_FORMAT) as tout:
        for i, (ti, data) in enumerate(members):
            if ti.name.endswith("meta.json") and i == 0:
                meta = json.loads(data)
                meta["command"], meta["prompt_id"] = ["Turning left"], {"id": 1}
                data = json.dumps(meta).encode()
                ti.size = len(data)
            tout.addfile(ti, io.BytesIO(data))
    msgs = [str(p) for p in verify(dataset, decode_video=False)]
    assert any("meta.command" in m and "not of type" in m for m in msgs), msgs
    assert any("meta.prompt_id" in m for m in msgs), msgs


def test_validator_treats_none_members_as_missing_and_always_names_a_schema_version_mismatch():
    s = make_dummy_sample()
    s["latent.npy"] = None
    assert any("required members ['latent.npy'] are missing" in p for p in sample_problems(s))
    s = make_dummy_sample(with_dino=False)
    s["dino.npy"] = None
    assert any("optional members ['dino.npy'] are None" in p for p in sample_problems(s))
    meta = dict(make_dummy_sample()["meta.json"], schema_version=2, ego_speed_mps=3.0)
    probs = meta_problems(meta, "k")
    assert probs[0].startswith("meta.schema_version = 2") and len(probs) == 2


def test_writer_keeps_shards_within_max_bytes_including_tar_record_padding(tmp_path):
    from shards.writer import ShardWriter

    samples = [make_dummy_sample(item_id=f"b/{i}", seed=i) for i in range(6)]
    multi = 0
    for limit in range(15000, 45000, 2500):   # tar pads every file to whole 10 KiB records; limits between them
        with ShardWriter(tmp_path / str(limit), "b", max_samples_per_shard=100, max_bytes_per_shard=limit) as w:
            for s in samples:
                w.write(s)
        infos = w.close()
        multi += sum(i.num_samples > 1 for i in infos)
        assert all(i.path.stat().st_size <= limit for i in infos if i.num_samples > 1), (limit, infos)
    assert multi > 0


def test_cli_names_a_corrupt_index_or_manifest_and_exits_1(dataset, capsys):
    ip = layout.index_path(dataset, SHARD)
    ip.write_text('{"shard": "unitA-00000.tar", "num_sampl')
    for cmd in ("ls", "stats"):
        assert main(["shards", cmd, str(dataset)]) == 1
        err = capsys.readouterr().err
        assert f"resim shards {cmd}: error: index {ip}: unreadable" in err
    ip.write_text("[1, 2]")
    assert main(["shards", "verify", "-q", "--no-video", str(dataset)]) == 1
    assert "is a JSON list, not an object" in capsys.readouterr().out
    assert main(["shards", "ls", str(dataset / "no-such-folder")]) == 1
    assert "is not a folder" in capsys.readouterr().err


def test_stats_says_when_manifests_and_indexes_disagree(dataset, capsys):
    layout.manifest_path(dataset, SHARD).unlink()
    assert main(["shards", "stats", str(dataset), "--json"]) == 0
    st = json.loads(capsys.readouterr().out)
    assert st["manifest_mismatch"] == [f"{SHARD}: index says 4 samples, its manifest has 0 rows"]
    assert st["num_samples"] == 6
    # bytes per sample divide the indexes' bytes by the indexes' counts (10 samples), not the manifests'
    assert st["bytes_per_sample"]["in_shards"] == pytest.approx(st["shard_bytes"] / 10)
    assert main(["shards", "stats", str(dataset)]) == 0
    assert "manifest does not match the index" in capsys.readouterr().out
