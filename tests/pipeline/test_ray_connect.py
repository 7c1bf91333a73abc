"""Joining a cluster that is not there, or not compatible, is one line naming the address and the fix
(resim/pipeline/ray_connect.py), never Ray's traceback; nothing is written to OUT."""
import os
import socket
import subprocess
import sys
import textwrap

from resim.pipeline.ray_connect import ClusterError, describe_address, explain, probe

from .conftest import REPO

# ray.init(address="auto") joins *any* Ray it finds on this machine (the last `ray start`, or any running GCS,
# e.g. another test session's embedded Ray): the child hides both, so it sees no cluster whatever else runs here.
_NO_CLUSTER_HERE = textwrap.dedent("""
    import sys
    import ray._private.services as services

    def find_gcs_addresses():
        return []

    find_gcs_addresses.cache_clear = lambda: None
    services.find_gcs_addresses = find_gcs_addresses
    services.find_bootstrap_address = lambda temp_dir=None: None
    from resim.cli import main

    sys.exit(main(sys.argv[1:]))
""")


def test_auto_with_no_cluster_is_one_line_and_writes_nothing(tmp_path):
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}   # RAY_ADDRESS would win over "auto"
    env["PYTHONPATH"] = str(REPO)
    r = subprocess.run([sys.executable, "-c", _NO_CLUSTER_HERE, "pipeline", "run",
                        str(REPO / "configs/pipeline/my_videos.yaml"), "--out", str(out), "--no-progress",
                        "--set", f"sources.opendv.root={videos}", "--set", "ray.address=auto"],
                       capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
    err = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert err == ["resim pipeline run: error: ray.address=auto: no Ray cluster is running on this machine; start "
                   "one with `ray start --head`, or join another with --set ray.address=HOST:6379, or run embedded "
                   "on this machine with --set ray.address=null"], r.stderr
    assert not (out / "config.yaml").exists()          # checked before OUT is prepared


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_address_nobody_listens_on_fails_at_once(monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    port = _free_port()
    try:
        probe(f"127.0.0.1:{port}")     # was: ray.init retrying for minutes, then a traceback
    except ClusterError as e:
        assert str(e) == (f"ray.address=127.0.0.1:{port}: no Ray cluster answers at 127.0.0.1:{port} (Connection "
                          f"refused); start one there with `ray start --head --port {port}`, check the address, or "
                          "run embedded on this machine with --set ray.address=null")
    else:
        raise AssertionError("no ClusterError")
    probe("auto")                      # nothing to probe: Ray looks for the cluster itself


def test_a_version_mismatch_is_one_line_naming_both_versions(monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    ray_says = RuntimeError(   # ray._private.utils.check_version_info's message
        "Version mismatch: The cluster was started with:\n    Ray: 2.9.3\n    Python: 3.10.12\n"
        "This process on node 10.0.0.5 was started with:\n    Ray: 2.60.0\n    Python: 3.11.7\n")
    e = explain("auto", ray_says)
    assert isinstance(e, ClusterError) and str(e) == (
        "ray.address=auto: the cluster runs Ray 2.9.3 / Python 3.10.12, this environment Ray 2.60.0 / Python 3.11.7; "
        "run resim from an environment with the cluster's Ray and Python versions (or restart the cluster from this "
        "one), or run embedded on this machine with --set ray.address=null")
    assert explain("auto", RuntimeError("something else")) is None      # not ours to rephrase: it propagates
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.5:6379")                  # Ray lets it win over "auto": say so
    assert describe_address("auto") == "ray.address=auto (RAY_ADDRESS=10.0.0.5:6379)"
