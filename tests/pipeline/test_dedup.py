"""Near-duplicate grouping (resim/pipeline/dedup.py): copies across videos are found and one of each group kept;
overlapping windows of one video are never "copies"; other footage is far."""
import numpy as np

from resim.pipeline.dedup import clip_signature, distance_bits, find_duplicates


def _video(seed, t=49, hw=(64, 96)):
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 255, (hw[0] // 8, hw[1] // 8, 3), dtype=np.uint8)
    big = np.kron(base, np.ones((8, 8, 1), np.uint8))
    return np.stack([np.roll(big, i, axis=1) for i in range(t)])


def test_copies_are_grouped_and_the_first_is_kept():
    long = _video(0, t=70)
    a, b = long[:49], _video(1)
    later = clip_signature(long[10:59])                                   # the window 10 frames on: overlapping
    noisy = np.clip(a.astype(int) + np.random.default_rng(2).integers(-6, 7, a.shape), 0, 255).astype(np.uint8)
    sa, sb, sn = clip_signature(a), clip_signature(b), clip_signature(noisy)
    assert len(sa) == 64 and distance_bits(sa, sn) <= 8 and distance_bits(sa, sb) > 64
    rows = [{"key": "v1_f0", "item_id": "v1", "start_frame": 0, "signature": sa},
            {"key": "v2_f0", "item_id": "v2", "start_frame": 0, "signature": sn},        # a re-upload of v1
            {"key": "v1_f10", "item_id": "v1", "start_frame": 10, "signature": later},   # overlapping window
            {"key": "v3_f0", "item_id": "v3", "start_frame": 0, "signature": sb},
            {"key": "v4_f0", "item_id": "v4", "start_frame": 0, "signature": None}]      # a v1 sample: no signature
    dups = find_duplicates(rows, max_bits=16, num_frames=49)
    assert [(d["key"], d["duplicate_of"]) for d in dups] == [("v2_f0", "v1_f0")], dups
    assert distance_bits(sa, later) > 16                                  # 10 frames on is another picture
    # far apart in the same video, the same picture is a copy (a re-used segment)
    rows[2].update(start_frame=60, signature=sa)
    assert {d["key"] for d in find_duplicates(rows, 16, 49)} == {"v1_f10", "v2_f0"}
