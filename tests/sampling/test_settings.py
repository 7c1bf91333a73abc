"""The settings of the sampling commands (resim/sample/settings.py): --config and --set over the preset and a
distilled student's own sampling section, validated on load, one line naming the key when wrong."""
import argparse

import pytest
import yaml

from resim.config import ConfigError
from resim.eval.command_following import CommandsEvalConfig
from resim.eval.policy_ranking import ClosedLoopRun
from resim.sample.settings import resolve_settings, with_guidance_start


def _args(checkpoint, *overrides, config=None, preset="resim", steps=None, no_guidance=False):
    return argparse.Namespace(checkpoint=str(checkpoint), preset=preset, steps=steps, no_guidance=no_guidance,
                              config=config, overrides=list(overrides))


@pytest.fixture
def student(tmp_path):
    """An export whose config carries a distilled student's sampling section: 4 steps, no guidance."""
    ck = tmp_path / "student" / "final"
    ck.mkdir(parents=True)
    (ck / "config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {"preset": "tiny"},
                                                    "sampling": {"num_steps": 4, "guidance": "none",
                                                                 "distilled_from": "runs/teacher"}}))
    (ck / "model.safetensors").write_bytes(b"")   # only its config is read here
    return tmp_path / "student"


def test_the_preset_then_the_file_then_set(tmp_path):
    s = resolve_settings(_args(tmp_path))
    assert (s.rollout.num_steps, s.rollout.chunk_frames, s.rollout.guidance.scale_start) == (50, 10, 7.5)
    assert s.runtime.compile == "auto" and s.runtime.batch_size == 4 and not s.scale_start_given
    f = tmp_path / "s.yaml"
    f.write_text("rollout: {chunk_frames: 5, guidance: {scale_start: 3}}\nruntime: {batch_size: 2}\n")
    s = resolve_settings(_args(tmp_path, "rollout.chunk_frames=2", config=f, steps=7))
    assert (s.rollout.num_steps, s.rollout.chunk_frames, s.rollout.guidance.scale_start) == (7, 2, 3.0)
    assert s.rollout.guidance.scale_end == 1.0 and s.runtime.batch_size == 2 and s.scale_start_given
    assert s.to_dict()["rollout"]["chunk_frames"] == 2            # what is saved with an output
    v = resolve_settings(_args(tmp_path, preset="vid2world"))
    assert v.rollout.chunk_frames == 1 and v.rollout.guidance.schedule == "constant"


def test_on_and_off_are_words_not_booleans(tmp_path):
    """YAML 1.1 reads `off` as false; the settings whose values are auto / on / off take it as the word."""
    s = resolve_settings(_args(tmp_path, "rollout.kv_cache=off", "runtime.compile=on"))
    assert (s.rollout.kv_cache, s.runtime.compile) == ("off", "on")


def test_a_distilled_student_samples_at_its_own_steps_unless_told(student):
    s = resolve_settings(_args(student))
    assert s.rollout.num_steps == 4 and not s.rollout.guidance.enabled and "distilled student" in s.origin
    s = resolve_settings(_args(student, "rollout.guidance.scale_start=2", steps=8))
    assert s.rollout.num_steps == 8 and s.rollout.guidance.enabled and s.rollout.guidance.scale_start == 2.0


def test_sections_of_a_command(tmp_path):
    s = resolve_settings(_args(tmp_path, "commands.group_ends=true"), {"commands": CommandsEvalConfig})
    assert s.section("commands").group_ends and s.section("commands").horizons_s == (0.5, 1.0, 2.0, 4.0)
    with pytest.raises(ConfigError, match="unknown settings section 'commands'"):   # not this command's
        resolve_settings(_args(tmp_path, "commands.group_ends=true"))
    with pytest.raises(ConfigError, match="replay drives the world model"):
        resolve_settings(_args(tmp_path, "closed_loop.replay=true", "closed_loop.true_only=true"),
                         {"closed_loop": ClosedLoopRun})
    with pytest.raises(ConfigError, match="variants=\\['policy', 'fast'\\]"):
        resolve_settings(_args(tmp_path, "closed_loop.variants=[policy, fast]"), {"closed_loop": ClosedLoopRun})
    raw = resolve_settings(_args(tmp_path, "quality.fid_weights=/w.pth"), {"quality": dict})
    assert raw.section("quality") == {"fid_weights": "/w.pth"}


def test_a_callers_own_start_scale(tmp_path):
    """A closed loop's default start scale, where the user gave none (resim.eval.policy_ranking.loop_guidance)."""
    s = resolve_settings(_args(tmp_path))
    assert with_guidance_start(s.rollout, 15.0).guidance.scales(3) == pytest.approx([15.0, 8.0, 1.0])
    v = resolve_settings(_args(tmp_path, preset="vid2world"))
    assert with_guidance_start(v.rollout, 4.0).guidance.scales(2) == [4.0, 4.0]
