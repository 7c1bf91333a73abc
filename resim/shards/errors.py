"""What reading a shard can go wrong with, and how WebDataset splits a member name: shared by the reader, the tar
walker (``tario``) and the manifest reader, so none of them imports another for it."""
from __future__ import annotations

import re

_BASE_PLUS_EXT = re.compile(r"^((?:.*/|)[^.]+)[.]([^/]*)$")  # the same split WebDataset uses
# raw-sample entry (a ``__*__`` name, like WebDataset's ``__key__``) holding why a member of the sample is unusable:
# set by ``resim.shards.tario`` on a link or device member, whose bytes are never read (a link could point anywhere)
BAD_MEMBER = "__bad_member__"


class ShardReadError(ValueError):
    """A shard cannot be read (truncated, not a tar, malformed grouping)."""


class ForbiddenMemberError(ShardReadError):
    """A shard carries a member in a code-executing format (pickle and friends)."""


def split_member_name(name: str) -> tuple[str | None, str | None]:
    """``"dir/KEY.meta.json" -> ("dir/KEY", "meta.json")`` exactly as WebDataset groups members."""
    m = _BASE_PLUS_EXT.match(name)
    return (m.group(1), m.group(2)) if m else (None, None)
