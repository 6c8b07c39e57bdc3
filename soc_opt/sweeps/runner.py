"""Running a sweep on Ray core tasks: scheduling, retries, status, live progress.

Each trial of a :class:`~soc_opt.sweeps.spec.SweepSpec` is one Ray task calling
:func:`soc_opt.sweeps.trial.run_trial` on its run directory ``OUT/trials/<task>/<setting>/<method>/seed_<n>``.
Why Ray core tasks and not Ray Tune: docs/choices.md ("Sweeps").

- Local by default: a private Ray instance on this machine's cores (no dashboard, quiet logs),
  listening on the loopback address only (:func:`_init_on_loopback`), shut down at the end;
  ``address`` joins an existing cluster instead (soc_opt installed on every
  node, ``OUT`` on a shared file system), with Ray's token authentication when a token is
  available and ``RAY_AUTH_MODE`` is unset, as ``ray start --head`` decides (:func:`_use_ray_token`).
  ``workers`` caps the trials in flight.
- A finished trial (``result.json`` present, same spec) is skipped; an unfinished or failed one
  is started again and resumes from its checkpoint.  A trial whose worker process dies is
  re-executed by Ray (``max_retries``) and resumes from its last checkpoint; when the retries are
  exhausted it is recorded as failed like any other error.
- ``status.json`` (all trials' states and errors) is rewritten on every change; the aggregated
  report (:mod:`soc_opt.sweeps.report`) is written at the end.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Callable

from .. import files
from ..experiments.run import same_settings
from ..experiments.rundir import lock_directory, refuse_foreign, unowned_entries
from .spec import (
    ERROR,
    PROGRESS,
    RESULT,
    TRIAL,
    SweepError,
    SweepSpec,
    TrialSpec,
    as_json,
    read_json,
    read_result,
    write_json,
)
from .trial import run_trial

#: What marks a folder as a sweep directory: its ``sweep.json`` (a table with ``name`` and ``trials``).
SWEEP_FILE = "sweep.json"

__all__ = ["run_sweep", "prepare_out", "ProgressBoard", "STATES"]

STATES = ("pending", "running", "done", "failed")


def check_sweep_dir(out: Path) -> None:
    """Refuse (:class:`SweepError`) an ``out`` that is neither new, empty nor a sweep directory (its
    ``sweep.json``): a sweep writes into no folder of the user's."""
    out = Path(out)
    if os.path.lexists(out) and not out.is_dir():
        raise SweepError(f"--out {str(out)!r} exists and is not a folder; use another --out")
    rec = read_json(out / SWEEP_FILE) if os.path.lexists(out / SWEEP_FILE) else None
    if isinstance(rec, dict) and isinstance(rec.get("name"), str) and isinstance(rec.get("trials"), list):
        return
    refuse_foreign(out, unowned_entries(out), "a sweep directory", "sweep.json of a sweep", SweepError)


def prepare_out(spec: SweepSpec, out: Path) -> dict[str, str]:
    """Check ``out`` against the spec (before anything runs); return the trials' initial states.

    A trial directory holding a different trial spec is an error naming it (a changed sweep
    file must not silently resume unrelated runs), and so is a ``result.json`` claiming a finished
    trial without the fields the report reads (:func:`soc_opt.sweeps.spec.read_result`).  Finished trials
    are ``"done"``; every other trial's ``trial.json`` is (re)written with the spec it will run with, so
    that the record names options added to soc_opt since the directory was first prepared.  Nothing is
    written through a link (:mod:`soc_opt.files`).
    """
    out = Path(out)
    check_sweep_dir(out)
    states = {}
    for t in spec.trials:
        d = out / t.relpath
        old = read_json(d / TRIAL)
        new = as_json(t.to_dict())
        if old is not None and not same_settings(old, new):
            raise SweepError(f"trial directory {str(d)!r} holds trial {t.id} with a different specification; "
                             "use another --out or delete it")
        res = read_result(d / RESULT)
        states[t.id] = "done" if (old is not None and res is not None) else "pending"
    write_json(out / SWEEP_FILE, spec.to_dict(), out)
    for t in spec.trials:
        d = out / t.relpath
        files.make_dirs(d, anchor=out)
        if states[t.id] != "done":  # it runs with this spec: record all of it (options added since included)
            write_json(d / TRIAL, t.to_dict(), out)
    return states


def _remote_trial(spec: TrialSpec, trial_dir: str, on_iteration, anchor: str | None = None):
    return run_trial(spec, trial_dir, on_iteration, anchor)


#: Where Ray looks for the token of a cluster with token authentication (Ray >= 2.52), in its order.
RAY_TOKEN_ENV = ("RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")


def _ray_token_available() -> bool:
    """A token in ``RAY_AUTH_TOKEN``, the file ``RAY_AUTH_TOKEN_PATH`` or ``~/.ray/auth_token``."""
    if os.environ.get("RAY_AUTH_TOKEN"):
        return True
    path = os.environ.get("RAY_AUTH_TOKEN_PATH")
    return Path(path).is_file() if path else (Path.home() / ".ray" / "auth_token").is_file()


def _use_ray_token(ray) -> bool:
    """Turn on Ray's token authentication for joining a cluster when a token is available.

    ``ray start --head`` enables token authentication when ``RAY_AUTH_MODE`` is unset and a token
    exists, but ``ray.init(address=...)`` does not do the same for the client, so it is refused
    (``InvalidAuthToken``).  Same rule here: ``RAY_AUTH_MODE`` set by the user is respected; unset
    and a token available: ``RAY_AUTH_MODE=token`` for this process (a cluster without
    authentication accepts such a client too).  Returns whether token mode is on.
    """
    mode = os.environ.get("RAY_AUTH_MODE")
    if mode is not None:
        return mode.lower() == "token"
    if not _ray_token_available():
        return False
    os.environ["RAY_AUTH_MODE"] = "token"
    config = getattr(getattr(ray, "_raylet", None), "Config", None)
    if config is not None and hasattr(config, "initialize"):  # Ray caches its config at import
        config.initialize("")
    return True


def _start_ray(address: str | None, num_cpus: int | None) -> bool:
    """Connect to Ray; returns whether this call started it (and so must shut it down)."""
    try:
        import ray
    except ImportError as e:  # pragma: no cover - ray is in the [sweep] and [test] extras
        raise SweepError("soc-opt sweep needs Ray: pip install 'soc_opt[sweep]'") from e
    if ray.is_initialized():
        return False
    quiet = dict(logging_level=logging.ERROR, log_to_driver=False)
    if address:
        token = _use_ray_token(ray)
        try:
            ray.init(address=address, **quiet)
        except ConnectionError as e:
            how = ("with token authentication (RAY_AUTH_MODE=token)" if token else
                   "without token authentication (RAY_AUTH_MODE is 'disabled' or no token was found)")
            raise SweepError(
                f"--address {address}: cannot connect to the Ray cluster {how}: {e}. A cluster started with "
                "`ray start --head` while a token exists (~/.ray/auth_token, RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH) "
                "requires the same token here; see docs/sweeps.md (Ray clusters)") from e
    else:
        _init_on_loopback(ray, num_cpus=num_cpus or os.cpu_count() or 1, include_dashboard=False, **quiet)
    return True


def _init_on_loopback(ray, **init) -> None:
    """``ray.init(**init)`` starting a local Ray whose servers listen on 127.0.0.1 only (docs/security.md, "Ray").

    Ray's servers (GCS, raylet, object manager, workers, agents) listen on every interface unless the node's
    address is the loopback address; ``ray.init`` replaces a given ``_node_ip_address`` of 127.0.0.1 by the
    machine's routable address, taking the node's address from ``ray_constants.ENABLE_RAY_CLUSTER`` (off:
    loopback, Ray's own choice on macOS and Windows).  That switch is off while the node starts; a node that
    still comes up elsewhere is shut down and refused, naming ``--address`` as the way to a cluster.
    """
    constants = ray._private.ray_constants
    before = constants.ENABLE_RAY_CLUSTER
    constants.ENABLE_RAY_CLUSTER = False
    try:
        ray.init(**init)
    finally:
        constants.ENABLE_RAY_CLUSTER = before
    gcs = str(ray.get_runtime_context().gcs_address)
    if not gcs.startswith("127.0.0.1:"):
        ray.shutdown()
        raise SweepError(f"the local Ray started at {gcs}, not on the loopback address 127.0.0.1, so other machines "
                         "could reach it; start a Ray node yourself and join it with --address (docs/sweeps.md)")


class _Status:
    """The trials' states and errors, mirrored to ``OUT/status.json``."""

    def __init__(self, spec: SweepSpec, out: Path, states: dict[str, str]):
        self.out = out
        self.spec = spec
        self.trials = {t.id: {"state": states[t.id], "dir": str(t.relpath)} for t in spec.trials}
        self.started = time.time()

    def set(self, tid: str, state: str, **info) -> None:
        self.trials[tid] = {"state": state, "dir": self.trials[tid]["dir"], **info}

    def counts(self) -> dict[str, int]:
        return {s: sum(1 for v in self.trials.values() if v["state"] == s) for s in STATES}

    def write(self) -> None:
        write_json(self.out / "status.json", {"sweep": self.spec.name, "updated": time.time(),
                                              "elapsed": time.time() - self.started,
                                              "counts": self.counts(), "trials": self.trials}, self.out)


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    *,
    address: str | None = None,
    workers: int | None = None,
    num_cpus: int | None = None,
    max_retries: int = 3,
    on_iteration: Callable | None = None,
    board: "ProgressBoard | None" = None,
    report: bool = True,
) -> dict:
    """Run every unfinished trial of ``spec`` under ``out``; write ``status.json`` and the report.

    ``on_iteration(trial_id, state, trial_dir)`` is called inside the worker after each
    checkpointed iteration (it must be picklable).  Returns ``{"status": ..., "report": ...}``.
    ``out`` must be new, empty or a sweep directory (:func:`check_sweep_dir`); the sweep holds its lock
    (``out/lock``, naming the holder's pid) while it runs, so a second sweep on ``out`` stops at once.
    """
    out = Path(out)
    if workers is not None and workers < 1:
        raise SweepError(f"--workers must be >= 1, got {workers}")
    check_sweep_dir(out)  # before the lock file is created
    with lock_directory(out, what="sweep directory"):
        return _run_sweep_locked(spec, out, address, workers, num_cpus, max_retries, on_iteration, board, report)


def _run_sweep_locked(spec, out, address, workers, num_cpus, max_retries, on_iteration, board, report) -> dict:
    states = prepare_out(spec, out)
    status = _Status(spec, out, states)
    board = board or ProgressBoard(len(spec.trials))
    for tid, st in states.items():
        board.set(tid, st, "finished earlier" if st == "done" else "")
    status.write()
    todo = [t for t in spec.trials if states[t.id] != "done"]
    started = _start_ray(address, num_cpus) if todo else False
    try:
        if todo:
            _schedule(todo, out, status, board, workers, max_retries, on_iteration)
    finally:
        status.write()
        board.close()
        if started:
            import ray

            ray.shutdown()
    result = {"status": status.trials, "counts": status.counts()}
    if report:
        from .report import write_report

        result["report"] = str(write_report(spec, out, status.trials))
    return result


def _schedule(todo: list[TrialSpec], out: Path, status: _Status, board: "ProgressBoard",
              workers: int | None, max_retries: int, on_iteration) -> None:
    import ray

    remote = ray.remote(_remote_trial)
    queue = list(todo)
    inflight: dict = {}  # ObjectRef -> TrialSpec
    for t in todo:
        p = out / t.relpath / PROGRESS
        old = read_json(p)
        if isinstance(old, dict) and old.get("state") == "running":  # left over from an interrupted sweep
            write_json(p, {**old, "state": "interrupted"}, out)
    try:
        while queue or inflight:
            while queue and (workers is None or len(inflight) < workers):
                t = queue.pop(0)
                ncpu = max(1, t.config.baseline.workers)
                ref = remote.options(num_cpus=ncpu, max_retries=max_retries, name=t.id).remote(
                    t, str(out / t.relpath), on_iteration, str(out))
                inflight[ref] = t
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
            for ref in ready:
                t = inflight.pop(ref)
                _finish(t, ref, out, status, board)
            _poll_running(inflight.values(), out, status, board)
    except BaseException:  # interrupted: stop the trials in flight; a rerun resumes them
        for ref, t in inflight.items():
            ray.cancel(ref, force=True)
            status.set(t.id, "pending", detail="interrupted")
        raise


def _finish(t: TrialSpec, ref, out: Path, status: _Status, board: "ProgressBoard") -> None:
    import ray

    try:
        res = ray.get(ref)
    except Exception as e:  # noqa: BLE001 - worker died past its retries, or Ray failed the task
        msg = f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}"
        files.write_text(out / t.relpath / ERROR, f"{t.id}\n{e}\n", anchor=out)
        res = {"status": "failed", "error": msg}
    if res["status"] == "done":
        status.set(t.id, "done", final_cost=res["final_cost"], wall_time=res["wall_time"], attempt=res["attempt"],
                   resumed_from=res["resumed_from"])
        board.set(t.id, "done", f"final cost {res['final_cost']:.6g} ({res['wall_time']:.1f}s"
                  + (f", resumed from iteration {res['resumed_from']}" if res["resumed_from"] else "") + ")")
    else:
        status.set(t.id, "failed", error=res["error"], error_file=str(t.relpath / ERROR))
        board.set(t.id, "failed", res["error"])
    status.write()


def _poll_running(inflight, out: Path, status: _Status, board: "ProgressBoard") -> None:
    changed = False
    for t in inflight:
        p = read_json(out / t.relpath / PROGRESS)
        if not isinstance(p, dict) or p.get("state") != "running":
            continue
        it, att = p.get("iteration"), p.get("attempt")
        att = att if type(att) is int else 1
        detail = f"iteration {it if type(it) is int else 0}/{p.get('iterations')}" + (
            f", attempt {att}" if att > 1 else "")
        if status.trials[t.id]["state"] != "running" or status.trials[t.id].get("detail") != detail:
            status.set(t.id, "running", detail=detail, attempt=att)
            board.set(t.id, "running", detail)
            changed = True
    if changed:
        status.write()


class ProgressBoard:
    """Live progress: one line per trial state and an overall bar (tqdm) on a terminal; plain
    lines (one per state change) otherwise."""

    def __init__(self, total: int, stream=None, live: bool | None = None):
        self.stream = stream or sys.stderr
        self.live = bool(self.stream.isatty()) if live is None else live
        self.total = total
        self.state: dict[str, str] = {}
        self.detail: dict[str, str] = {}
        self._shown: dict[str, str] = {}
        if self.live:
            from tqdm import tqdm

            size = dict(ncols=self._width() + 1, nrows=max(len(STATES) + 2, shutil.get_terminal_size((100, 20)).lines))
            self.bar = tqdm(total=total, desc="sweep", unit="trial", file=self.stream, position=0, leave=True, **size)
            self.lines = {s: tqdm(total=0, bar_format="{desc}", file=self.stream, position=i + 1, leave=True, **size)
                          for i, s in enumerate(STATES)}

    def set(self, tid: str, state: str, detail: str = "") -> None:
        old = self.state.get(tid)
        self.state[tid] = state
        self.detail[tid] = detail
        if self.live:
            if state in ("done", "failed") and old not in ("done", "failed"):
                self.bar.update(1)
            if state == "failed":
                self.bar.write(f"[failed] {tid}: {detail}", file=self.stream)
            self._render()
        elif self._shown.get(tid) != state:  # plain lines: state changes only
            self._shown[tid] = state
            if state != "pending":
                self._print(f"[{state}] {tid}" + (f": {detail}" if detail else ""))
                if state in ("done", "failed"):
                    self._print("progress: " + self._summary())

    def _summary(self) -> str:
        c = {s: sum(1 for v in self.state.values() if v == s) for s in STATES}
        finished = c["done"] + c["failed"]
        return f"{finished}/{self.total} finished (" + ", ".join(f"{s} {c[s]}" for s in STATES) + ")"

    def _print(self, line: str) -> None:
        print(line, file=self.stream, flush=True)

    @staticmethod
    def _width() -> int:
        return max(40, shutil.get_terminal_size((100, 20)).columns - 1)  # fallback when the size is unknown

    def _render(self) -> None:
        width = self._width()
        for s in STATES:
            ids = [t for t, v in self.state.items() if v == s]
            if s == "running":
                items = [f"{t} [{self.detail[t]}]" for t in ids]
            elif s == "failed":
                items = [f"{t}" for t in ids]
            else:
                items = ids
            text = f"{s:8s}{len(ids):4d}  " + ", ".join(items)
            self.lines[s].set_description_str(text[:width] if len(text) <= width else text[: width - 3] + "...")
        self.bar.refresh()

    def close(self) -> None:
        if self.live:
            self._render()
            self.bar.close()
            for line in self.lines.values():
                line.close()
