import numpy as np
import pytest

from resim.train.tasks.reward.data import ClipError, collate, window_indices


def test_window_indices(tiny_cfg):
    # 4 frames every 2 -> span 7
    np.testing.assert_array_equal(window_indices(10, tiny_cfg, "end"), [3, 5, 7, 9])
    np.testing.assert_array_equal(window_indices(10, tiny_cfg, "start"), [0, 2, 4, 6])
    with pytest.raises(ClipError, match="6 frames, the model's window needs 7"):
        window_indices(6, tiny_cfg)


def test_collate_video_shapes(tiny_cfg, toy):
    b = collate(toy[:3], tiny_cfg, use_features=False)
    assert b["video"].shape == (3, 4, 3, 32, 48) and b["video"].dtype.is_floating_point
    assert 0.0 <= float(b["video"].min()) and float(b["video"].max()) <= 1.0
    assert b["infraction_score"].shape == (3,)
    with pytest.raises(ClipError, match="no stored features"):
        collate(toy[:1], tiny_cfg, use_features=True)


def test_clips_from_episode_record():
    from resim.pipeline.sources.episode import Episode, Outcome, SourceError

    from resim.train.tasks.reward.data import clips_from_episode
    from tests.support.reward_toy import toy_episode_frames

    frames = toy_episode_frames(0.3, 30, 16, 24, np.random.default_rng(0))

    def loader(start, stop, size_hw):
        for i in range(start, stop):
            if i == 25 and bad:
                raise SourceError("carla/r1", "frame 25: unreadable jpeg")
            yield frames[i]

    bad = False
    ep = Episode(source="carla", item_id="carla/r1", fps_hz=10.0, num_frames=30, frame_size_hw=(16, 24),
                 outcome=Outcome(hazard=True, infraction_score=0.3), _loader=loader)
    clips = clips_from_episode(ep, clip_frames=12, stride_frames=8)
    assert [c.key for c in clips] == ["carla/r1@0", "carla/r1@8", "carla/r1@16"]
    assert all(c.infraction_score == 0.3 and c.hazard and c.item_id == "carla/r1" for c in clips)
    np.testing.assert_array_equal(clips[1].frames, frames[8:20])
    assert clips_from_episode(ep.replace(outcome=None), 12, 8) == []
    bad = True
    with pytest.raises(SourceError):
        clips_from_episode(ep, 12, 8)


def test_clips_from_short_episode_hold_last():
    """An episode shorter than a clip (ended early after a crash) gives no clip, or one with its last frame held."""
    from resim.pipeline.sources.episode import Episode, Outcome

    from resim.train.tasks.reward.data import clips_from_episode
    from tests.support.reward_toy import toy_episode_frames

    frames = toy_episode_frames(0.3, 9, 16, 24, np.random.default_rng(0))
    ep = Episode(source="carla", item_id="carla/r2", fps_hz=10.0, num_frames=9, frame_size_hw=(16, 24),
                 outcome=Outcome(hazard=True, infraction_score=0.6),
                 _loader=lambda start, stop, size_hw: iter(frames[start:stop]))
    assert clips_from_episode(ep, clip_frames=12, stride_frames=4) == []
    (clip,) = clips_from_episode(ep, clip_frames=12, stride_frames=4, hold_last=True)
    assert clip.key == "carla/r2@0+hold3" and clip.frames.shape[0] == 12
    np.testing.assert_array_equal(clip.frames[:9], frames)
    np.testing.assert_array_equal(clip.frames[9:], np.repeat(frames[-1:], 3, axis=0))
