"""The layers of docs/architecture.md, checked on every import, at the top of a file or inside a function.

One namespace, ``resim``; its folders in the order data travels, each importing only the ones below it:

* the kernel (``resim.config``, ``resim.argtypes``, ``resim.folders``, ``resim.shipped``, ``resim.__version__``);
* data: ``media`` → ``shards`` → ``labeling`` / ``synthworld`` → ``pipeline``;
* learning: ``models`` → ``diffusion`` → ``sample`` → ``train`` → ``eval``; it reads the data layers' formats
  (media, shards, labeling, synthworld) and never calls the pipeline, which never calls it;
* the face (``resim.cli``, ``resim.demo``, ``resim.__main__``), which nothing below imports.

``shards`` stays light (no torch, no Ray); ``media`` and ``synthworld`` import nothing of ours but the kernel.
The test parses the source (nothing is imported), so an import hidden in a function counts too.
"""
import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

KERNEL = {"resim", "resim.config", "resim.argtypes", "resim.folders", "resim.shipped"}
FACE = {"resim.cli", "resim.demo", "resim.__main__"}
DATA = ["media", "shards", "labeling", "synthworld", "pipeline"]
LEARNING = ["models", "diffusion", "sample", "train", "eval"]
FOLDERS = DATA + LEARNING


def _above(folder: str, order: list[str]) -> set[str]:
    return set(order[order.index(folder) + 1:])


# folder -> folders of ours it must not import (the face is forbidden to all of them)
FORBIDDEN: dict[str, set[str]] = {
    "media": set(FOLDERS) - {"media"},
    "shards": _above("shards", DATA) | set(LEARNING),
    "labeling": {"synthworld", "pipeline"} | set(LEARNING),
    "synthworld": set(FOLDERS) - {"synthworld"},
    "pipeline": set(LEARNING),
    **{f: _above(f, LEARNING) | {"pipeline"} for f in LEARNING},
}
THIRD_PARTY_FORBIDDEN = {"shards": {"torch", "ray"}}
NOT_SHIPPED = {"lab", "tests", "bench", "scripts"}   # folders of the repository outside the wheel


def layer_of(module: str) -> str | None:
    """``resim.train.stream`` → ``train``; the kernel → ``kernel``; the face → ``face``; not ours → None."""
    parts = module.split(".")
    if parts[0] != "resim":
        return None
    if module in KERNEL or ".".join(parts[:2]) in KERNEL:
        return "kernel"
    if ".".join(parts[:2]) in FACE:
        return "face"
    return parts[1] if parts[1] in FOLDERS else "unknown"


def imports_of(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import statement in ``path``, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
    return out


def violations(root: Path) -> set[tuple[str, str, int]]:
    """(file, imported module, line) of every import against the layers, under ``root/resim``."""
    found = set()
    for f in sorted((root / "resim").rglob("*.py")):
        rel = f.relative_to(root)
        src = layer_of(".".join(rel.with_suffix("").parts))
        for line, mod in imports_of(f):
            dst = layer_of(mod)
            bad = (dst == "unknown" or mod.split(".")[0] in NOT_SHIPPED
                   or (dst == "face" and src != "face")
                   or (src == "kernel" and dst not in (None, "kernel"))
                   or (src in FORBIDDEN and dst in FORBIDDEN[src])
                   or mod.split(".")[0] in THIRD_PARTY_FORBIDDEN.get(src, ()))
            if bad:
                found.add((rel.as_posix(), mod, line))
    return found


def test_one_import_namespace():
    """Every package of the distribution lives under resim/ (the wheel test checks the built wheel)."""
    stray = sorted(p.parent.name for p in REPO.glob("*/__init__.py") if p.parent.name != "resim")
    assert not stray, f"top-level packages beside resim: {stray}"


def test_imports_follow_the_layers():
    found = violations(REPO)
    assert not found, "imports against the layers (docs/architecture.md):\n" + "\n".join(
        f"  {f}:{line} imports {mod}" for f, mod, line in sorted(found))


@pytest.mark.parametrize("where, planted", [
    ("shards", "import torch"),
    ("shards", "from resim.labeling import flow"),
    ("labeling", "from resim.pipeline import runner"),
    ("media", "from resim.shards.schema import COMMANDS"),
    ("synthworld", "from resim.labeling.commands import command_from_trajectory"),
    ("pipeline", "from resim.models.world.dit import WorldModel"),
    ("models", "from resim.diffusion.ddim import DDIMSampler"),
    ("diffusion", "from resim.sample.rollout import rollout"),
    ("sample", "from resim.train.trainer import Trainer"),
    ("train", "from resim.eval.report import format_protocol"),
    ("train", "from resim.pipeline.config import PipelineConfig"),
    ("eval", "from resim.cli import build_parser"),
    ("eval", "from resim.demo.run import run_demo"),
    ("config.py", "from resim.models import registry"),
    ("models", "from resim.nowhere import x"),
    ("eval", "from lab.detail_probe import probe"),
])
def test_a_planted_upward_import_is_caught_even_inside_a_function(tmp_path, where, planted):
    f = tmp_path / "resim" / (where if where.endswith(".py") else f"{where}/planted.py")
    f.parent.mkdir(parents=True)
    f.write_text(f"def f():\n    {planted}\n")
    assert violations(tmp_path) == {(f.relative_to(tmp_path).as_posix(), planted.split()[1], 2)}


def test_what_the_layers_allow_is_not_flagged(tmp_path):
    """The control: imports downward and within a folder pass."""
    f = tmp_path / "resim" / "eval" / "ok.py"
    f.parent.mkdir(parents=True)
    f.write_text("from resim.train.trainer import Trainer\nfrom resim.models import registry\n"
                 "from resim.shards.schema import COMMANDS\nfrom resim.config import ConfigError\nimport torch\n")
    assert violations(tmp_path) == set()
