"""The dependency directions of docs/architecture.md, checked on every import, at the top of a file or inside a
function: shards <- labeling <- pipelines; training reads shards and never calls the pipeline; media (video
I/O, encoders shared by the pipeline and training) and synthworld (the synthetic world's simulator, shared by
``resim synth`` and the closed loops) import nothing of ours; shards stays light (no torch,
no Ray). The test parses the source (nothing is imported), so an import hidden in a function counts too."""
import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
OURS = ("shards", "labeling", "pipelines", "training", "media", "synthworld", "resim", "bench", "scripts")

# package -> top-level modules it must not import
FORBIDDEN = {
    "shards": {"torch", "ray", "pipelines", "training", "labeling"},
    "labeling": {"pipelines", "training"},
    "training": {"pipelines"},
    "media": set(OURS) - {"media"},
    "synthworld": set(OURS) - {"synthworld"},
}

# Known violations, each with the reason it is still there; the test fails on any other, and on an entry here
# that no longer occurs (so the list only shrinks). None is left.
KNOWN: set[tuple[str, str]] = set()


def imports_of(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import statement in ``path``, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
    return out


def violations(root: Path, rules: dict[str, set[str]]) -> set[tuple[str, str, int]]:
    found = set()
    for pkg, bad in rules.items():
        for f in sorted((root / pkg).rglob("*.py")):
            for line, mod in imports_of(f):
                if mod.split(".")[0] in bad:
                    found.add((f.relative_to(root).as_posix(), mod, line))
    return found


def test_imports_follow_the_architecture():
    found = violations(REPO, FORBIDDEN)
    new = sorted(v for v in found if (v[0], v[1]) not in KNOWN)
    assert not new, "imports against the architecture (docs/architecture.md):\n" + "\n".join(
        f"  {f}:{line} imports {mod}" for f, mod, line in new)
    gone = KNOWN - {(f, m) for f, m, _ in found}
    assert not gone, f"fixed, remove from KNOWN: {sorted(gone)}"


@pytest.mark.parametrize("pkg, planted", [("shards", "import torch"), ("labeling", "from pipelines import runner"),
                                          ("training", "from pipelines.config import PipelineConfig"),
                                          ("media", "from shards.schema import COMMANDS"),
                                          ("synthworld", "from resim.config import ConfigError")])
def test_a_planted_violation_is_caught_even_inside_a_function(tmp_path, pkg, planted):
    (tmp_path / pkg).mkdir()
    (tmp_path / pkg / "planted.py").write_text(f"def f():\n    {planted}\n")
    assert violations(tmp_path, FORBIDDEN) == {(f"{pkg}/planted.py", planted.split()[1], 2)}
