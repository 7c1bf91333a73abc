"""Planting what our writers refuse to write (NaN latents), to test that the readers refuse it too."""
import io
import tarfile
from pathlib import Path

import numpy as np


def plant_nan_latents(tar: Path, index: tuple = ...) -> None:
    """Rewrite ``tar`` with ``latent[index] = NaN`` in every ``latent.npy`` (all of it by default); each member, and
    so the tar, keeps its size (the loader compares tar sizes with the index)."""
    with tarfile.open(tar) as t:
        members = [(m, t.extractfile(m).read()) for m in t.getmembers()]
    with tarfile.open(tar, "w", format=tarfile.USTAR_FORMAT) as t:
        for m, raw in members:
            if m.name.endswith("latent.npy"):
                arr = np.load(io.BytesIO(raw))
                arr[index] = np.nan
                buf = io.BytesIO()
                np.save(buf, arr)
                assert len(buf.getvalue()) == len(raw)
                raw = buf.getvalue()
            t.addfile(m, io.BytesIO(raw))
