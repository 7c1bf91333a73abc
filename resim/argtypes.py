"""argparse types shared by the subcommands: a bad value is a one-line usage error (exit 2), not a traceback.
Also :func:`wrap`, for descriptions of parsers that keep their epilog's layout, and :func:`add_settings_args`, the
``--config`` / ``--set`` of the sampling commands.

Why typed and not ``if args.x:``: a 0 used to mean "the default" or "all" by accident (``--stride 0``,
``--limit 0``, ``--steps 0``), and a negative count reached ``random.sample`` as a traceback.
"""
from __future__ import annotations

import argparse
import textwrap
from pathlib import Path


def _int_at_least(text: str, low: int) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}") from None
    if v < low:
        raise argparse.ArgumentTypeError(f"must be >= {low}, got {v}")
    return v


def positive_int(text: str) -> int:
    """An integer >= 1."""
    return _int_at_least(text, 1)


def non_negative_int(text: str) -> int:
    """An integer >= 0."""
    return _int_at_least(text, 0)


def height_width(text: str) -> tuple[int, int]:
    """``HxW`` with two integers >= 1, e.g. ``64x112``."""
    parts = text.lower().split("x")
    try:
        h, w = (int(v) for v in parts)
    except ValueError:   # wrong count or not integers
        raise argparse.ArgumentTypeError(f"expected HxW, two integers >= 1 such as 64x112, got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"expected HxW with both >= 1, got {text!r}")
    return h, w


def _float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if v != v or v in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def positive_float(text: str) -> float:
    """A finite number > 0 (a duration, a speed)."""
    v = _float(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def non_negative_float(text: str) -> float:
    """A finite number >= 0 (a guidance scale)."""
    v = _float(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def torch_device(text: str) -> str:
    """``cpu``, ``cuda``, ``cuda:N`` or ``mps`` (spelling only; whether it exists here is checked by the command,
    which imports torch). A typo such as ``cudaa`` used to reach torch as a RuntimeError traceback."""
    t = text.strip().lower()
    kind, _, index = t.partition(":")
    if kind in ("cpu", "mps") and not index or kind == "cuda" and (not _ or index.isdigit()):
        return t
    raise argparse.ArgumentTypeError(f"expected cpu, cuda, cuda:N or mps, got {text!r}")


def local_dir(text: str) -> str:
    """An existing local folder (model weights/configs): never a hub id, so nothing is downloaded by mistake."""
    p = Path(text).expanduser()
    if not p.is_dir():
        what = "a file, not a folder" if p.exists() else "no such folder"
        raise argparse.ArgumentTypeError(f"{text}: {what} (a local model folder is required; nothing is "
                                         "downloaded)")
    return str(p)


def wrap(text: str) -> str:
    """A description wrapped here, so a RawDescriptionHelpFormatter parser can keep its epilog's layout."""
    return textwrap.fill(text, width=90)


SETTINGS_HELP = ("settings beyond the flags: YAML file with sections rollout (resim.sample.rollout.RolloutConfig), "
                 "runtime (resim.sample.settings.RuntimeConfig){extra}")


def add_settings_args(p: argparse.ArgumentParser, sections: tuple[str, ...] = ()) -> None:
    """``--config FILE`` and ``--set SECTION.KEY=VALUE`` of a sampling command (resolved by
    ``resim.sample.settings.resolve_settings``); ``sections``: its own sections beside rollout and runtime."""
    extra = "".join(f", {s}" for s in sections)
    p.add_argument("--config", default=None, metavar="FILE", help=SETTINGS_HELP.format(extra=extra))
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting, applied after --config (repeatable), e.g. --set rollout.chunk_frames=1 "
                        "--set rollout.guidance.scale_start=5 --set runtime.compile=on --set runtime.text_encoder=DIR"
                        + (f"; sections rollout, runtime{extra}" if extra else ""))
