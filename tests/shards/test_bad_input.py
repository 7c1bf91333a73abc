"""Damaged datasets and malformed samples: every reader reports the item and the reason, nothing is silently short.

Each case came from a review that found the old behaviour: a tar cut on a block boundary read as a shorter
whole shard, tarfile ended quietly at a corrupt header, a flipped shape byte became a 416-TiB allocation, a
list in meta.json crashed verify, a corrupt index crashed ls/stats with a bare traceback.
"""
import io
import json
import re
import tarfile

import numpy as np
import pytest

from resim.cli import main
from resim.shards import layout, safejson
from resim.shards.confine import UnsafePathError, confined
from resim.shards.npy import NpyError, decode_npy, encode_npy
from resim.shards.reader import ShardReadError, decode_sample, find_sample, iter_raw_shard, iter_samples
from resim.shards.tario import open_records
from tests.support.shards import NotRegular, insert_raw_sample, make_dummy_sample
from resim.shards.validate import sample_problems, meta_problems
from resim.shards.verify import verify

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
    meta = dict(make_dummy_sample()["meta.json"], schema_version=4, ego_speed_mps=3.0)
    probs = meta_problems(meta, "k")
    assert probs[0].startswith("meta.schema_version = 4") and len(probs) == 2


def test_older_samples_without_the_later_fields_are_read_and_a_current_one_needs_them():
    from resim.shards.schema import QUALITY_META

    meta = make_dummy_sample()["meta.json"]
    v2 = {k: v for k, v in meta.items() if k not in QUALITY_META}
    old = {k: v for k, v in v2.items() if k not in ("ego_motion_pct_s", "stopped", "signature")}
    assert meta_problems(dict(old, schema_version=1), meta["key"]) == []
    assert meta_problems(dict(v2, schema_version=2), meta["key"]) == []
    assert any("lacks fields ['ego_motion_pct_s', 'stopped', 'signature', " in p for p in meta_problems(old, meta["key"]))
    assert any(f"lacks fields {list(QUALITY_META)}" in p for p in meta_problems(v2, meta["key"]))
    assert any("not in schema v1" in p for p in meta_problems(dict(meta, schema_version=1), meta["key"]))
    assert any("not in schema v2" in p for p in meta_problems(dict(meta, schema_version=2), meta["key"]))


def test_writer_keeps_shards_within_max_bytes_including_tar_record_padding(tmp_path):
    from resim.shards.writer import ShardWriter

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


# ---- hostile datasets: a bad file next to good ones --------------------------------------------------------------
BOMB = b"[" * 200_000   # json.loads recursed once per level: RecursionError, which no reader treated as bad data


def _files_under(folder):
    return {p for p in folder.rglob("*")} if folder.exists() else set()


def test_confined_refuses_absolute_dotdot_nul_and_escaping_symlinks(tmp_path):
    base = tmp_path / "base"
    (base / "sub").mkdir(parents=True)
    (tmp_path / "outside").mkdir()
    (base / "out-link").symlink_to(tmp_path / "outside")
    (base / "in-link").symlink_to(base / "sub")
    assert confined(base, "sub/x.png", "item") == base / "sub" / "x.png"
    assert confined(base, "in-link/x.png", "item") == base / "in-link" / "x.png"   # a link that stays inside
    for name, reason in [("/etc/passwd", "is an absolute path"), ("../x", "climbs out of"),
                         ("a/../../x", "climbs out of"), ("a\0b", "NUL byte"), ("", "not a file name"),
                         ("out-link/x.png", "leads through a symbolic link"), ("\\\\tmp\\x", "is an absolute path")]:
        with pytest.raises(UnsafePathError, match=reason) as e:
            confined(base, name, "sample 'k': preview file")
        assert str(e.value).startswith("sample 'k': preview file ") and "\n" not in str(e.value)


def test_safe_json_limits_depth_without_recursion_and_counts_only_brackets_outside_strings(tmp_path):
    assert safejson.loads(b'{"a": ["[[[[", {"b": "\\"[{"}]}') == {"a": ["[[[[", {"b": '"[{'}]}
    assert safejson.loads(b'"' + b"[" * 1000 + b'"') == "[" * 1000           # brackets in a string: depth 0
    with pytest.raises(safejson.JSONLimitError, match="nested 200000 levels deep, more than the limit of 64"):
        safejson.loads(BOMB)
    with pytest.raises(safejson.JSONLimitError, match="larger than the limit"):
        safejson.loads(b"[1]" + b" " * 100, max_bytes=50)
    with pytest.raises(safejson.JSONLimitError, match="not a regular file"):
        safejson.load_file("/dev/zero")                                       # never read
    p = tmp_path / "big.json"
    p.write_bytes(b"[" + b"0," * 100 + b"0]")
    with pytest.raises(safejson.JSONLimitError, match="larger than the limit of 64 bytes"):
        safejson.load_file(p, max_bytes=64)


def test_preview_skips_a_sample_whose_key_escapes_the_out_folder(dataset, tmp_path, capsys):
    out = tmp_path / "a" / "b" / "previews"
    out.mkdir(parents=True)
    escape = insert_raw_sample(dataset, SHARD, "../../escaped")            # would write tmp_path/a/escaped.png
    absolute = insert_raw_sample(dataset, SHARD, str(tmp_path / "abs"))    # would write tmp_path/abs.png
    for p in layout.manifest_dir(dataset).glob("*.parquet"):               # preview only this shard's samples
        if p.name != SHARD.replace(".tar", ".parquet"):
            p.unlink()
    before = _files_under(tmp_path) - _files_under(out)
    assert main(["shards", "preview", str(dataset), "--random", "100", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert sorted(err) == sorted([
        f"resim shards preview: skipping sample {escape!r}: preview file '../../escaped.png' climbs out of {out} "
        "with '..'",
        f"resim shards preview: skipping sample {absolute!r}: preview file '{tmp_path / 'abs'}.png' is an absolute "
        f"path; it must name a file inside {out}"]), err
    assert len(list(out.glob("*.png"))) == 4                                 # the good samples of the shard
    assert _files_under(tmp_path) - _files_under(out) == before              # nothing written outside --out
    assert not (tmp_path / "a" / "escaped.png").exists() and not (tmp_path / "abs.png").exists()


def test_manifest_naming_a_shard_outside_the_dataset_is_not_read(dataset, capsys):
    import pyarrow.parquet as pq

    mp = layout.manifest_path(dataset, SHARD)
    t = pq.read_table(mp)
    key = t["key"][0].as_py()
    pq.write_table(t.set_column(t.schema.get_field_index("shard"), "shard",
                                [["/dev/zero"] + t["shard"].to_pylist()[1:]]), mp)
    assert main(["shards", "show", str(dataset), key]) == 1
    assert capsys.readouterr().err.strip() == (f"resim shards show: error: manifest row of sample {key!r}: shard "
                                               f"'/dev/zero' is an absolute path; it must name a file inside "
                                               f"{layout.shards_dir(dataset)}")


def _set_prompt_entry(root, **changes):
    """Change the null prompt's entry of prompts.json (the table is dataset input); returns its id."""
    from resim.shards.prompts import PromptTable

    table = PromptTable(root)
    data = json.loads(table.json_path.read_text())
    pid = next(p for p, e in data["prompts"].items() if e["role"] == "null")
    data["prompts"][pid].update(changes)
    table.json_path.write_text(json.dumps(data))
    return pid


@pytest.mark.parametrize("file,reason", [
    ("/dev/zero", "is an absolute path"),                 # was read until MemoryError
    ("/etc/passwd", "is an absolute path"),               # was opened
    ("../../../../../../../etc/passwd", "climbs out of"),
    ("evil.npy", "leads through a symbolic link"),        # a link inside prompts/ to a file outside
])
def test_prompt_entry_naming_a_file_outside_prompts_is_refused(dataset, capsys, file, reason):
    from resim.shards.prompts import PromptTable, PromptTableError

    if file == "evil.npy":
        (layout.prompts_dir(dataset) / file).symlink_to("/etc/passwd")
    pid = _set_prompt_entry(dataset, file=file)
    with pytest.raises(PromptTableError, match=f"^prompt {pid}: file '{re.escape(file)}' {reason}"):
        PromptTable(dataset).get(pid)
    key = layout.read_index(dataset, SHARD)["keys"][0]
    assert main(["shards", "show", str(dataset), key]) == 1               # attaches the null prompt
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"resim shards show: error: prompt {pid}: file '{file}' {reason}") and "\n" not in err
    assert main(["shards", "verify", "-q", "--no-video", str(dataset)]) == 1
    out = capsys.readouterr().out
    assert f"dataset: prompt {pid}: file '{file}' {reason}" in out, out


def test_prompt_file_size_is_checked_against_the_entry_before_reading(dataset):
    from resim.shards.prompts import PromptTable, PromptTableError

    pid = _set_prompt_entry(dataset, bytes=10**12)                        # a shape of 16 x 32 bf16 cannot be 1 TB
    with pytest.raises(PromptTableError, match=f"prompt {pid}: bytes 1000000000000 does not fit shape"):
        PromptTable(dataset).get(pid)
    pid = _set_prompt_entry(dataset, bytes=1100, shape=[16, 32])          # fits the shape, not the file on disk
    with pytest.raises(PromptTableError, match=f"prompt {pid}: file .* holds 1152 bytes, prompts.json says 1100"):
        PromptTable(dataset).get(pid)


def test_json_bomb_in_a_sample_is_one_bad_sample_for_every_cli(dataset, tmp_path, capsys):
    bomb = insert_raw_sample(dataset, SHARD, "synthetic-bomb-000", {"meta.json": BOMB})   # first in the tar
    good = layout.read_index(dataset, SHARD)["keys"][1]
    assert main(["shards", "verify", "-q", "--no-video", str(dataset)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert [line for line in out if bomb in line] == [
        f"shard {SHARD} key {bomb}: shard {layout.shards_dir(dataset) / SHARD} sample {bomb!r}: member meta.json "
        "cannot be decoded: JSON nested 200000 levels deep, more than the limit of 64"], out
    assert main(["shards", "show", str(dataset), bomb]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("resim shards show: error: ") and "nested 200000 levels deep" in err and "\n" not in err
    assert main(["shards", "show", str(dataset), good, "--json"]) == 0        # the bomb before it is not decoded
    assert json.loads(capsys.readouterr().out)["key"] == good
    assert main(["shards", "preview", str(dataset), bomb, "--out", str(tmp_path) + "/"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"resim shards preview: skipping shard ") and "nested 200000" in err and "\n" not in err
    assert not list(tmp_path.glob("*.png"))
    with pytest.raises(ShardReadError, match="nested 200000 levels deep"):
        list(iter_samples(dataset, attach_prompts=False))


@pytest.mark.parametrize("ext,member,reason", [
    # a link's target is never read: tarfile's extractfile follows a hard link to the other member's bytes, and
    # tarfile/WebDataset drop a symbolic link silently, which left the sample without meta.json (a KeyError later)
    ("meta.json", NotRegular(tarfile.SYMTYPE, "/etc/passwd"),
     "member '{key}.meta.json' is a symbolic link to '/etc/passwd', not a regular file"),
    ("latent.npy", NotRegular(tarfile.LNKTYPE, "{first}.latent.npy"),
     "member '{key}.latent.npy' is a hard link to '{first}.latent.npy', not a regular file"),
    ("frames.mp4", NotRegular(tarfile.CHRTYPE), "member '{key}.frames.mp4' is a character device, not a regular file"),
    ("meta.json", None, "required member meta.json missing"),
])
def test_a_link_device_or_missing_member_is_one_bad_sample(dataset, tmp_path, capsys, ext, member, reason):
    first = layout.read_index(dataset, SHARD)["keys"][0]
    if member is not None:
        member = NotRegular(member.type, member.target.format(first=first))
    key = insert_raw_sample(dataset, SHARD, "synthetic-link-000", {ext: member}, first=False)
    line = f"shard {layout.shards_dir(dataset) / SHARD} sample {key!r}: {reason.format(key=key, first=first)}"
    with pytest.raises(ShardReadError) as e:
        find_sample(dataset, key, attach_prompts=False)
    assert str(e.value) == line
    assert find_sample(dataset, first, attach_prompts=False)["__key__"] == first    # its neighbours still read
    with pytest.raises(ShardReadError, match=re.escape(line)):
        list(iter_samples(dataset, attach_prompts=False))
    assert any(key in str(p) for p in verify(dataset, decode_video=False))
    assert main(["shards", "show", str(dataset), key]) == 1                         # was a KeyError traceback
    assert capsys.readouterr().err.strip() == f"resim shards show: error: {line}"
    for p in layout.manifest_dir(dataset).glob("*.parquet"):                        # preview only this shard's samples
        if p.name != SHARD.replace(".tar", ".parquet"):
            p.unlink()
    out = tmp_path / "previews"
    assert main(["shards", "preview", str(dataset), "--random", "100", "--out", str(out)]) == 1
    assert capsys.readouterr().err.strip() == f"resim shards preview: skipping {line}"
    assert len(list(out.glob("*.png"))) == 4 and not (out / f"{key}.png").exists()  # the good samples still render
