"""Fixtures of the pipeline tests: one local Ray per session, one tiny synthetic world, config builders.

Keep it cheap: the VAE runs at 16x24 here (16x fewer pixels than the demo), 49-frame ReSim clips,
a stride of 4 s so each 8 s episode gives at most a handful of windows.
"""
import logging
import os
import shutil
from pathlib import Path

import pytest

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")

REPO = Path(__file__).resolve().parents[2]

# Overrides every test config shares (small and quick; same code paths as the demo).
FAST = [
    "encode.height_px=16", "encode.width_px=24", "encode.frames_height_px=16", "encode.frames_width_px=24",
    "clip.stride_frames=40", "ray.num_cpus=2", "ray.progress_bars=false",
    "ray.stages.encode.actors=1", "ray.stages.encode.num_cpus=0.5",
]


@pytest.fixture(scope="session")
def ray_session():
    """One embedded local Ray for the whole session (ray.init ~3 s, shutdown ~1.5 s)."""
    import ray

    repo = str(REPO)
    pp = os.environ.get("PYTHONPATH", "")
    if repo not in pp.split(os.pathsep):   # workers import our packages from this checkout
        os.environ["PYTHONPATH"] = os.pathsep.join([repo] + ([pp] if pp else []))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    import ray.data

    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False
    ctx.print_on_execution_start = False
    logging.getLogger("ray.data").setLevel(logging.ERROR)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="session")
def synth_world(tmp_path_factory) -> Path:
    """A tiny synthetic world (6 episodes: two per layout, one hazardous CARLA run; 8 s, 64x112), made once."""
    from resim.pipeline.sources.synth.generate import generate, preset

    root = tmp_path_factory.mktemp("synth") / "world"
    generate(root, 6, 0, preset("tiny"), progress=False)
    return root


def make_config(out: Path, overrides=(), base: str = "configs/pipeline/synthetic.yaml"):
    from resim.pipeline.load import load_config

    return load_config(REPO / base, [*FAST, *overrides], out=out)


@pytest.fixture
def config_for(tmp_path, synth_world):
    """Build a validated config on the session's synthetic world: config_for(name, *overrides)."""
    def build(name: str = "out", *overrides):
        return make_config(tmp_path / name, [f"sources.synthetic.root={synth_world}", *overrides])
    return build


def copy_world(world: Path, dest: Path) -> Path:
    shutil.copytree(world, dest)
    return dest
