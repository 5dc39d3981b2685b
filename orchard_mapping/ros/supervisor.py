"""The project's own launcher: starts each node of the graph as its own process and watches them.

`launch`/`launch_ros` are not on PyPI, so `orchard-map launch` uses this (launch files for `ros2 launch`
on a full ROS 2 install live in `launch/`). What it does:
- each node is `python -m orchard_mapping.ros.<module> ...` in its own process (and session, so a
  stop reaches the nodes in the order the supervisor chooses), with the supervisor's environment: the
  discovery settings are the caller's (the Makefile, the tests and CI set loopback-only discovery; on
  a vehicle the user chooses), plus the project's Fast DDS profile for large messages unless the
  caller names one (`FASTRTPS_DEFAULT_PROFILES_FILE`);
- every line a node prints is printed with the node's name in front;
- SIGINT or SIGTERM stops the graph cleanly: SIGTERM to every node but those marked `stop_last` (the
  recorder), then, once they have exited, to those: a node exits only once its subscribers acknowledged
  what it published (ros/spin.py), so the recorder has everything when it is told to stop. SIGKILL to a node
  still running after `stop_timeout_s` (a guard against a node that hangs); exit code 0;
- a node that dies is reported (name, exit code) and what it started goes with it (its process group is
  killed: a side's finishing process, for instance); if its spec allows restarts it is started again (at
  most `max_restarts` times), else the graph is stopped and the supervisor exits 1; the nodes its spec names
  in `restart_with` are stopped (if still running) and started again from their beginning with it;
- the graph's scratch folder (`scratch`: the odometry node's keyframe spool, its input journal) is made
  before the first node starts, named to every node in ORCHARD_GRAPH_SCRATCH, kept across a node's
  restarts, and removed when the graph ends;
- a node marked `ends_graph` (the trait reporter replaying a bag: it exits when the last report is
  written) stops the graph when it exits with 0: exit code 0.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from orchard_mapping.errors import OrchardMappingError
from orchard_mapping.resources import config_dir

__all__ = ["SCRATCH_ENV", "NodeSpec", "Supervisor", "graph_environment"]

log = logging.getLogger(__name__)

FASTDDS_PROFILE = "fastdds_large_messages.xml"  # in config/: a 64 MB shared-memory segment (docs/ros.md)
SCRATCH_ENV = "ORCHARD_GRAPH_SCRATCH"  # the graph's scratch folder, for every node (removed when the graph ends)
SCRATCH_PREFIX = "orchard-graph-"


@dataclass(frozen=True)
class NodeSpec:
    name: str
    module: str  # under orchard_mapping.ros, e.g. "player"
    args: tuple[str, ...] = ()
    restart: bool = False  # start it again when it dies
    ends_graph: bool = False  # its clean exit (code 0) ends the graph
    finite: bool = False  # it may end by itself with 0 (a bag player): not a death
    stop_last: bool = False  # stopped once every other node has exited (the recorder: it takes what they sent)
    # nodes started again from their beginning with this one's restart (the odometry node on a replay: the bag
    # player, so the new node receives the whole recording, not the rest of it)
    restart_with: tuple[str, ...] = ()
    # exit codes that say the node's work failed for good (a refused merge, a side that cannot be mapped): the
    # graph stops with 1, the node is not started again (it would fail the same way)
    final_codes: tuple[int, ...] = ()


@dataclass
class _Running:
    spec: NodeSpec
    proc: subprocess.Popen
    restarts: int = 0
    started: float = field(default_factory=time.monotonic)


def graph_environment(base: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of every node process: the caller's, plus the project's Fast DDS profile for large
    messages unless the caller names one."""
    env = dict(os.environ if base is None else base)
    if "FASTRTPS_DEFAULT_PROFILES_FILE" not in env:
        profile = config_dir() / FASTDDS_PROFILE
        if profile.is_file():
            env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
    env.setdefault("PYTHONUNBUFFERED", "1")  # node output reaches the log line by line
    return env


class Supervisor:
    def __init__(self, specs: list[NodeSpec], *, env: dict[str, str] | None = None, max_restarts: int = 3,
                 stop_timeout_s: float = 30.0, out=None, scratch_root: str | Path | None = None) -> None:
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise OrchardMappingError(f"node names must be unique: {names}")
        self.specs = specs
        self.env = graph_environment(env)
        self.max_restarts = max_restarts
        self.stop_timeout_s = stop_timeout_s
        self.out = out or sys.stdout
        self.running: dict[str, _Running] = {}
        self.events: list[str] = []  # what happened to the nodes (deaths, restarts), in order
        self._stop = threading.Event()
        self._print_lock = threading.Lock()
        self.scratch_root = scratch_root
        self.scratch: Path | None = None  # made by run(), removed when it returns

    # -- output

    def _say(self, line: str) -> None:
        with self._print_lock:
            print(line, file=self.out, flush=True)

    def _event(self, text: str) -> None:
        self.events.append(text)
        self._say(f"[supervisor] {text}")

    def _pump(self, name: str, stream) -> None:
        for line in iter(stream.readline, ""):
            self._say(f"[{name}] {line.rstrip()}")
        stream.close()

    # -- processes

    def _start(self, spec: NodeSpec) -> subprocess.Popen:
        cmd = [sys.executable, "-m", f"orchard_mapping.ros.{spec.module}", *spec.args]
        proc = subprocess.Popen(cmd, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)
        threading.Thread(target=self._pump, args=(spec.name, proc.stdout), daemon=True).start()
        return proc

    def pids(self) -> dict[str, int]:
        return {name: r.proc.pid for name, r in self.running.items()}

    def stop(self) -> None:
        """Ask the supervisor's loop to stop the graph (thread-safe; also what SIGINT/SIGTERM do)."""
        self._stop.set()

    def _stop_all(self) -> None:
        names = list(reversed(list(self.running)))
        self._stop_nodes([n for n in names if not self.running[n].spec.stop_last])
        self._stop_nodes([n for n in names if self.running[n].spec.stop_last])

    def _stop_nodes(self, names: list[str]) -> None:
        self._stop_nodes_of({name: self.running[name] for name in names})

    def _stop_nodes_of(self, nodes: "dict[str, _Running]") -> None:
        for r in nodes.values():
            if r.proc.poll() is None:
                r.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.stop_timeout_s
        for name, r in nodes.items():
            try:
                r.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._event(f"{name} did not stop in {self.stop_timeout_s:.0f} s: killed")
                r.proc.kill()
                r.proc.wait()
            _kill_group(r.proc.pid)  # what it started and left behind (a side's finishing process)

    def _start_again(self, name: str) -> None:
        """Stop node `name` if it runs and start it again from its beginning (restart_with)."""
        spec = next((s for s in self.specs if s.name == name), None)
        if spec is None:
            return
        old = self.running.pop(name, None)
        if old is not None:
            self._stop_nodes_of({name: old})
        self.running[name] = _Running(spec, self._start(spec), old.restarts if old is not None else 0)
        self._event(f"{name} started again from its beginning")

    def run(self, poll_s: float = 0.2) -> int:
        """Start the graph and watch it until it ends: 0 (stopped, or an ends_graph node finished), 1 (a node
        died that may not restart)."""
        handlers = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                handlers[sig] = signal.signal(sig, lambda *_: self._stop.set())
        self.scratch = Path(tempfile.mkdtemp(prefix=f"{SCRATCH_PREFIX}{os.getpid()}-", dir=self.scratch_root))
        self.env[SCRATCH_ENV] = str(self.scratch)
        try:
            for spec in self.specs:
                self.running[spec.name] = _Running(spec, self._start(spec))
            self._say(f"[supervisor] started {', '.join(f'{n} (pid {p})' for n, p in self.pids().items())}")
            code = self._watch(poll_s)
        finally:
            try:
                self._stop_all()
            finally:
                shutil.rmtree(self.scratch, ignore_errors=True)
                for sig, h in handlers.items():
                    signal.signal(sig, h)
        return code

    def _watch(self, poll_s: float) -> int:
        while not self._stop.wait(poll_s):
            for name, r in list(self.running.items()):
                if self.running.get(name) is not r:  # started again meanwhile (restart_with)
                    continue
                rc = r.proc.poll()
                if rc is None:
                    continue
                spec = r.spec
                if rc == 0 and spec.ends_graph:
                    self._event(f"{name} finished: stopping the graph")
                    return 0
                if rc == 0 and spec.finite:
                    self._event(f"{name} finished")
                    del self.running[name]
                    continue
                _kill_group(r.proc.pid)  # what it started goes with it (a side's finishing process)
                if rc in spec.final_codes:
                    self._event(f"{name} failed (exit code {rc}): stopping the graph")
                    return 1
                self._event(f"{name} died (exit code {rc})")
                if spec.restart and r.restarts < self.max_restarts:
                    self.running[name] = _Running(spec, self._start(spec), r.restarts + 1)
                    self._event(f"{name} restarted ({r.restarts + 1} of at most {self.max_restarts})")
                    for other in spec.restart_with:
                        self._start_again(other)
                    continue
                self._event(f"stopping the graph: {name} may not be restarted")
                return 1
        return 0



def _kill_group(pgid: int) -> None:
    """SIGKILL what is left of a node's process group (each node is started in a session of its own, so the
    group is the node and what it started); nothing if none is left."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
