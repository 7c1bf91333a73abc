"""Per-clip quality columns (resim/pipeline/clip_quality.py): each measure moves the way its name says on frames built to
differ in that one property, the filters name the column that failed, and bad bounds are refused on load."""
import cv2
import numpy as np
import pytest

from resim.config import ConfigError
from resim.pipeline.clip_quality import clip_quality, quality_problem
from resim.pipeline.config import QualityConfig


def _drive(T=17, h=64, w=96, seed=0, gain=1.0, offset=0.0) -> np.ndarray:
    """A textured scene panning 2 px per frame (the car moves): (T, h, w, 3) uint8."""
    rng = np.random.default_rng(seed)
    world = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 2 * T)).astype(np.float32), (0, 0), 1.2)
    world = (world - world.mean()) * 2.5 + 128
    frames = np.stack([world[:, 2 * t: 2 * t + w] for t in range(T)])
    return np.clip(frames[..., None].repeat(3, -1) * gain + offset, 0, 255).astype(np.uint8)


def test_each_measure_moves_with_its_property():
    base = clip_quality(_drive())
    dark = clip_quality(_drive(gain=0.25))
    assert dark["luma_mean_8bit"] < base["luma_mean_8bit"] / 3
    flat = clip_quality(_drive(gain=0.2, offset=100))
    assert flat["luma_std_8bit"] < base["luma_std_8bit"] / 3
    blurred = np.stack([cv2.GaussianBlur(f, (0, 0), 2.0) for f in _drive()])
    q_blur = clip_quality(blurred)
    assert q_blur["sharpness_lapvar"] < base["sharpness_lapvar"] / 5
    assert abs(q_blur["luma_mean_8bit"] - base["luma_mean_8bit"]) < 3      # blur alone: brightness kept

    overlay = _drive().copy()
    overlay[:, -16:, :, :] = 0                                            # a dashboard strip along the bottom
    overlay[:, -12:-4, 10:80:4, :] = 255                                  # with burnt-in digits
    q_over = clip_quality(overlay)
    assert base["static_edge_frac"] < 0.01 < q_over["static_edge_frac"] < 0.3
    frozen = np.repeat(_drive()[:1], 17, axis=0)                          # stands still: every edge is static
    assert clip_quality(frozen)["static_edge_frac"] > q_over["static_edge_frac"]
    sky = np.full((17, 64, 96, 3), 180, np.uint8)                         # flat and static, but no edge
    assert clip_quality(sky)["static_edge_frac"] == 0.0


def test_filters_name_the_column_value_and_bound_and_pass_what_was_not_measured():
    q = {**clip_quality(_drive(gain=0.25)), "flow_quality": None}
    assert quality_problem(q, QualityConfig()) is None
    why = quality_problem(q, QualityConfig(min_luma_mean_8bit=60))
    assert why.startswith("low quality: luma_mean_8bit ") and "< quality.min_luma_mean_8bit 60" in why
    assert quality_problem(q, QualityConfig(min_flow_quality=0.5)) is None             # no flow: not judged
    assert "flow_quality 0.1 < quality.min_flow_quality 0.5" in quality_problem({**q, "flow_quality": 0.1},
                                                                                QualityConfig(min_flow_quality=0.5))
    assert "static_edge_frac" in quality_problem({**q, "static_edge_frac": 0.4}, QualityConfig(max_static_edge_frac=0.2))


@pytest.mark.parametrize("bad", [{"max_static_edge_frac": 1.5}, {"min_luma_mean_8bit": -1},
                                 {"min_luma_mean_8bit": 300}, {"min_luma_mean_8bit": 200, "max_luma_mean_8bit": 100},
                                 {"min_sharpness_lapvar": float("nan")}])
def test_bad_bounds_are_refused_with_the_key(bad):
    with pytest.raises(ConfigError, match="quality[.]"):
        QualityConfig(**bad)
