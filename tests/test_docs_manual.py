"""docs/ reads as a manual: guides stay short (≤ ~300 lines), model cards shorter (≤ ~150), experiment logs live
in docs/lab/YYYY-MM-DD-topic.md, and every relative link between the pages resolves."""
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
GUIDES = sorted(DOCS.glob("*.md"))
CARDS = sorted((DOCS / "models").glob("*.md"))
MANUAL = [REPO / "README.md", *GUIDES, *CARDS]            # every page outside docs/lab/

DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
CLOCK = re.compile(r"\b\d\d:\d\d(:\d\d)? ?UTC\b")          # a lab log's "rule fixed 09:12 UTC"
LINK = re.compile(r"\]\(([^)#\s]+)(#[^)]*)?\)")


def _rel(p: Path) -> str:
    return str(p.relative_to(REPO))


def test_there_are_pages_to_check():
    assert len(GUIDES) >= 10 and len(CARDS) >= 4, (GUIDES, CARDS)


@pytest.mark.parametrize("page", GUIDES, ids=_rel)
def test_a_guide_stays_under_300_lines(page):
    n = len(page.read_text().splitlines())
    assert n <= 300, f"{_rel(page)}: {n} lines; move history to docs/lab/ and keep what holds now"


@pytest.mark.parametrize("page", CARDS, ids=_rel)
def test_a_model_card_stays_under_150_lines(page):
    n = len(page.read_text().splitlines())
    assert n <= 150, f"{_rel(page)}: {n} lines; a card is the model, its data, its command, its numbers, its limits"


@pytest.mark.parametrize("page", MANUAL, ids=_rel)
def test_no_dated_log_outside_the_lab(page):
    """A measurement may carry its date (a table's date column, "measured 2026-11-30"); a page may not be a diary:
    no dated section headings, no clock times."""
    bad = []
    for i, line in enumerate(page.read_text().splitlines(), 1):
        if line.startswith("#") and DATE.search(line):
            bad.append(f"{i}: dated heading: {line.strip()}")
        if CLOCK.search(line):
            bad.append(f"{i}: clock time: {line.strip()[:80]}")
    assert not bad, f"{_rel(page)}: a lab log belongs in docs/lab/YYYY-MM-DD-topic.md:\n" + "\n".join(bad)


@pytest.mark.parametrize("page", [*MANUAL, *sorted((DOCS / "lab").glob("*.md"))], ids=_rel)
def test_relative_links_resolve(page):
    missing = []
    for m in LINK.finditer(page.read_text()):
        target = m.group(1)
        if re.match(r"[a-z]+:", target):                   # http:, https:, mailto:
            continue
        if not (page.parent / target).exists():
            missing.append(target)
    assert not missing, f"{_rel(page)}: links to files that do not exist: {missing}"


def test_the_checks_catch_a_diary(tmp_path):
    """The patterns above are the ones a lab log uses (the test would pass vacuously otherwise)."""
    assert DATE.search("## Where it stands (2026-11-30)")
    assert CLOCK.search("rule fixed 09:12 UTC, before the run")
    assert not CLOCK.search("step 10:1 ratio")
    assert LINK.search("see [the log](lab/2026-11-29-x.md#finding-3)").group(1) == "lab/2026-11-29-x.md"
