"""The shard stream: typed batches, equal batch counts per rank, exact positions, mixing, bad data."""
import io
import json
import tarfile

import pytest
import torch

from resim.cli import main
from resim.config import ConfigError, from_dict
from tests.support.shards import insert_raw_sample
from resim.train.config import DataConfig
from resim.train.data import Batch, StreamLoader
from resim.train.stream import DataError, shard_mixing

from tests.support.training import navsim_spec, write_world_dataset


def _cfg(root, **kw):
    return from_dict(DataConfig, {"shards": str(root), "batch_size_per_gpu": 2, **kw})


def _keys(loader, epochs=1):
    out = []
    for _ in range(epochs):
        out += [tuple(b.keys) for b in loader]
    return out


def test_batch_is_typed_and_moves(world_dataset):
    b = next(iter(StreamLoader(_cfg(world_dataset), verbose=False)))
    assert isinstance(b, Batch) and len(b) == 2
    assert b.latents.shape == (2, 13, 16, 8, 12) and b.latents.dtype == torch.float16  # as stored
    assert b.text.shape == b.null_text.shape == (2, 16, 64) and b.text.dtype == torch.float32
    from resim.shards.prompts import PromptTable
    table = PromptTable(world_dataset)
    for i, m in enumerate(b.meta):
        torch.testing.assert_close(b.text[i], torch.tensor(table.get(m["prompt_id"], as_float32=True)))
        torch.testing.assert_close(b.null_text[i], torch.tensor(table.get(m["null_prompt_id"], as_float32=True)))
    assert b.trajectory.shape == (2, 8, 3) and b.has_trajectory.all()
    assert b.command.dtype == torch.long and len(b.source) == len(b.keys) == 2
    assert not torch.equal(b.text[0], b.null_text[0])  # command prompt vs the prefix alone
    moved = b.to("cpu")
    assert isinstance(moved, Batch) and moved.keys == b.keys
    assert moved.latents.dtype == torch.float32 and torch.equal(moved.latents, b.latents.float())


def test_equal_batches_per_rank_with_fewer_shards_than_workers(tmp_path):
    root = write_world_dataset(tmp_path / "one", num_samples=3, per_shard=3)  # 1 shard < 2 ranks x 2 workers
    counts = []
    for rank in (0, 1):
        loader = StreamLoader(_cfg(root, num_workers=2, samples_per_epoch=10), rank=rank, world_size=2, verbose=False)
        batches = list(loader)
        counts.append(len(batches))
        assert all(len(b) == 2 for b in batches)
        assert len(batches) == len(loader) == 4  # ceil(10 / (2 x 2 ranks x 2 workers)) x 2 workers
    assert counts[0] == counts[1]


def test_position_round_trip_with_workers(world_dataset):
    cfg = _cfg(world_dataset, num_workers=2, samples_per_epoch=16)
    full = _keys(StreamLoader(cfg, verbose=False), epochs=2)
    for cut in (1, 3, 4):  # inside the epoch (odd and even: the worker rotation) and at its end
        a = StreamLoader(cfg, verbose=False)
        it = iter(a)
        head = [tuple(next(it).keys) for _ in range(cut)]
        state = json.loads(json.dumps(a.state_dict()))
        b = StreamLoader(cfg, verbose=False)
        b.load_state_dict(state)
        tail = _keys(b, epochs=2)
        assert head + tail[: len(full) - cut] == full


def test_source_mixing_weights(tmp_path):
    probs, share = shard_mixing([{"opendv": 10}, {"opendv": 10}, {"navsim": 5}, {"carla": 1}],
                                {"opendv": 1, "navsim": 1, "carla": 2})
    assert share == pytest.approx({"opendv": 0.25, "navsim": 0.25, "carla": 0.5})
    assert probs[0] == probs[1] == pytest.approx(0.125)
    root = write_world_dataset(tmp_path / "mix", num_samples=16, per_shard=4, sources=("opendv", "opendv", "opendv", "carla"))
    loader = StreamLoader(_cfg(root, samples_per_epoch=400, source_weights={"opendv": 1.0, "carla": 1.0},
                               open_shards_per_worker=1), verbose=False)
    src = [s for b in loader for s in b.source]
    assert 0.4 < src.count("carla") / len(src) < 0.6  # 1:1 although carla has 1/4 of the samples
    with pytest.raises(DataError, match="no weight"):
        StreamLoader(_cfg(root, source_weights={"navsim": 1.0}), verbose=False)


def _corrupt(root):
    """Shard 0: one sample's latent replaced by garbage; shard 1: truncated mid-way. Shard 2 stays good."""
    shards = sorted((root / "shards").glob("*.tar"))
    src = shards[0]
    members = []
    with tarfile.open(src) as t:
        for m in t.getmembers():
            members.append((m, t.extractfile(m).read()))
    bad_key = None
    with tarfile.open(src, "w") as t:
        for m, data in members:
            if m.name.endswith("latent.npy") and bad_key is None:
                bad_key = m.name.split(".")[0]
                data = b"\x93NUMPY garbage" + b"\0" * (len(data) - 14)
            m.size = len(data)
            t.addfile(m, io.BytesIO(data))
    raw = shards[1].read_bytes()
    shards[1].write_bytes(raw[: len(raw) // 2 + 100])
    return src.name, shards[1].name, bad_key


def test_corrupt_sample_and_truncated_shard_are_skipped_and_counted(world_dataset, capfd):
    bad_shard, cut_shard, bad_key = _corrupt(world_dataset)
    loader = StreamLoader(_cfg(world_dataset, samples_per_epoch=40), verbose=False)
    keys = [k for b in loader for k in b.keys]
    assert len(keys) == 40 and bad_key not in keys  # full batches, the bad sample never served
    err = capfd.readouterr().err
    assert loader.skipped > 0
    assert f"skipping corrupt sample {bad_key!r}" in err and bad_shard in err
    # the truncated shard is left out before the first batch: its size is not its index's
    assert f"{cut_shard}: " in err and "its index recorded" in err


def test_strict_mode_names_the_shard(world_dataset):
    bad_shard, cut_shard, _ = _corrupt(world_dataset)
    with pytest.raises(DataError) as ei:
        for _ in StreamLoader(_cfg(world_dataset, samples_per_epoch=40, strict=True), verbose=False):
            pass
    assert bad_shard in str(ei.value) or cut_shard in str(ei.value)


def test_every_shard_bad_is_an_error_not_a_hang(tmp_path):
    root = write_world_dataset(tmp_path / "bad", num_samples=4, per_shard=2)
    for p in (root / "shards").glob("*.tar"):       # garbage of the recorded size: found only when read
        p.write_bytes(b"x" * p.stat().st_size)
    with pytest.raises(DataError, match="in a row failed"):
        next(iter(StreamLoader(_cfg(root, max_consecutive_failures=5), verbose=False)))
    for p in (root / "shards").glob("*.tar"):       # garbage of another size: found before the first batch
        p.write_bytes(b"not a tar at all" * 10)
    with pytest.raises(DataError, match="none of the 2 committed shards is usable"):
        next(iter(StreamLoader(_cfg(root, max_consecutive_failures=5), verbose=False)))


def _add_pickle_member(shard):
    """Append a sample carrying a pickle member to ``shard`` (rewritten, still a valid tar)."""
    with tarfile.open(shard) as t:
        members = [(m, t.extractfile(m).read()) for m in t.getmembers()]
    with tarfile.open(shard, "w") as t:
        for m, data in members:
            t.addfile(m, io.BytesIO(data))
        m = tarfile.TarInfo("zzz-evil.state.pickle")
        payload = b"\x80\x04never unpickled"
        m.size = len(payload)
        t.addfile(m, io.BytesIO(payload))


def test_pickle_member_refuses_the_shard(world_dataset, capfd):
    shards = sorted((world_dataset / "shards").glob("*.tar"))
    _add_pickle_member(shards[0])
    loader = StreamLoader(_cfg(world_dataset, samples_per_epoch=24), verbose=False)
    keys = [k for b in loader for k in b.keys]
    assert len(keys) == 24 and "zzz-evil" not in keys
    err = capfd.readouterr().err
    assert "code-executing format" in err and shards[0].name in err and loader.skipped > 0
    with pytest.raises(DataError, match="code-executing"):
        for _ in StreamLoader(_cfg(world_dataset, samples_per_epoch=24, strict=True), verbose=False):
            pass


def test_position_of_another_sample_order_is_refused(world_dataset):
    a = StreamLoader(_cfg(world_dataset), verbose=False)
    next(iter(a))
    state = a.state_dict()
    del state["plan"]["sample_order"]  # a position saved by the loader before the counter-based hash
    with pytest.raises(DataError, match="cannot resume the data position"):
        StreamLoader(_cfg(world_dataset), verbose=False).load_state_dict(state)


# ---------------------------------------------------------------- mixed clip geometries (OpenDV 13 / NAVSIM 3)
def _mixed(root, per_shard=4):
    return write_world_dataset(root, num_samples=16, per_shard=per_shard, sources=("opendv", "navsim"),
                               specs={"navsim": navsim_spec()})


def _shape(b):
    return tuple(b.latents.shape[1:])


def test_mixed_geometries_give_homogeneous_batches_equal_per_rank(tmp_path):
    root = _mixed(tmp_path / "mix", per_shard=8)  # 2 shards < 2 ranks x 2 workers
    counts, shapes = [], set()
    for rank in (0, 1):
        loader = StreamLoader(_cfg(root, batch_size_per_gpu=3, num_workers=2, samples_per_epoch=60),
                              rank=rank, world_size=2, verbose=False)
        batches = list(loader)
        counts.append(len(batches))
        assert len(batches) == len(loader) == 10  # ceil(60 / (3 x 2 ranks x 2 workers)) x 2 workers
        for b in batches:
            assert len(b) == 3 and len({m["latent_shape"][0] for m in b.meta}) == 1  # one geometry per batch
            if b.latents.shape[1] == 13:
                assert set(b.source) == {"opendv"} and b.num_history_latent_frames == 3
                assert b.latent_frame_dt_s == pytest.approx(0.4)
            else:
                assert set(b.source) == {"navsim"} and b.latents.shape[1] == 3
                assert b.num_history_latent_frames == 1 and b.latent_frame_dt_s == pytest.approx(2.0)
            shapes.add(_shape(b))
    assert counts[0] == counts[1]
    assert shapes == {(13, 16, 8, 12), (3, 16, 8, 12)}


def test_mixed_geometries_follow_source_weights(tmp_path):
    root = write_world_dataset(tmp_path / "mix", num_samples=16, per_shard=4,
                               sources=("opendv", "opendv", "opendv", "navsim"), specs={"navsim": navsim_spec()})
    loader = StreamLoader(_cfg(root, samples_per_epoch=400, source_weights={"opendv": 1.0, "navsim": 1.0}),
                          verbose=False)
    src = [s for b in loader for s in b.source]
    assert 0.4 < src.count("navsim") / len(src) < 0.6  # 1:1 in samples, whatever the bucket order


def test_mixed_geometries_position_round_trip(tmp_path):
    root = _mixed(tmp_path / "mix")
    cfg = _cfg(root, batch_size_per_gpu=3, num_workers=2, samples_per_epoch=36)
    full = _keys(StreamLoader(cfg, verbose=False), epochs=2)
    pending_seen = False
    for cut in range(1, 7):
        a = StreamLoader(cfg, verbose=False)
        it = iter(a)
        head = [tuple(next(it).keys) for _ in range(cut)]
        state = json.loads(json.dumps(a.state_dict()))
        pending_seen |= any(c["pending"] for c in state["cursors"].values())
        b = StreamLoader(cfg, verbose=False)
        b.load_state_dict(state)
        tail = _keys(b, epochs=2)
        assert head + tail[: len(full) - cut] == full
    assert pending_seen  # some cut fell where a bucket was partly filled


def test_buffered_sample_that_cannot_be_reread_is_skipped_or_strict(tmp_path, capfd):
    root = _mixed(tmp_path / "mix")
    cfg = _cfg(root, batch_size_per_gpu=3, samples_per_epoch=36)
    a = StreamLoader(cfg, verbose=False)
    it = iter(a)
    state = None
    for _ in range(6):
        next(it)
        if a.state_dict()["cursors"]["0"]["pending"]:
            state = json.loads(json.dumps(a.state_dict()))
            break
    assert state is not None
    shard, rec = state["cursors"]["0"]["pending"][0][0]
    state["cursors"]["0"]["pending"][0][0] = [shard, 10_000]  # past the end: as if the shard had changed
    b = StreamLoader(cfg, verbose=False)
    b.load_state_dict(state)
    before = b.skipped
    assert all(len(x) == 3 for x in b)
    assert b.skipped == before + 1 and "cannot re-read buffered sample" in capfd.readouterr().err
    s = StreamLoader(_cfg(root, batch_size_per_gpu=3, samples_per_epoch=36, strict=True), verbose=False)
    s.load_state_dict(state)
    with pytest.raises(DataError, match="cannot re-read"):
        next(iter(s))


def test_too_many_geometries_is_an_error(tmp_path):
    root = _mixed(tmp_path / "mix")
    with pytest.raises(DataError, match="max_shape_buckets=1"):
        for _ in StreamLoader(_cfg(root, batch_size_per_gpu=3, samples_per_epoch=36, max_shape_buckets=1),
                              verbose=False):
            pass


# ---- hostile datasets: a bad file next to good ones --------------------------------------------------------------
def test_json_bomb_in_meta_is_a_skipped_sample(world_dataset, capfd):
    shard = sorted((world_dataset / "shards").glob("*.tar"))[0].name
    bomb = insert_raw_sample(world_dataset, shard, "synthetic-bomb-000", {"meta.json": b"[" * 200_000})
    loader = StreamLoader(_cfg(world_dataset, samples_per_epoch=24), verbose=False)
    keys = [k for b in loader for k in b.keys]          # was a RecursionError out of the worker: training ended
    assert len(keys) == 24 and bomb not in keys and loader.skipped > 0
    err = capfd.readouterr().err
    assert f"skipping corrupt sample {bomb!r} of shard" in err and "nested 200000 levels deep" in err


@pytest.mark.parametrize("file,reason", [("/dev/zero", "is an absolute path"), ("../../x.npy", "climbs out of")])
def test_prompt_entry_outside_prompts_is_a_data_error_naming_the_prompt(world_dataset, file, reason):
    path = world_dataset / "prompts" / "prompts.json"
    table = json.loads(path.read_text())
    pid = sorted(table["prompts"])[0]
    table["prompts"][pid]["file"] = file
    path.write_text(json.dumps(table))
    with pytest.raises(DataError, match=f"^prompt {pid}: file '{file}' {reason}"):
        StreamLoader(_cfg(world_dataset), verbose=False)   # refused when the loader is built, nothing read


def test_pipe_urls_are_refused_unless_allowed(tmp_path, capsys):
    ran = tmp_path / "ran"
    url = f"pipe:touch {ran}"   # a shell command, reachable from --set
    with pytest.raises(ConfigError, match=r"data.urls 'pipe:touch .*' is a pipe: URL, a shell command; "
                                          r"set data.allow_pipe_urls=true"):
        from_dict(DataConfig, {"urls": ["a.tar", url]})
    with pytest.raises(ConfigError, match="is a pipe: URL"):
        from_dict(DataConfig, {"urls": [" PIPE:touch x"]})   # gopen lower-cases the scheme, strips blanks
    argv = ["train", "world", "--preset", "tiny", "--out", str(tmp_path / "run"), "--print-config",
            "--set", f"data.urls=['{url}']"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("resim train world: config error: ") and "data.urls 'pipe:touch" in err and "\n" not in err
    assert main(argv + ["--set", "data.allow_pipe_urls=true"]) == 0   # the explicit opt-in
    assert url in capsys.readouterr().out
    assert from_dict(DataConfig, {"urls": [url], "allow_pipe_urls": True}).urls == (url,)
    assert not ran.exists()


def test_shuffle_commands_draws_each_clips_command_from_its_key_alone(world_dataset):
    from resim.shards.prompts import PromptTable
    from resim.shards.schema import COMMANDS
    prompts = PromptTable(world_dataset)
    table = prompts.entries()
    emb = {p: torch.tensor(prompts.get(p, as_float32=True)) for p in table}
    prefix = lambda p: table[p]["text"].rsplit(table[p]["command"], 1)[0]
    plain = {k: (m, c) for b in StreamLoader(_cfg(world_dataset), verbose=False)
             for k, m, c in zip(b.keys, b.meta, b.command.tolist())}
    seen = {}
    for b in StreamLoader(_cfg(world_dataset, shuffle_commands=True), verbose=False):
        for i, k in enumerate(b.keys):
            pid = b.meta[i]["prompt_id"]
            assert b.meta[i] == plain[k][0]                                      # the record is kept
            # the text the model sees is a command prompt of the same prefix, and Batch.command names it
            shown = [p for p in table if torch.equal(b.text[i], emb[p])]
            assert len(shown) == 1 and table[shown[0]]["role"] == "command"
            assert table[shown[0]]["command"] == COMMANDS[int(b.command[i])]
            assert prefix(shown[0]) == prefix(pid)
            seen[k] = int(b.command[i])
    recorded = [plain[k][1] for k in seen]
    drawn = [seen[k] for k in seen]
    assert len(set(drawn)) == 3 and drawn != recorded                            # every command, not the recorded ones
    again = {k: int(c) for b in StreamLoader(_cfg(world_dataset, shuffle_commands=True), verbose=False)
             for k, c in zip(b.keys, b.command)}
    assert again == seen                                                         # fixed by the key: any order, any resume
    other = {k: int(c) for b in StreamLoader(_cfg(world_dataset, shuffle_commands=True, seed=1), verbose=False)
             for k, c in zip(b.keys, b.command)}
    assert other != seen


def test_the_held_out_episodes_are_never_streamed(world_dataset):
    """data.split: train (the default) leaves the held-out side of the dataset's split.json out, whole shards and
    single clips alike; all streams every episode; the loader says which side it read."""
    from resim.shards import split

    s = split.write(world_dataset, split.SplitConfig(heldout_fraction=0.3, min_heldout_episodes=2))
    assert len(s.heldout) >= 2

    def items(**kw):
        loader = StreamLoader(_cfg(world_dataset, samples_per_epoch=120, **kw), verbose=False)
        return loader, {m["item_id"] for _ in range(2) for b in loader for m in b.meta}

    loader, seen = items()
    assert seen == set(s.train)                              # every training episode, no held-out one
    assert loader.split["side"] == "train" and loader.split["episodes_heldout"] == len(s.heldout)
    assert loader.split["origin"] == str(world_dataset / "split.json")
    _, seen = items(split="all")
    assert seen == set(s.train) | set(s.heldout)
    with pytest.raises(ConfigError, match="split: 'heldout' is not one of"):
        _cfg(world_dataset, split="heldout")                 # training never streams the held-out side
