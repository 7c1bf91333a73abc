"""The one device resolver: ``None`` / ``"auto"`` → the GPU when torch sees one, else the CPU; an explicit device
is checked against this machine and torch build, so a wrong one is one line naming it, not torch's
AssertionError "Torch not compiled with CUDA enabled" in the middle of a run."""
from __future__ import annotations

import torch


class DeviceError(ValueError):
    """A device this machine or torch build cannot use; the message names it and what to use instead."""


def resolve_device(device: str | None = None, want_gpu: bool = True, flag: str = "device") -> str:
    """``device`` (``None``/``"auto"``: the best one here; ``want_gpu=False``: the CPU) as a torch device string.
    ``flag``: how the user chose it, for the message (``"--device"`` on a command line)."""
    if device is None or device == "auto":
        return "cuda" if want_gpu and torch.cuda.is_available() else "cpu"
    kind, _, index = device.partition(":")
    if kind == "cuda":
        if not torch.cuda.is_available():
            why = "this torch build has no CUDA support" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise DeviceError(f"{flag} {device}: {why}; use {flag} cpu (or leave {flag} out)")
        n = torch.cuda.device_count()
        if index and int(index) >= n:
            raise DeviceError(f"{flag} {device}: there are {n} CUDA device(s) here (cuda:0 .. cuda:{n - 1})")
    elif kind == "mps" and not torch.backends.mps.is_available():
        raise DeviceError(f"{flag} {device}: MPS is not available here; use {flag} cpu")
    return device
