"""Tests for soc_opt/sweep_runner.py: joining a Ray cluster (``soc-opt sweep --address``).

The cluster is a real head node, started by ``ray start --head --block`` on a loopback port with
its own temporary directory and ``HOME`` (whose ``~/.ray/auth_token`` makes Ray >= 2.59 enable
token authentication, as on a user's machine after any local Ray session), and stopped by
terminating that process (which stops the node's processes) in a ``finally``.  Oracle: the trial
run on the cluster has the same metrics as the same run in this process.
"""

import csv
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from soc_opt.experiments.run import run_experiment
from soc_opt.sweeps.spec import load_sweep
from soc_opt.tasks import load_task

# the Ray tests run in one pytest-xdist worker, one after the other (`make test` uses --dist loadgroup):
# two local Ray clusters at once on a 2-core machine only slow each other down
pytestmark = pytest.mark.xdist_group("ray")

ROOT = Path(__file__).resolve().parents[1]
SWEEP = """name = "cluster"
tasks = ["linear2d"]
methods = ["lqr-flm"]
seeds = [0]
[common]
baseline = { iterations = 2, samples = 4 }
task = { T = 10 }
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ray_cli() -> str:
    exe = Path(sys.executable).with_name("ray")
    return str(exe) if exe.exists() else (shutil.which("ray") or pytest.skip("the ray command is not installed"))


def _metrics(path: Path) -> list[dict]:
    with open(path / "metrics.csv") as f:
        return [{k: v for k, v in row.items() if not k.startswith("time_")} for row in csv.DictReader(f)]


def _start_head(env: dict, port: int, temp: str) -> tuple[subprocess.Popen, list[str]]:
    """``ray start --head --block`` in the background; returns once it reports the runtime started."""
    head = subprocess.Popen(
        [_ray_cli(), "start", "--head", "--block", "--port", str(port), "--node-ip-address", "127.0.0.1",
         "--temp-dir", temp, "--include-dashboard=false", "--num-cpus", "2", "--disable-usage-stats"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(head.stdout.readline, "")), daemon=True)
    reader.start()
    deadline = time.monotonic() + 240
    while not any("Ray runtime started" in ln for ln in lines):
        if head.poll() is not None or time.monotonic() > deadline:
            raise AssertionError("ray start --head failed:\n" + "".join(lines[-30:]))
        time.sleep(0.2)
    return head, lines


def _stop(head: subprocess.Popen) -> None:
    """Stop the node started by :func:`_start_head` (SIGTERM: ``ray start --block`` stops its processes)."""
    if head.poll() is None:
        head.terminate()
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            head.kill()
            head.wait(timeout=30)


def test_sweep_joins_a_ray_head_node_that_uses_token_authentication(tmp_path):
    home = tmp_path / "home"
    (home / ".ray").mkdir(parents=True)
    (home / ".ray" / "auth_token").write_text(secrets.token_hex(32))
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env.update(HOME=str(home), PYTHONPATH=os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]),
               OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    (tmp_path / "s.toml").write_text(SWEEP)
    port = _free_port()
    temp = tempfile.mkdtemp(prefix="r", dir="/tmp")  # short: Ray's socket paths must stay short
    head = None
    try:
        head, log = _start_head(env, port, temp)
        assert any("Token authentication is enabled" in ln for ln in log), "".join(log[-30:])
        r = subprocess.run([sys.executable, "-c", "import sys; from soc_opt.cli import main; sys.exit(main())",
                            "sweep", str(tmp_path / "s.toml"), "--out", str(tmp_path / "out"),
                            "--address", f"127.0.0.1:{port}"],
                           env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-3000:]
        assert "1 done, 0 failed" in r.stdout
    finally:
        if head is not None:
            _stop(head)
        shutil.rmtree(temp, ignore_errors=True)
    (trial,) = load_sweep(tmp_path / "s.toml").trials
    result = json.loads((tmp_path / "out" / trial.relpath / "result.json").read_text())
    assert result["status"] == "done" and result["iterations"] == 2
    task = load_task(trial.task, overrides=trial.task_overrides)
    run_experiment(task, trial.method, trial.config, trial.seed, tmp_path / "here")
    assert _metrics(tmp_path / "out" / trial.relpath) == _metrics(tmp_path / "here")


# ------------------------------------------------------------------ issue 48 item 11: the local Ray listens on loopback

def _descendants(root: int) -> set[int]:
    parent = {}
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                parent[int(p)] = int(Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                pass
    out, grew = {root}, True
    while grew:
        new = {p for p, pp in parent.items() if pp in out} - out
        out |= new
        grew = bool(new)
    return out


def _listening(pids: set[int]) -> list[str]:
    """``"address:port"`` of every TCP socket in LISTEN state held by one of ``pids`` (from /proc, no tools)."""
    inodes = set()
    for pid in pids:
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
        except OSError:
            continue
    out = []
    for table, size in (("/proc/net/tcp", 4), ("/proc/net/tcp6", 16)):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] != "0A" or f[9] not in inodes:  # 0A: LISTEN
                continue
            addr, port = f[1].split(":")
            raw = bytes.fromhex(addr)
            raw = b"".join(raw[i:i + 4][::-1] for i in range(0, size, 4))  # /proc prints 32-bit words host-endian
            out.append(f"{socket.inet_ntop(socket.AF_INET if size == 4 else socket.AF_INET6, raw)}:{int(port, 16)}")
    return out


def test_a_local_sweep_listens_on_the_loopback_address_only(tmp_path, monkeypatch):
    """Every TCP socket the Ray processes of ``soc-opt sweep`` (without ``--address``) listen on, collected while
    the trial runs (GCS, raylet, object manager, agents, the worker), is bound to the loopback address."""
    ray = pytest.importorskip("ray")
    from soc_opt.sweeps import runner

    assert not ray.is_initialized()
    (tmp_path / "s.toml").write_text(SWEEP)
    spec = load_sweep(tmp_path / "s.toml")
    listening, poll = set(), runner._poll_running

    def poll_and_look(*args):
        listening.update(_listening(_descendants(os.getpid())))
        return poll(*args)

    monkeypatch.setattr(runner, "_poll_running", poll_and_look)
    with open(os.devnull, "w") as quiet:
        res = runner.run_sweep(spec, tmp_path / "out", workers=1, num_cpus=1, report=False,
                               board=runner.ProgressBoard(1, stream=quiet, live=False))
    assert res["counts"]["done"] == 1
    assert listening, "no listening socket found: the check would prove nothing"
    assert all(a.rsplit(":", 1)[0] in ("127.0.0.1", "::ffff:127.0.0.1", "::1") for a in listening), sorted(listening)
