"""The dataset's train / held-out split (resim/shards/split.py): whole episodes on one side, stable when the
dataset grows, topped up per source with hazardous and clean drives in turn, written and read back, and the
errors a user meets (a split file that misses episodes, a malformed one) in one line."""
import json

import pytest

from resim.config import ConfigError
from resim.shards import split
from resim.shards.errors import ShardReadError
from resim.shards.writer import ShardWriter
from tests.support.shards import add_dummy_prompts, make_dummy_sample


def _eps(n, source="carla", hazard=None, prefix="ep"):
    return {f"{prefix}-{source}-{i}": (source, hazard) for i in range(n)}


def test_an_episode_side_does_not_move_when_the_dataset_grows():
    cfg = split.SplitConfig(heldout_fraction=0.25, seed=3)
    small = split.of_episodes(_eps(40), cfg, "test")
    big = split.of_episodes({**_eps(40), **_eps(200, prefix="more")}, cfg, "test")
    assert small.heldout <= big.heldout and small.train <= big.train
    assert 0.15 < len(big.heldout) / 240 < 0.35            # about the fraction, by hash
    assert split.of_episodes(_eps(40), split.SplitConfig(0.25, seed=4), "t").heldout != small.heldout


def test_each_source_is_topped_up_with_hazard_classes_in_turn_and_one_episode_trains():
    eps = {**_eps(3, "carla", True), **_eps(3, "carla", False, prefix="x"), **_eps(2, "opendv"), **_eps(1, "navsim")}
    s = split.of_episodes(eps, split.SplitConfig(heldout_fraction=1e-12, min_heldout_episodes=2), "test")
    carla = [e for e in s.heldout if eps[e][0] == "carla"]
    assert len(carla) == 2 and {eps[e][1] for e in carla} == {True, False}
    assert len([e for e in s.heldout if eps[e][0] == "opendv"]) == 1      # one of the two trains
    assert not [e for e in s.heldout if eps[e][0] == "navsim"]            # a single episode trains
    assert s.topped_up == s.heldout
    s = split.of_episodes(eps, split.SplitConfig(heldout_fraction=0.99, min_heldout_episodes=0), "test")
    assert all(any(eps[e][0] == src for e in s.train) for src in ("carla", "opendv", "navsim"))


@pytest.mark.parametrize("bad", [{"heldout_fraction": 0.0}, {"heldout_fraction": 1.0},
                                 {"min_heldout_episodes": -1}])
def test_config_is_validated(bad):
    with pytest.raises(ConfigError, match="split."):
        split.SplitConfig(**bad)


def _dataset(root, episodes=6):
    add_dummy_prompts(root)
    with ShardWriter(root, "d", max_samples_per_shard=4, config_hash="x") as w:
        for e in range(episodes):
            for k in range(2):
                w.write(make_dummy_sample(source="carla", item_id=f"route-{e}", start_frame=10 * k, seed=e * 10 + k,
                                          hazard=bool(e % 2)))
    w.close()


def test_written_and_read_back_and_every_episode_on_one_side(tmp_path):
    _dataset(tmp_path)
    computed = split.read(tmp_path)                          # no split.json yet: the defaults
    assert computed.origin.startswith("the default split, computed on read") and "resim shards split" in computed.origin
    written = split.write(tmp_path, split.SplitConfig(heldout_fraction=0.3, seed=1, min_heldout_episodes=2))
    back = split.read(tmp_path)
    assert (back.heldout, back.train) == (written.heldout, written.train)
    assert back.heldout.isdisjoint(back.train) and len(back.heldout | back.train) == 6
    assert len(back.heldout) >= 2 and back.origin == str(tmp_path / "split.json")
    assert back.record("heldout")["side"] == "heldout" and back.record("train")["episodes_heldout"] == len(back.heldout)
    with pytest.raises(ShardReadError, match="neither side"):
        back.side("route-99")


def test_a_split_file_that_misses_episodes_or_is_malformed_is_one_line(tmp_path):
    _dataset(tmp_path)
    path = tmp_path / "split.json"
    split.write(tmp_path, split.SplitConfig())
    body = json.loads(path.read_text())
    body["train"] = body["train"][1:]
    path.write_text(json.dumps(body))
    with pytest.raises(ShardReadError, match="grew after its split was written") as e:
        split.read(tmp_path)
    assert "\n" not in str(e.value) and "resim shards split" in str(e.value)
    path.write_text("[1, 2]")
    with pytest.raises(ShardReadError, match="not a split file"):
        split.read(tmp_path)


def test_several_datasets_with_one_episode_on_both_sides_are_refused(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        _dataset(d)
    sa = split.write(a, split.SplitConfig(seed=0))
    sb = split.write(b, split.SplitConfig(seed=5))
    if sa.heldout == sb.heldout:
        pytest.skip("these seeds happen to agree")           # the error needs them to differ
    with pytest.raises(ShardReadError, match="held out in one of"):
        split.read_all([a, b])
    assert split.read_all([a]).heldout == sa.heldout
