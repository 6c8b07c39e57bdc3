"""No file soc_opt reads makes it wait (issue 48 item 1): a FIFO, a socket or a device planted at any name it
reads is refused (or, where an unreadable file counts as absent, passed over) without blocking.

A FIFO opened for reading without ``O_NONBLOCK`` blocks until a writer comes.  Each test runs the real entry
point under a watchdog that, if the reader is still waiting after :data:`WAIT` seconds, opens the FIFO for
writing (which releases it) and records that it had to: a regression fails the test instead of hanging
the suite.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import stat
import threading
from pathlib import Path

import pytest

from soc_opt.cli import main

ARGS = ["--method", "lqr-flm", "--iterations", "2", "--samples", "4", "--progress", "lines"]
CMP = ["compare", "linear2d", "--seeds", "1", "--iterations", "2", "--samples", "4", "--i-switch", "1",
       "--progress", "lines"]
#: Seconds a reader may wait on a FIFO before the watchdog releases it (and the test fails).
WAIT = 30.0


@contextlib.contextmanager
def watchdog(fifos):
    """Release, after WAIT seconds, any reader blocked on one of ``fifos``; yields the list of those released."""
    released, stop = [], threading.Event()

    def watch():
        wait = WAIT
        while not stop.wait(wait):  # after WAIT seconds, release every new wait at once
            wait = 0.1
            for p in fifos:
                with contextlib.suppress(OSError):
                    os.close(os.open(p, os.O_WRONLY | os.O_NONBLOCK))  # succeeds only when a reader waits
                    released.append(str(p))

    t = threading.Thread(target=watch, daemon=True)
    t.start()
    try:
        yield released
    finally:
        stop.set()
        t.join()


#: Runs ``soc_opt.cli`` in a child (address space capped at 2 GiB, so that a regression cannot take the machine's
#: memory) and reports its exit status and peak resident memory: a child of pytest itself would inherit pytest's
#: peak (Linux keeps the high-water mark across exec).
_LAUNCH = """
import resource, subprocess, sys
cap = lambda: resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))
p = subprocess.run([sys.executable, "-m", "soc_opt.cli", *sys.argv[1:]], preexec_fn=cap, capture_output=True,
                   text=True)
sys.stderr.write(p.stderr)
print("RSS", p.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""
#: Peak resident memory a refused hostile input may cost (issue 48): the command line alone peaks near 135 MB.
HOSTILE_RSS_MB = 300


def peak_run(args: list[str], timeout: float = 300) -> tuple[int, float, str]:
    """``(exit status, peak resident MB, standard error)`` of ``soc-opt ARGS`` in a fresh process; a command still
    running after ``timeout`` seconds (a regression: refusals take a few) is killed with its children and fails."""
    import signal
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-c", _LAUNCH, *map(str, args)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        pytest.fail(f"soc-opt {' '.join(map(str, args))[:200]} still ran after {timeout:.0f} s")
    line = [ln for ln in out.splitlines() if ln.startswith("RSS")][-1].split()
    return int(line[1]), int(line[2]) / 1024, err


def _fifo(path: Path) -> Path:
    path.unlink(missing_ok=True)
    os.mkfifo(path)
    return path


def _error(capsys) -> str:
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("soc-opt: error:"), lines
    return lines[0]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    d = tmp_path_factory.mktemp("fifo") / "run"
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 0
    return d


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    d = tmp_path_factory.mktemp("fifo") / "cmp"
    assert main([*CMP, "--out", str(d)]) == 0
    return d


RUN_PLACES = {  # name -> (extra arguments, set the run back one iteration first)
    "config.json": ([], True), "task.json": ([], True), "checkpoint.npz": ([], True),
    "checkpoint.npz of a finished run": ([], False), "checkpoint.prev.npz": (["--previous-checkpoint"], True),
}


@pytest.mark.parametrize("place", list(RUN_PLACES))
def test_a_fifo_in_a_run_directory_is_refused_naming_it_without_waiting(finished, tmp_path, capsys, place):
    name = place.split()[0]
    extra, unfinished = RUN_PLACES[place]
    d = tmp_path / "run"
    shutil.copytree(finished, d)
    if unfinished:
        shutil.copyfile(d / "checkpoint.prev.npz", d / "checkpoint.npz")
    fifo = _fifo(d / name)
    with watchdog([fifo]) as released:
        rc = main(["run", "linear2d", *ARGS, *extra, "--out", str(d)])
    assert released == []
    assert rc == 2 and name in _error(capsys)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)  # refused, not replaced


@pytest.mark.parametrize("name", ["compare.json", "seed_0/fork_state.npz", "seed_0/lqr-flm/config.json",
                                  "seed_0/lqr-flm/checkpoint.npz"])
def test_a_fifo_in_a_compare_directory_is_refused_without_waiting(compared, tmp_path, capsys, name):
    d = tmp_path / "cmp"
    shutil.copytree(compared, d)
    fifo = _fifo(d / name)
    with watchdog([fifo]) as released:
        rc = main([*CMP, "--out", str(d)])
    assert released == []
    if name in ("compare.json", "seed_0/fork_state.npz"):  # unreadable: counts as absent; rewritten by renaming
        assert rc == 0 and stat.S_ISREG(os.lstat(d / name).st_mode)
    else:
        assert rc == 2 and Path(name).name in _error(capsys)


@pytest.mark.parametrize("name", ["trial.json", "result.json"])
def test_a_fifo_as_a_trial_record_counts_as_absent_without_waiting(tmp_path, name):
    from soc_opt.sweeps.runner import prepare_out
    from soc_opt.sweeps.spec import load_sweep

    spec = load_sweep(Path(__file__).resolve().parents[1] / "problems" / "sweeps" / "linear2d_small.toml")
    out = tmp_path / "sweep"
    prepare_out(spec, out)
    fifo = _fifo(out / spec.trials[0].relpath / name)
    with watchdog([fifo]) as released:
        states = prepare_out(spec, out)
    assert released == []
    assert states[spec.trials[0].id] == "pending"


def test_a_fifo_as_sweep_json_is_refused_without_waiting(tmp_path, capsys):
    sweep = Path(__file__).resolve().parents[1] / "problems" / "sweeps" / "linear2d_small.toml"
    out = tmp_path / "sweep"
    out.mkdir()
    fifo = _fifo(out / "sweep.json")
    with watchdog([fifo]) as released:
        rc = main(["sweep", str(sweep), "--out", str(out), "--workers", "1"])
    assert released == []
    assert rc == 2 and "sweep.json" in _error(capsys)


@pytest.mark.parametrize("what", ["--config", "task file", "sweep file", "verify --replay"])
def test_a_fifo_named_on_the_command_line_is_refused_naming_it_without_waiting(tmp_path, capsys, what):
    fifo = _fifo(tmp_path / "named.toml")
    args = {"--config": ["run", "linear2d", *ARGS, "--config", str(fifo), "--out", str(tmp_path / "r")],
            "task file": ["run", str(fifo), *ARGS, "--out", str(tmp_path / "r")],
            "sweep file": ["sweep", str(fifo), "--dry-run"],
            "verify --replay": ["verify", "--replay", str(fifo)]}[what]
    with watchdog([fifo]) as released:
        rc = main(args)
    assert released == []
    err = _error(capsys)
    assert rc == 2 and str(fifo) in err and "FIFO" in err, err
    assert not (tmp_path / "r").exists()


def test_a_unix_socket_is_refused_with_a_message_naming_it(finished, tmp_path, capsys):
    d = tmp_path / "run"
    shutil.copytree(finished, d)
    shutil.copyfile(d / "checkpoint.prev.npz", d / "checkpoint.npz")
    (d / "config.json").unlink()
    short = Path(f"/tmp/soc-opt-test-{os.getpid()}.sock")  # AF_UNIX paths are short: bound outside, then moved
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(short))
        os.rename(short, d / "config.json")
        assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    err = _error(capsys)
    assert "config.json" in err and "is a socket" in err and "Errno" not in err


@pytest.mark.parametrize("kind", ["fifo", "device", "folder"])
def test_the_reader_refuses_what_is_no_regular_file_before_opening_it(tmp_path, kind):
    from soc_opt.reading import RefusedFile, check_regular, read_regular

    path = {"fifo": lambda: _fifo(tmp_path / "f"), "device": lambda: Path("/dev/zero"),
            "folder": lambda: tmp_path}[kind]()
    with watchdog([path] if kind == "fifo" else []) as released:
        with pytest.raises(RefusedFile, match="not a regular file"):
            read_regular(path, 1 << 20, follow=True)
        with pytest.raises(RefusedFile, match="not a regular file"):
            check_regular(path)
    assert released == []


def test_the_reader_refuses_a_link_unless_told_to_follow_and_bounds_the_size(tmp_path):
    from soc_opt.reading import RefusedFile, read_regular

    (tmp_path / "data").write_bytes(b"x" * 100)
    (tmp_path / "link").symlink_to(tmp_path / "data")
    with pytest.raises(RefusedFile, match="symbolic link"):
        read_regular(tmp_path / "link", 1000)
    assert read_regular(tmp_path / "link", 1000, follow=True) == b"x" * 100
    with pytest.raises(RefusedFile, match="more than"):
        read_regular(tmp_path / "data", 99)


def test_a_refusal_survives_being_sent_between_processes():
    import pickle

    from soc_opt.reading import RefusedFile

    e = pickle.loads(pickle.dumps(RefusedFile("/x/config.json", "is a FIFO (named pipe), not a regular file")))
    assert (e.path, str(e)) == ("/x/config.json", "'/x/config.json' is a FIFO (named pipe), not a regular file")
