"""The Ray that `resim pipeline run` starts on this machine: who else can use it.

One driver process starts Ray exactly as the pipeline does (``resim.pipeline.runner.init_ray`` on the synthetic
config) and holds it while the tests look at it from outside: the listening sockets of every Ray process are read
with psutil (a Ray dependency), and a second process tries to run code through it from the machine's network
address and from the loopback, with and without the run's token.
"""
import ipaddress
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

REPO = Path(__file__).resolve().parents[2]

DRIVER = """
import json, sys
from resim.pipeline.load import load_config
from resim.pipeline.runner import init_ray
init_ray(load_config(sys.argv[1], ["ray.num_cpus=1"]))
import ray
print(json.dumps({"gcs": ray.get_runtime_context().gcs_address}), flush=True)
sys.stdin.read()   # hold the cluster until the test closes stdin
"""

# what an attacker who knows the machine's address and the GCS port runs (the reproduction)
ATTACK = """
import sys, ray
ray.init(address=sys.argv[1], logging_level="ERROR")
@ray.remote
def touch(path):
    open(path, "w").write("ran")
ray.get(touch.remote(sys.argv[2]), timeout=60)
"""


def _external_ipv4() -> str | None:
    for addrs in psutil.net_if_addrs().values():
        for a in addrs:
            if a.family.name == "AF_INET" and not ipaddress.ip_address(a.address).is_loopback:
                return a.address
    return None


@pytest.fixture(scope="module")
def embedded_ray(tmp_path_factory):
    """(driver process, GCS port, the run's environment) of a Ray started as the pipeline starts it."""
    home = tmp_path_factory.mktemp("home")   # no ~/.ray/auth_token of the user's: the run must make its own
    # none of the session's Ray settings: what the run gets is what `init_ray` sets
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("RAY_AUTH", "RAY_ADDRESS", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"))}
    env.update(HOME=str(home), PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", DRIVER, str(REPO / "configs/pipeline/synthetic.yaml")],
                            env=env, cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line, "the driver exited before Ray came up"
        port = int(json.loads(line)["gcs"].rsplit(":", 1)[1])
        yield proc, port, env
    finally:
        proc.stdin.close()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()


def _attack(address: str, target: Path, env: dict) -> subprocess.CompletedProcess:
    """A local Ray client (clusters off, as a local client must: else it looks for the node at the machine's
    address and retries for minutes) running code at ``address``."""
    return subprocess.run([sys.executable, "-c", ATTACK, address, str(target)], cwd="/", capture_output=True,
                          env=dict(env, RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0"), text=True, timeout=180)


def test_from_another_machine_the_run_s_ray_is_not_there(embedded_ray):
    """The issue's reproduction came in through the machine's address and the GCS port: every port a Ray process
    listens on now refuses a connection there (a Ray client would retry a refused address for minutes)."""
    ip = _external_ipv4()
    if ip is None:
        pytest.skip("this machine has no non-loopback IPv4 interface to come from")
    ports = sorted({port for _, _, port in _listening(embedded_ray[0])})
    assert embedded_ray[1] in ports
    answered = []
    for port in ports:
        try:
            with socket.create_connection((ip, port), timeout=5):
                answered.append(port)
        except OSError:
            pass
    assert not answered, f"ports {answered} of the run's Ray answer on {ip}"


def test_on_this_machine_only_the_token_holder_runs_code(embedded_ray, tmp_path):
    _, port, env = embedded_ray
    outsider = {k: v for k, v in env.items() if not k.startswith("RAY_AUTH")}
    outsider["HOME"] = str(tmp_path)
    target = tmp_path / "pwned"
    r = _attack(f"127.0.0.1:{port}", target, outsider)
    assert r.returncode != 0 and not target.exists(), "a local process without the token ran code"
    # the control: the run's own token gets in, so the refusal above is the token's doing (and this is how a
    # user's own shell reaches the run's Ray: it must hold the token)
    insider = dict(env, **{k: v for k, v in _ray_environ(embedded_ray[0]).items() if k.startswith("RAY_AUTH")})
    r = _attack(f"127.0.0.1:{port}", target, insider)
    assert r.returncode == 0 and target.read_text() == "ran", r.stderr[-2000:]


def _ray_environ(proc: subprocess.Popen) -> dict:
    """The environment the driver handed to Ray's GCS (the driver's own /proc environ is its start-up one)."""
    gcs = [p for p in psutil.Process(proc.pid).children(recursive=True) if p.name() == "gcs_server"]
    assert gcs, "no gcs_server under the driver"
    return gcs[0].environ()


def _loopback(ip: str) -> bool:
    a = ipaddress.ip_address(ip)
    return a.is_loopback or bool(getattr(a, "ipv4_mapped", None) and a.ipv4_mapped.is_loopback)   # ::ffff:127.0.0.1


def _listening(proc: subprocess.Popen) -> list[tuple[str, str, int]]:
    """(process name, ip, port) of every TCP socket a process of this Ray listens on."""
    out = []
    for p in [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]:
        try:
            conns = p.net_connections(kind="tcp")
        except psutil.Error:
            continue
        out += [(p.name(), c.laddr.ip, c.laddr.port) for c in conns if c.status == psutil.CONN_LISTEN]
    return out


def test_the_run_makes_its_own_token_and_never_writes_it_to_home(embedded_ray):
    proc, _, env = embedded_ray
    ray_env = _ray_environ(proc)
    assert ray_env.get("RAY_AUTH_MODE") == "token" and len(ray_env.get("RAY_AUTH_TOKEN", "")) >= 32
    assert not (Path(env["HOME"]) / ".ray" / "auth_token").exists()


def test_every_socket_of_the_embedded_ray_is_on_loopback(embedded_ray):
    proc = embedded_ray[0]
    socks = _listening(proc)
    assert socks, "found no listening socket: the test does not see Ray's processes"
    exposed = [s for s in socks if not _loopback(s[1])]
    assert not exposed, f"{len(exposed)} of {len(socks)} listening sockets reachable from other machines: {exposed}"
