"""Shared test set-up: quiet, offline, single-threaded torch, one Ray per session."""
import os

# Tiny models everywhere: one thread is much faster than two fighting over a shared 2-core machine
# (a tiny world-model step: 33 ms on 1 thread vs 1.5 s on 2 with the other core busy). Subprocesses inherit it.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from resim.models import registry  # noqa: E402
from resim.pipeline.ray_connect import secure_embedded  # noqa: E402

# Ray as resim runs it: token authentication, one token for the session's Rays and the processes that join them
secure_embedded()

# the generic trainer's test model (tests/support/toy.py), registered for the tests only, not in the product
registry.register("toy", "tests.support.toy:build_toy")

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture
def needs_inductor():
    """Skip, with the reason, where torch.compile cannot build CPU kernels (no C++ compiler or Python headers):
    the compile tests need inductor, the product only uses it when asked (``--compile``, ``trainer.compile``)."""
    import torch   # as in one_torch_thread

    try:
        torch.compile(lambda x: x * 2 + 1)(torch.ones(2))
    except Exception as e:
        pytest.skip(f"torch.compile cannot build CPU kernels on this machine: {str(e).splitlines()[0][:120]}")


@pytest.fixture
def one_torch_thread():
    """torch on one thread for the test, restored after (a test module opts in with
    ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``): tiny models run fastest so, and a reduction
    order that does not depend on the thread count lets the exact-resume tests compare bits."""
    import torch   # imported when a test asks for it: a session of torch-free tests (shards) does not load it

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """../shared beside the checkout (real dashcam clips, format fixtures); skip where absent."""
    if not SHARED.is_dir():
        pytest.skip("../shared is absent (a user's clone has none); this test reads real data from it")
    return SHARED


def _udta_before_tracks(src, dst):
    """Copy an MP4 with its ``moov/udta`` box (iTunes metadata, the ``covr`` cover) moved in front of the tracks, as
    some taggers write it: FFmpeg's demuxer then makes the cover stream 0 (its own muxer writes udta last). moov
    keeps its size, so the chunk offsets into mdat stay valid."""
    import struct

    b = bytearray(src.read_bytes())

    def boxes(i, end):
        while i < end:
            size, kind = struct.unpack(">I4s", b[i:i + 8])
            yield i, size, kind
            i += size

    moov = next((i, n) for i, n, k in boxes(0, len(b)) if k == b"moov")
    kids = list(boxes(moov[0] + 8, sum(moov)))
    u = next(k for k in kids if k[2] == b"udta")
    t = next(k for k in kids if k[2] == b"trak")
    box = bytes(b[u[0]:u[0] + u[1]])
    del b[u[0]:u[0] + u[1]]
    b[t[0]:t[0]] = box
    dst.write_bytes(bytes(b))
    return dst


@pytest.fixture
def udta_before_tracks():
    """The function above (tests/labeling/test_video.py and tests/sources/test_opendv.py build cover-first MP4s)."""
    return _udta_before_tracks


def pytest_collection_modifyitems(config, items):
    """``@pytest.mark.gpu`` tests skip where no CUDA GPU is visible (the marker alone skips nothing).

    torch is imported only when a collected test carries the marker: most suites here never need it."""
    gpu_items = [item for item in items if item.get_closest_marker("gpu") is not None]
    if not gpu_items:
        return
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (none visible)")
    for item in gpu_items:
        item.add_marker(skip)
