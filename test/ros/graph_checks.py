"""What the node graph's tests share: launching the graph on the 2-tree fixture row (in process, or as a child
whose output is read line by line, to kill nodes at chosen moments), comparing its trees with the offline
run's, and a CPU hog to run beside it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from orchard_mapping.io.bags import iter_messages
from orchard_mapping.io.results import read_trees
from orchard_mapping.resources import config_dir

COLOUR = "/camera/color/image_raw"


def mask_params(sim: Path, path: Path, masks: Path | None = None, **extra) -> Path:
    """config/ros_params.yaml with trunks from the simulator's masks (and `extra` sections merged), written to
    path."""
    params = yaml.safe_load((config_dir() / "ros_params.yaml").read_text())
    p = params["/**"]["ros__parameters"]
    p["trunks"].update(source="masks", masks_dir=str(masks or sim / "masks"))
    for section, values in extra.items():
        p[section].update(values)
    path.write_text(yaml.safe_dump(params))
    return path


def odometry_status(rec: Path) -> dict:
    """The last status the odometry node published, from a recording."""
    return [json.loads(m.data) for _, m in iter_messages(rec, "/orchard/odometry/status")][-1]


def same_trees(rec: Path, out: Path, offline: Path) -> None:
    """The trees the graph published (decoded from the recording) and wrote are the offline run's: same ids,
    flags and per-side trunk ids, positions within 1 cm, diameters within 1 mm, heights within 1 cm, canopy
    volumes within 2 %."""
    offline_trees = read_trees(offline / "trees.json")
    msgs = [m for _, m in iter_messages(rec, "/orchard/trees")]
    assert len(msgs) == 1 and msgs[0].header.frame_id == "map", len(msgs)
    live = msgs[0].trees
    assert len(live) == len(offline_trees) >= 2, (len(live), len(offline_trees))
    for m, t in zip(live, offline_trees, strict=True):
        assert m.tree_id == t.id and list(m.flags) == list(t.flags), (m, t)
        pos = np.array([m.position.x, m.position.y, m.position.z])
        assert np.linalg.norm(pos - np.array(t.position)) < 0.01, (pos, t.position)  # 1 cm
        if t.trunk_diameter_m is None:
            assert np.isnan(m.trunk_diameter)
        else:
            assert abs(m.trunk_diameter - t.trunk_diameter_m) < 1e-3, (m.trunk_diameter, t.trunk_diameter_m)  # 1 mm
        # height and canopy volume as offline (the same merge_and_measure on side maps equal within 1 mm)
        assert t.height_m is not None and abs(m.height - t.height_m) < 0.01, (m.height, t.height_m)  # 1 cm
        assert t.canopy_volume_m3 is not None and abs(m.canopy_volume - t.canopy_volume_m3) < 0.02 * t.canopy_volume_m3
        assert m.fruit_count == -1  # not measured yet, as offline (null)
        for side in ("front", "back"):
            own = (t.per_side or {}).get(side)
            assert getattr(m, f"trunk_id_{side}") == (own["trunk_id"] if own else -1)
    written = read_trees(out / "trees.json")
    assert [(w.id, w.flags) for w in written] == [(t.id, t.flags) for t in offline_trees]
    assert max(np.linalg.norm(np.subtract(w.position, t.position)) for w, t in zip(written, offline_trees, strict=True)) < 0.01


def node_pids(module: str) -> list[int]:
    """The running processes of `python -m orchard_mapping.ros.<module>` (the node itself, not what it started)."""
    want = f"orchard_mapping.ros.{module}".encode()
    pids = []
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            argv = (p / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if len(argv) > 2 and argv[1] == b"-m" and argv[2] == want:
            pids.append(int(p.name))
    return pids


def children(pid: int) -> list[int]:
    """The processes whose parent is pid."""
    out = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if int((p / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(p.name))
            except (OSError, IndexError, ValueError):
                pass
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def kill_node(module: str) -> tuple[int, list[int]]:
    """SIGKILL the one running node process of `module`: its pid and the processes it had started."""
    pids = node_pids(module)
    assert len(pids) == 1, (module, pids)
    kids = children(pids[0])
    os.kill(pids[0], signal.SIGKILL)
    return pids[0], kids


def launch_and_kill(args: list[str], kills: list[tuple[Callable[[str], bool], tuple[str, ...]]],
                    env: dict[str, str] | None = None, timeout_s: float = 1500,
                    orphans: list[int] | None = None, killed_at: dict[str, float] | None = None
                    ) -> tuple[int, str, list[str]]:
    """Run `orchard-map launch ARGS` as a child, reading its output line by line; at the first line for which
    a kill's predicate holds, SIGKILL the nodes it names (each kill once, in order). Returns the exit code,
    the whole output and the nodes killed; `orphans` gets the processes the killed nodes had started,
    `killed_at` the system time (s) of each kill."""
    proc = subprocess.Popen([sys.executable, "-m", "orchard_mapping.cli.main", "launch", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=None if env is None else {**os.environ, **env})
    lines, killed, todo = [], [], list(kills)
    t0 = time.monotonic()
    try:
        for line in proc.stdout:
            lines.append(line)
            if todo and todo[0][0](line):
                for module in todo.pop(0)[1]:
                    _, kids = kill_node(module)
                    killed.append(module)
                    if killed_at is not None:
                        killed_at[module] = time.time()
                    if orphans is not None:
                        orphans.extend(kids)
                    lines.append(f"[test] killed {module}\n")
            if time.monotonic() - t0 > timeout_s:
                break
        rc = proc.wait(timeout=max(1.0, timeout_s - (time.monotonic() - t0)))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return rc, "".join(lines), killed


class CpuHog:
    """`n` busy-loop processes beside a test (each spins for at most `limit_s`, and is killed when the test
    ends): the graph's result must not depend on the machine's load."""

    def __init__(self, n: int = 2, limit_s: float = 1200.0) -> None:
        code = f"import time\nend = time.monotonic() + {limit_s}\nwhile time.monotonic() < end:\n    pass\n"
        self.procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]

    def cpu_seconds(self) -> float:
        """CPU seconds the hog took so far (user + system, from /proc)."""
        total = 0.0
        for p in self.procs:
            try:
                fields = Path(f"/proc/{p.pid}/stat").read_text().rsplit(")", 1)[1].split()
                total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            except (OSError, IndexError, ValueError):
                pass
        return total

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait()
