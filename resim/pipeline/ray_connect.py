"""Joining a Ray cluster (``ray.address``) with one-line errors instead of Ray's tracebacks.

``ray.init(address="auto")`` with no cluster raised a raw ``ConnectionError`` traceback; against a cluster of
another Ray or Python version a 40-line ``Version mismatch`` traceback; and an explicit ``HOST:PORT`` that nobody
listens on retried for minutes before dying. Here each is a :class:`ClusterError` whose message names the
address and the way out, and an explicit address is probed with one TCP connect first, so a dead address fails
in seconds.

Authentication is Ray's own token mode (``RAY_AUTH_MODE=token``,
https://docs.ray.io/en/latest/ray-security/token-auth.html). A Ray that resim starts on this machine always uses it (:func:`secure_embedded`); joining a cluster or submitting
to one, the token is found where Ray's own CLI finds it (``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH``,
``~/.ray/auth_token``), and resim never reads, logs or saves it. docs/security.md says what each mode exposes.
"""
from __future__ import annotations

import logging
import os
import re
import secrets
import socket
from pathlib import Path

log = logging.getLogger(__name__)

# how long the TCP probe of an explicit HOST:PORT waits: a live GCS answers at once, a firewalled one never does
PROBE_TIMEOUT_S = 5.0

EMBEDDED_HINT = "or run embedded on this machine with --set ray.address=null"


class ClusterError(RuntimeError):
    """The Ray cluster cannot be used as configured (one line: the address and the reason)."""


def has_token() -> bool:
    """A token is where Ray looks for one: ``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH`` or ``~/.ray/auth_token``."""
    return bool(os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
                or (Path.home() / ".ray" / "auth_token").is_file())


def secure_embedded() -> str:
    """A Ray this process is about to start that only this machine can reach, and only with a token; returns
    ``RAY_AUTH_MODE``. Call before ``import ray``: Ray reads both settings at import.

    * **Loopback only.** Ray binds every server it starts (GCS, raylet, workers, agents) to the node's IP address,
      and takes the machine's network address as that IP unless clusters are off
      (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, ``ray._private.services.get_node_ip_address``): then the node
      IP is the loopback and nothing listens on another interface. (``_node_ip_address="127.0.0.1"`` does not
      do it: ``ray.init`` turns a loopback address back into the machine's.) An embedded run is one machine by
      definition; joining a cluster does not come through here.
    * **A token** (Ray's ``RAY_AUTH_MODE=token``), so another user of this machine cannot use the run's Ray
      either. Without a token of the user's own, one is made for this process alone and handed to Ray's
      processes through the environment they inherit; Ray would otherwise write ``~/.ray/auth_token``, a
      credential that outlives a cluster that lives only as long as this run. An explicit
      ``RAY_AUTH_MODE=disabled`` is the user's choice, said once on the console."""
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    mode = os.environ.setdefault("RAY_AUTH_MODE", "token").lower()
    if mode == "token" and not has_token():
        os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)
    elif mode == "disabled":
        log.warning("RAY_AUTH_MODE=disabled: while this run lasts, any user of this machine can run code as you "
                    "through its Ray (docs/security.md); unset it to use a token")
    return mode


def describe_address(address: str | None) -> str:
    """How an error names the address: the config value, and ``RAY_ADDRESS`` where that overrides it."""
    env = os.environ.get("RAY_ADDRESS")
    if env and (address is None or address == "auto"):
        # Ray lets RAY_ADDRESS win over a null or "auto" address, so the message must name it
        return f"ray.address={address or 'null'} (RAY_ADDRESS={env})"
    return f"ray.address={address}"


def _host_port(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of an explicit ``[ray://]HOST:PORT``; None for ``auto`` and anything unparsable."""
    m = re.fullmatch(r"(?:ray://)?\[?([^\]\s]+?)\]?:(\d{1,5})", address.strip())
    return (m.group(1), int(m.group(2))) if m else None


def probe(address: str, where: str | None = None) -> None:
    """``ClusterError`` where nothing accepts a TCP connection at an explicit ``HOST:PORT`` (``auto``: no probe,
    Ray itself finds the cluster or fails at once). ``where``: how the message names the address."""
    hp = _host_port(address)
    if hp is None:
        return
    host, port = hp
    try:
        with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S):
            return
    except OSError as e:
        why = "timed out" if isinstance(e, socket.timeout) else (e.strerror or type(e).__name__)
        raise ClusterError(
            f"{where or describe_address(address)}: no Ray cluster answers at {host}:{port} ({why}); start one "
            f"there with `ray start --head --port {port}`, check the address, {EMBEDDED_HINT}") from None


def explain(address: str | None, e: BaseException) -> ClusterError | None:
    """The one-line :class:`ClusterError` for what ``ray.init`` raised, or None where it is not a cluster problem."""
    where = describe_address(address)
    text = str(e)
    if type(e).__name__ == "AuthenticationError" or "InvalidAuthToken" in text:
        return ClusterError(f"{where}: the cluster refused this process's Ray token (none found, or another); set "
                            f"RAY_AUTH_MODE=token and the cluster's token in RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH, "
                            f"as for Ray's own CLI (docs/security.md), {EMBEDDED_HINT}")
    if "Version mismatch" in text:
        # Ray's message: "The cluster was started with:\n Ray: A\n Python: B\nThis process ... with:\n Ray: C ..."
        rays = re.findall(r"Ray:\s*(\S+)", text)
        pys = re.findall(r"Python:\s*(\S+)", text)
        if len(rays) >= 2 and len(pys) >= 2:
            versions = (f"the cluster runs Ray {rays[0]} / Python {pys[0]}, this environment Ray {rays[1]} / "
                        f"Python {pys[1]}")
        else:
            versions = "the cluster runs another Ray or Python version than this environment"
        return ClusterError(f"{where}: {versions}; run resim from an environment with the cluster's Ray and Python "
                            f"versions (or restart the cluster from this one), {EMBEDDED_HINT}")
    if isinstance(e, ConnectionError) or "Could not find any running Ray instance" in text:
        if "Could not find any running Ray instance" in text:
            reason = "no Ray cluster is running on this machine"
        else:
            reason = f"cannot connect ({text.strip().splitlines()[0] if text.strip() else type(e).__name__})"
        return ClusterError(f"{where}: {reason}; start one with `ray start --head`, or join another with "
                            f"--set ray.address=HOST:6379, {EMBEDDED_HINT}")
    return None


def join(address: str | None, **init_kwargs) -> None:
    """``ray.init(address=address, **init_kwargs)``; a missing, dead or incompatible cluster is a ``ClusterError``."""
    import ray   # ray takes seconds to import and the CLI imports this module: only when joining

    env = os.environ.get("RAY_ADDRESS")
    target = env if env and (address is None or address == "auto") else address   # what Ray will use
    if target:
        probe(target, describe_address(address))
    try:
        ray.init(address=address, **init_kwargs)
    except (ConnectionError, RuntimeError, ray.exceptions.AuthenticationError) as e:
        err = explain(address, e)
        if err is None:
            raise
        raise err from None
