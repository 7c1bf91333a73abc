"""verify catches truncation, flipped bytes, missing samples, wrong shapes, broken prompt references."""
import io
import json
import tarfile

import numpy as np

from resim.shards import layout
from resim.shards.fsio import sha256_file
from resim.shards.manifest import read_indexes
from resim.shards.npy import decode_npy, encode_npy
from resim.shards.verify import verify

SHARD = "unitA-00001.tar"


def _rewrite(root, shard, fn):
    """Rebuild a shard applying fn(name, bytes) -> bytes | None, then make the index's sha/size match
    (a writer bug that slipped past validation, not disk corruption)."""
    path = layout.shards_dir(root) / shard
    with tarfile.open(path) as tin:
        members = [(ti, tin.extractfile(ti).read()) for ti in tin.getmembers()]
    with tarfile.open(path, "w", format=tarfile.USTAR_FORMAT) as tout:
        for ti, data in members:
            data = fn(ti.name, data)
            if data is not None:
                ti.size = len(data)
                tout.addfile(ti, io.BytesIO(data))
    ip = layout.index_path(root, shard)
    idx = json.loads(ip.read_text())
    idx["sha256"], idx["bytes"] = sha256_file(path)
    ip.write_text(json.dumps(idx))


def _msgs(root):
    return [str(p) for p in verify(root)]


def test_clean_dataset_verifies(dataset):
    assert verify(dataset) == []


def test_truncated_shard(dataset):
    path = layout.shards_dir(dataset) / SHARD
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    msgs = _msgs(dataset)
    assert any(m.startswith(f"shard {SHARD}") and "truncated" in m for m in msgs), msgs
    assert any(f"shard {SHARD}" in m and "sha256" in m for m in msgs)


def test_flipped_byte(dataset):
    path = layout.shards_dir(dataset) / SHARD
    data = bytearray(path.read_bytes())
    data[3000] ^= 0x01
    path.write_bytes(bytes(data))
    msgs = _msgs(dataset)
    assert any(f"shard {SHARD}" in m and "sha256" in m and "corrupted" in m for m in msgs), msgs


def test_missing_sample(dataset):
    key = read_indexes(dataset)[1]["keys"][2]
    _rewrite(dataset, SHARD, lambda name, data: None if name.startswith(key + ".") else data)
    msgs = _msgs(dataset)
    assert f"shard {SHARD}: holds 3 samples, index says 4" in msgs, msgs
    assert f"shard {SHARD} key {key}: listed in the index but missing from the shard" in msgs


def test_wrong_shape(dataset):
    key = read_indexes(dataset)[1]["keys"][0]

    def cut(name, data):
        if name == f"{key}.latent.npy":
            return encode_npy(decode_npy(data)[:, :, :2])
        return data

    _rewrite(dataset, SHARD, cut)
    msgs = _msgs(dataset)
    assert len(msgs) == 1 and msgs[0].startswith(f"shard {SHARD} key {key}: latent.npy shape"), msgs


def test_wrong_video_length_and_prompt_reference(dataset):
    from tests.support.shards import dummy_frames
    from resim.shards.video import encode_mp4

    keys = read_indexes(dataset)[1]["keys"]

    def edit(name, data):
        if name == f"{keys[0]}.frames.mp4":
            return encode_mp4(dummy_frames(10, 32, 48), 10.0)
        if name == f"{keys[1]}.meta.json":
            meta = json.loads(data)
            meta["prompt_id"] = "f" * 64
            return json.dumps(meta).encode()
        return data

    _rewrite(dataset, SHARD, edit)
    msgs = _msgs(dataset)
    assert f"shard {SHARD} key {keys[0]}: frames.mp4 has 10 frames, meta.num_frames = 49" in msgs, msgs
    assert any(m.startswith(f"shard {SHARD} key {keys[1]}: meta.prompt_id ffff") and "does not resolve" in m
               for m in msgs), msgs


def test_prompt_file_corrupted_and_index_without_shard(dataset):
    npy = sorted((dataset / "prompts").glob("*.npy"))[0]
    arr = decode_npy(npy.read_bytes())
    npy.write_bytes(encode_npy(np.zeros_like(arr)))
    (layout.shards_dir(dataset) / "unitA-00002.tar").unlink()
    msgs = _msgs(dataset)
    assert any(npy.stem in m and "sha256" in m for m in msgs), msgs
    assert any(m.startswith("shard unitA-00002.tar") and "missing" in m for m in msgs)


def _regroup(root, shard, order):
    """Rebuild a shard with its samples in ``order(keys) -> keys`` (may repeat a key), and make the index's
    sha/size match (a writer bug, not disk corruption). Returns the new key order."""
    path = layout.shards_dir(root) / shard
    with tarfile.open(path) as tin:
        members = [(ti, tin.extractfile(ti).read()) for ti in tin.getmembers()]
    by_key: dict = {}
    for ti, data in members:
        by_key.setdefault(ti.name.split(".", 1)[0], []).append((ti, data))
    keys = order(list(by_key))
    with tarfile.open(path, "w", format=tarfile.USTAR_FORMAT) as tout:
        for k in keys:
            for ti, data in by_key[k]:
                tout.addfile(ti, io.BytesIO(data))
    ip = layout.index_path(root, shard)
    idx = json.loads(ip.read_text())
    idx["sha256"], idx["bytes"] = sha256_file(path)
    ip.write_text(json.dumps(idx))
    return keys


def _edit_index(root, shard, fn):
    ip = layout.index_path(root, shard)
    idx = json.loads(ip.read_text())
    fn(idx)
    ip.write_text(json.dumps(idx))


def test_index_keys_out_of_tar_order(dataset):
    keys = read_indexes(dataset)[1]["keys"]
    _edit_index(dataset, SHARD, lambda idx: idx.update(keys=[keys[0], keys[2], keys[1], keys[3]]))
    msgs = _msgs(dataset)
    assert len(msgs) == 1 and msgs[0].startswith(f"shard {SHARD} key {keys[1]}: out of order: sample 1 of the tar, "
                                                 f"but position 2 in the index"), msgs


def test_tar_samples_out_of_index_order(dataset):
    keys = read_indexes(dataset)[1]["keys"]
    _regroup(dataset, SHARD, lambda ks: [ks[3], *ks[:3]])
    msgs = _msgs(dataset)
    assert len(msgs) == 1 and msgs[0].startswith(f"shard {SHARD} key {keys[3]}: out of order: sample 0 of the tar, "
                                                 f"but position 3 in the index"), msgs


def test_duplicate_keys_in_tar_and_index(dataset):
    keys = read_indexes(dataset)[1]["keys"]
    _regroup(dataset, SHARD, lambda ks: [*ks[:3], ks[0]])     # the last sample replaced by a copy of the first
    _edit_index(dataset, SHARD, lambda idx: idx.update(keys=[*keys[:3], keys[0]]))
    msgs = _msgs(dataset)
    assert f"shard {SHARD} key {keys[0]}: duplicate key: a second sample with this key in the shard " \
           "(keys must be unique)" in msgs, msgs
    assert f"shard {SHARD} key {keys[0]}: listed 2 times in the index (keys must be unique)" in msgs, msgs
    assert not any("also in shard" in m for m in msgs), msgs


def test_duplicate_key_in_index_only(dataset):
    keys = read_indexes(dataset)[1]["keys"]
    _edit_index(dataset, SHARD, lambda idx: idx.update(keys=[keys[0], *keys[:3], keys[3]]))
    msgs = _msgs(dataset)
    assert f"shard {SHARD} key {keys[0]}: listed 2 times in the index (keys must be unique)" in msgs, msgs
    assert f"shard {SHARD}: index lists 5 keys but num_samples is 4" in msgs, msgs
    assert not any("out of order" in m for m in msgs), msgs


def test_orphan_manifest_is_reported(dataset):
    layout.manifest_path(dataset, SHARD).rename(layout.manifest_path(dataset, "unitA-00009.tar"))
    msgs = _msgs(dataset)
    assert "shard unitA-00009.tar: manifest unitA-00009.parquet has neither an index nor a shard (left by an " \
           "interrupted writer; rerun that work unit, or delete it)" in msgs, msgs
