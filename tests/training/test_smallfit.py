"""The small-model harness shared by Video2Reward and the IDM (resim/train/smallfit.py), tested once here: the split
by episode, the partition into usable and skipped clips, the epoch batches, the trainer run and the batched
prediction. The models' own parts (targets, windows, losses, metrics) are tested in tests/reward and tests/eval."""
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from torch import nn

from resim.train import smallfit
from resim.train.config import OptimConfig
from resim.train.smallfit import ClipError, EpochBatches, frames_to_tensor, heldout_count, split_by_episode


@dataclass
class Clip:
    key: str
    item_id: str
    value: float = 0.0
    flag: bool = False


def clips(n_eps: int, per: int, flag=lambda e, c: False) -> list[Clip]:
    return [Clip(f"e{e}@{c}", f"ep{e}", float(e * per + c), flag(e, c)) for e in range(n_eps) for c in range(per)]


def episodes(cs) -> set[str]:
    return {c.item_id for c in cs}


# ---- split by episode --------------------------------------------------------------------------------------

@pytest.mark.parametrize("n_eps, per, fraction, seed", [(5, 4, 0.25, 3), (20, 3, 0.25, 0), (7, 1, 0.5, 11),
                                                        (2, 6, 0.9, 1)])
def test_split_never_puts_an_episode_on_both_sides(n_eps, per, fraction, seed):
    cs = clips(n_eps, per)
    train, held = split_by_episode(cs, fraction, seed)
    assert not episodes(train) & episodes(held)
    assert episodes(train) | episodes(held) == episodes(cs)
    assert len(episodes(held)) == heldout_count(n_eps, fraction) and len(train) + len(held) == len(cs)
    # each side keeps the input order; whole episodes: every clip of a held-out episode is held out
    assert train == [c for c in cs if c.item_id in episodes(train)]
    assert held == [c for c in cs if c.item_id in episodes(held)]


def test_split_is_seeded_and_independent_of_input_order():
    cs = clips(20, 4)
    _, held = split_by_episode(cs, 0.25, seed=3)
    assert split_by_episode(cs, 0.25, seed=3)[1] == held
    assert episodes(split_by_episode(list(reversed(cs)), 0.25, seed=3)[1]) == episodes(held)
    assert episodes(split_by_episode(cs, 0.25, seed=4)[1]) != episodes(held)


def test_heldout_count_rounds_half_up_and_keeps_one_episode_for_training():
    assert [heldout_count(n, 0.25) for n in (2, 4, 5, 6, 8, 10)] == [1, 1, 1, 2, 2, 3]   # 1.5 -> 2, 2.5 -> 3
    assert heldout_count(4, 0.01) == 1                  # at least one
    assert heldout_count(4, 0.25, min_heldout=2) == 2
    assert heldout_count(4, 0.25, min_heldout=9) == 3   # one always trains
    assert heldout_count(3, 0.99) == 2


def test_split_guarantees_a_minimum_of_heldout_episodes():
    cs = clips(4, 3)
    assert len(episodes(split_by_episode(cs, 0.25)[1])) == 1
    train, held = split_by_episode(cs, 0.25, min_heldout=2)
    assert len(episodes(held)) == 2 and len(episodes(train)) == 2
    assert len(episodes(split_by_episode(cs, 0.25, min_heldout=9)[0])) == 1


def test_split_of_one_episode_is_refused():
    with pytest.raises(ValueError, match=r"4 clips from 1 episode\(s\): a split by episode needs at least 2"):
        split_by_episode(clips(1, 4), 0.25)


def test_stratified_split_holds_out_from_each_stratum_of_two_or_more_episodes():
    # episode e is positive when any of its clips is: here its last clip, for even e
    cs = clips(10, 3, flag=lambda e, c: e % 2 == 0 and c == 2)
    train, held = split_by_episode(cs, 0.25, seed=5, stratum=lambda c: c.flag)
    assert not episodes(train) & episodes(held)
    pos = {f"ep{e}" for e in range(0, 10, 2)}
    assert len(episodes(held) & pos) == 1 and len(episodes(held) - pos) == 1   # round(0.25 * 5) of each
    # a stratum of one episode is held out from not at all; the other still is
    one = [c for c in cs if c.item_id in ("ep0", "ep1", "ep3", "ep5")]
    train, held = split_by_episode(one, 0.5, seed=0, stratum=lambda c: c.flag)
    assert "ep0" in episodes(train) and len(episodes(held)) == 2 and episodes(held) < {"ep1", "ep3", "ep5"}
    # nothing to hold out: the caller decides (no error here)
    assert split_by_episode(clips(2, 2, flag=lambda e, c: e == 0), 0.5, stratum=lambda c: c.flag)[1] == []


# ---- usable clips, frames ----------------------------------------------------------------------------------

def test_usable_names_the_skipped_clips_and_their_reasons_in_order():
    cs = clips(3, 2)

    def check(c):
        if c.value % 2:
            raise ClipError(f"odd value {c.value:g}")
    ok, skipped = smallfit.usable(cs, check)
    assert ok == cs[0::2]
    assert skipped == [{"key": c.key, "reason": f"odd value {c.value:g}"} for c in cs[1::2]]
    with pytest.raises(KeyError):   # other errors are not bad input: they propagate
        smallfit.usable(cs, lambda c: {}[c.key])


def test_frames_to_tensor():
    f = np.random.default_rng(0).integers(0, 256, (3, 4, 5, 3), dtype=np.uint8)
    t = frames_to_tensor(f[:, :, ::-1])       # a non-contiguous view (a mirrored clip)
    assert t.shape == (3, 3, 4, 5) and t.dtype == torch.float32
    assert torch.equal(t, torch.from_numpy(f[:, :, ::-1].copy()).permute(0, 3, 1, 2).float() / 255.0)
    with pytest.raises(ClipError, match=r"uint8 RGB, got \(3, 4, 5, 3\) float32"):
        frames_to_tensor(f.astype(np.float32))


# ---- epoch batches -----------------------------------------------------------------------------------------

def test_epoch_batches_shuffle_each_epoch_with_its_seed_and_cover_every_clip_once():
    cs = clips(5, 2)
    data = EpochBatches(cs, 3, seed=7, collate=lambda chunk: [c.key for c in chunk])
    assert len(data) == 4
    epochs = [[k for b in data for k in b] for _ in range(3)]
    assert [len(b) for b in EpochBatches(cs, 3, 7, lambda chunk: chunk)] == [3, 3, 3, 1]
    for e, keys in enumerate(epochs):
        assert keys == [cs[j].key for j in np.random.default_rng(7 * 1000 + e).permutation(len(cs))]
    assert epochs[0] != epochs[1] and sorted(epochs[0]) == sorted(c.key for c in cs)
    again = EpochBatches(cs, 3, seed=7, collate=lambda chunk: [c.key for c in chunk])
    assert [k for b in again for k in b] == epochs[0]   # a fresh object starts at epoch 0 again


def test_epoch_batches_pass_each_clip_its_own_draw_and_report_epoch_ends():
    cs = clips(4, 2)
    ends = []
    data = EpochBatches(cs, 3, seed=2, collate=lambda chunk, d: list(zip([c.key for c in chunk], d)),
                        augment=lambda rng, n: rng.random(n), on_epoch_end=ends.append)
    got = []
    for e in range(2):
        got.append([p for b in data for p in b])
        assert ends == list(range(1, e + 2))
    rng = np.random.default_rng(2 * 1000 + 1)
    order = rng.permutation(len(cs))
    assert got[1] == list(zip([cs[j].key for j in order], rng.random(len(cs))))


# ---- prediction and training -------------------------------------------------------------------------------

class Affine(nn.Module):
    """y = w * x + b on a clip's value; dropout shows whether predict runs in eval mode."""

    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(1, 1)
        self.drop = nn.Dropout(0.9)

    def forward(self, x):
        return self.drop(self.lin(x[:, None]))[:, 0]

    def loss(self, batch):
        err = self(batch["x"]) - batch["y"]
        return (err ** 2).mean(), {"mae": err.abs().mean()}


def collate(chunk):
    x = torch.tensor([c.value / 20 for c in chunk], dtype=torch.float32)
    return {"x": x, "y": 3 * x - 1, "keys": [c.key for c in chunk]}


def test_predict_keeps_input_order_across_batches_in_eval_mode():
    torch.manual_seed(0)
    m = Affine().train()
    cs = clips(10, 7)[::-1]   # 70 clips: batches of 32, 32, 6
    pred = smallfit.predict(m, cs, collate, lambda mod, b: mod(b["x"]), batch_size=32)
    assert not m.training
    with torch.no_grad():
        expect = m.lin.weight.item() * np.array([c.value / 20 for c in cs], np.float32) + m.lin.bias.item()
    np.testing.assert_allclose(pred, expect, rtol=1e-6)
    assert smallfit.predict(m, [], collate, lambda mod, b: mod(b["x"]), empty_shape=(8, 3)).shape == (0, 8, 3)


def _fit(tmp_path, name):
    torch.manual_seed(0)
    m = Affine()
    m.drop.p = 0.0
    data = EpochBatches(clips(4, 5), 6, seed=1, collate=collate)
    cfg = lambda steps: smallfit.run_config("toy", {}, steps=steps, batch_size=6, seed=1,   # noqa: E731
                                            optim=OptimConfig(lr=0.05, weight_decay=0.0), save_final_weights=False,
                                            preset="toy", reference={})
    return m, smallfit.fit(m, data, 3, cfg, tmp_path / name)


def test_fit_runs_the_trainer_for_whole_epochs_and_is_reproducible(tmp_path):
    m, res = _fit(tmp_path, "a")
    assert res["steps"] == 3 * 4 and res["final_step"] == 12 and not m.training
    assert [r["step"] for r in res["history"]] == list(range(1, 13))
    assert res["history"] == smallfit.read_history(tmp_path / "a") and "mae" in res["history"][0]
    assert res["history"][-1]["loss"] < res["history"][0]["loss"]
    assert np.isfinite(res["samples_per_s"]) and res["samples_per_s"] > 0
    assert (tmp_path / "a" / "config.yaml").is_file()
    m2, res2 = _fit(tmp_path, "b")
    assert [r["loss"] for r in res2["history"]] == [r["loss"] for r in res["history"]]
    assert all(torch.equal(a, b) for a, b in zip(m.state_dict().values(), m2.state_dict().values()))
