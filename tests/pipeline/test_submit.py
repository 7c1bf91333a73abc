"""`resim pipeline submit` against a real local cluster (`ray start --head`), bounded in time.

The cluster runs in its own process group with a private temp dir; the test kills exactly that group
at the end (never `ray stop`, which would stop every Ray on the machine).
"""
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .conftest import FAST, REPO


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def ray_head(tmp_path_factory):
    port, dport = _free_port(), _free_port()
    # every port explicit: the session's embedded Ray (and other users' clusters) hold the defaults, and a
    # head whose dashboard agent cannot bind its port answers "No available agent to submit job"
    extra = [f"--{k}={_free_port()}" for k in ("dashboard-agent-listen-port", "dashboard-agent-grpc-port",
                                                "metrics-export-port", "runtime-env-agent-port",
                                                "ray-client-server-port", "node-manager-port",
                                                "object-manager-port")]
    temp = Path(f"/tmp/rsp{os.getpid()}")      # short: Ray's unix socket paths must stay < 108 chars
    bindir = str(Path(sys.executable).parent)
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0",
               PATH=bindir + os.pathsep + os.environ.get("PATH", ""))
    env.pop("RAY_ADDRESS", None)
    log = open(tmp_path_factory.mktemp("rayhead") / "ray_start.log", "w")
    proc = subprocess.Popen(
        [os.path.join(bindir, "ray"), "start", "--head", "--block", f"--port={port}", f"--dashboard-port={dport}",
         "--dashboard-host=127.0.0.1", "--num-cpus=2", "--include-dashboard=true", f"--temp-dir={temp}",
         "--disable-usage-stats", *extra],
        env=env, start_new_session=True, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{dport}"
    try:
        from ray.job_submission import JobSubmissionClient

        deadline = time.monotonic() + 90
        while True:
            try:
                JobSubmissionClient(url).list_jobs()
                break
            except Exception:  # noqa: BLE001 - the dashboard is not up yet (connection refused, 5xx)
                if time.monotonic() > deadline or proc.poll() is not None:
                    pytest.fail(f"ray start --head did not come up; see {log.name}")
                time.sleep(1)
        yield url
    finally:
        # stop exactly what we started: the `ray start` process group (gcs, raylet, dashboard, workers)
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(2)
            except subprocess.TimeoutExpired:
                pass
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(10)
        log.close()
        import shutil

        shutil.rmtree(temp, ignore_errors=True)


@pytest.mark.slow
def test_submit_status_logs_against_ray_start_head(ray_head, synth_world, tmp_path, capsys):
    from resim.cli import main

    out = tmp_path / "out"
    args = ["pipeline", "submit", str(REPO / "configs/pipeline/synthetic.yaml"), "--out", str(out),
            "--address", ray_head, "--job-id", "resim-test-job", "--follow", "--timeout-s", "240"]
    for o in [*FAST, f"sources.synthetic.root={synth_world}", "sources.synthetic.layouts=[opendv]"]:
        args += ["--set", o]
    rc = main(args)
    printed = capsys.readouterr()
    assert rc == 0, printed.out[-3000:] + printed.err[-3000:]
    assert printed.out.splitlines()[0] == "resim-test-job"
    assert "clips written" in printed.out                    # the job's own summary, streamed back

    assert main(["pipeline", "status", "resim-test-job", "--address", ray_head]) == 0
    assert capsys.readouterr().out.strip() == "SUCCEEDED"
    assert main(["pipeline", "logs", "resim-test-job", "--address", ray_head]) == 0
    assert "synthetic/opendv" in capsys.readouterr().out
    assert (out / "config.yaml").is_file() and (out / "stats.json").is_file()
    assert main(["shards", "verify", str(out)]) == 0

    # the head runs with a token (the session's, as `ray start` takes it: RAY_AUTH_MODE/RAY_AUTH_TOKEN); a shell
    # without it is refused in one line, and the job's env vars carry no token
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
    env.update(HOME=str(tmp_path), PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-m", "resim", "pipeline", "status", "resim-test-job", "--address", ray_head],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr[-2000:]
    assert "token" in r.stderr.lower() or "unauthorized" in r.stderr.lower(), r.stderr
    from ray.job_submission import JobSubmissionClient

    job_env = JobSubmissionClient(ray_head).get_job_info("resim-test-job").runtime_env.get("env_vars", {})
    assert job_env and not any(k.startswith("RAY_AUTH") for k in job_env)
