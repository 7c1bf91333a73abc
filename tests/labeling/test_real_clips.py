"""The labeler on real dashcam footage (../shared/data/dashcam; skipped where absent).

What the clips show (frames viewed every 0.5 s, docs/labeling.md): solidWhiteRight drives a
straight freeway; challenge follows a gentle right-hand freeway curve (distant hills drift
left, the barrier ahead bends right) with no lane change or turn.
"""
from resim.labeling.windows import label_video


def test_solid_white_right_is_straight(dashcam_dir):
    res = label_video(dashcam_dir / "solidWhiteRight.mp4")
    assert len(res.windows) == 3
    for w in res.windows:
        assert w.command == "Moving forward"
        assert abs(w.yaw_deg) < 4.0, w


def test_challenge_is_a_gentle_right_curve(dashcam_dir):
    res = label_video(dashcam_dir / "challenge.mp4")
    assert res.info.pixel_aspect > 1.3          # anamorphic 64:45 is honoured
    for w in res.windows:
        assert -16.0 < w.yaw_deg < -3.0, w          # right (negative), gentle
        assert w.command == "Moving forward"
