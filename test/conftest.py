"""Project-wide pytest set-up.

Every process that starts rclpy in the tests keeps DDS discovery on loopback.
This is forced here, at import time, before any test module imports rclpy;
child processes inherit it. (On a vehicle users choose their own discovery
settings: only the tests, CI, the Makefile and the launcher force it.)

Portability switches (`make test-portable`; `make test` runs with none set). Results must not hinge
on the processor: another CPU takes other SIMD paths in OpenCV, so these switches move results the
way another machine would, and the accuracy tests must still pass with margin.
- ORCHARD_TEST_CV=noopt: OpenCV's optimised code paths off (cv2.setUseOptimized(False)).
- ORCHARD_TEST_CV=threads1: OpenCV on one thread (cv2.setNumThreads(1)).
- ORCHARD_TEST_SEED_OFFSET=N: the accuracy tests' simulated rows use their seed + N.
- ORCHARD_ACCURACY_LOG=FILE: every accuracy check appends a JSON line (test, quantity, value, limit,
  switches) to FILE; scripts/accuracy_table.py turns the lines of several runs into one table.
The BLAS settings of the machine are left as they are.

Accuracy checks go through the `accuracy` fixture: it asserts, records the value and its limit, and
the terminal summary lists every check with its margin; a check within 20 % of its limit is marked
fragile there (and is not acceptable: make the algorithm more robust, never only the limit wider).
"""

import json
import os
import random
import shutil
from contextlib import contextmanager

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

# One random ROS domain per test session (forced, like the discovery range), so
# that concurrent test runs on one machine (two developers, CI) never see each
# other's topics. 1..101 are domain ids safe on Linux for any participant count.
# `make test` runs the files on pytest-xdist workers: the controller draws the session's domain and each
# worker (which inherits the controller's environment) takes the next ones, so two workers' graphs never meet.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw0", "gw1", ... on a worker; "" otherwise
if _WORKER and "ORCHARD_TEST_DOMAIN" in os.environ:
    os.environ["ROS_DOMAIN_ID"] = str(1 + (int(os.environ["ORCHARD_TEST_DOMAIN"]) + int(_WORKER[2:])) % 101)
else:
    os.environ["ORCHARD_TEST_DOMAIN"] = str(random.SystemRandom().randint(0, 100))
    os.environ["ROS_DOMAIN_ID"] = str(1 + int(os.environ["ORCHARD_TEST_DOMAIN"]))

import cv2  # noqa: E402
import pytest  # noqa: E402

from orchard_mapping.pipeline.sides import process_alive  # noqa: E402

CV_SWITCH = os.environ.get("ORCHARD_TEST_CV", "")
SEED_OFFSET = int(os.environ.get("ORCHARD_TEST_SEED_OFFSET", "0") or 0)
if CV_SWITCH not in ("", "noopt", "threads1"):
    raise pytest.UsageError(f"ORCHARD_TEST_CV={CV_SWITCH!r}: expected '', 'noopt' or 'threads1'")
if CV_SWITCH == "noopt":
    cv2.setUseOptimized(False)
elif CV_SWITCH == "threads1":
    cv2.setNumThreads(1)
FRAGILE_FRACTION = 0.2  # a value within 20 % of its limit is fragile
_RECORDS: list[dict] = []


def switches() -> str:
    parts = [f"cv={CV_SWITCH}"] if CV_SWITCH else []
    if SEED_OFFSET:
        parts.append(f"seed+{SEED_OFFSET}")
    return " ".join(parts) or "default"


def pytest_configure(config):
    config.addinivalue_line("markers", "accuracy: checks accuracy against the simulator's truth "
                                       "(repeated by make test-portable)")
    config.addinivalue_line("markers", "slow: end-to-end runs of minutes each (the live graph's fault replays, a "
                                       "block drive, same bytes twice): `make test-slow`, not `make test`; CI runs both")


@pytest.fixture(scope="session", autouse=True)
def _prune_ended_sessions(tmp_path_factory) -> None:
    """Remove the temporary folders of earlier test sessions that have ended before this one writes its own.
    pytest keeps the folders of the last sessions and prunes older ones only at exit; a full run writes
    ~4 GB of simulated rows, and on a machine that runs the suite again and again (CI) the kept folders
    filled its disk during the next run (a CI run once failed with "No space left on device"). A folder whose
    session is still running (its `.lock` names a live process) is left alone."""
    base = _session_temp(tmp_path_factory)
    if base.parent.name != f"pytest-of-{_user()}":
        return  # --basetemp given: pytest empties that folder itself
    for old in base.parent.glob("pytest-*"):
        if old == base or not old.name[len("pytest-"):].isdigit() or old.is_symlink():
            continue
        try:
            pid = int((old / ".lock").read_text())
        except (OSError, ValueError):
            pid = None  # no lock: the session ended (or never took one)
        if pid is not None and process_alive(pid):
            continue
        shutil.rmtree(old, ignore_errors=True)


def _session_temp(tmp_path_factory):
    """The session's temporary folder, the same for every xdist worker (each worker's own is a folder in it)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if _WORKER else base


@contextmanager
def _made_once(tmp_path_factory, name: str):
    """`with _made_once(factory, name) as (folder, made):` a session fixture's folder that every xdist worker
    shares: the first worker to come makes it (made False: fill it) while the others wait on a file lock, and
    they then read it (made True). Without xdist: a new folder, made False."""
    import fcntl

    root = _session_temp(tmp_path_factory)
    if not _WORKER:
        yield tmp_path_factory.mktemp(name), False
        return
    folder, done = root / f"shared_{name}", root / f"shared_{name}.done"
    with open(root / f"shared_{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # held while the folder is made; released at the end of the block
        if done.is_file():
            yield folder, True
            return
        shutil.rmtree(folder, ignore_errors=True)  # a worker that failed half way left it
        folder.mkdir()
        yield folder, False
        done.touch()


def _user() -> str:
    import getpass

    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return "unknown"


@pytest.fixture(scope="session")
def scratch(tmp_path_factory):
    """`with scratch(name) as folder:` a folder for a module- or session-scoped fixture's simulated row,
    removed when the fixture is torn down (pytest otherwise keeps every row, ~0.35 GB a side, to the end
    of the session)."""

    @contextmanager
    def make(name: str):
        path = tmp_path_factory.mktemp(name)
        try:
            yield path
        finally:
            shutil.rmtree(path, ignore_errors=True)

    return make


@pytest.fixture(scope="session")
def seed_offset() -> int:
    """Added to the seeds of the accuracy tests' simulated rows (ORCHARD_TEST_SEED_OFFSET)."""
    return SEED_OFFSET


@pytest.fixture(scope="session")
def standard_row(tmp_path_factory, seed_offset):
    """The 2-tree `standard` row (15 Hz, both sweeps of the paper's protocol, true trunk masks for every
    frame) and `orchard_mapping.pipeline.run` on it with trunks from those masks: (sim folder, result
    folder). Shared by the single-side tests and the node graph's (which must give the same trees)."""
    from orchard_mapping.config import load_config
    from orchard_mapping.pipeline import run
    from orchard_mapping.sim.scenario import load_scenario
    from orchard_mapping.sim.simulate import simulate

    with _made_once(tmp_path_factory, "standard") as (root, made):
        sim, out = root / "standard", root / "result"
        if not made:
            sc = load_scenario("standard", {"row.n_trees": 2, "camera.rate_hz": 15, "masks_every": 1})
            sim = simulate(sc, 11 + seed_offset, sim).out_dir
            run(sim / "front", sim / "back", out,
                load_config(overrides={"trunks": {"source": "masks", "masks_dir": str(sim / "masks")}}))
    return sim, out


@pytest.fixture(scope="session")
def loop_row(tmp_path_factory, seed_offset):
    """The 2-tree `loop` row (one continuous drive round the row in one bag, 15 Hz, true trunk masks for
    every frame) and `run` on that one bag with its sides told by the camera's U-turn
    (input.side_source=trajectory: the bag's side topic is ignored) and trunks from the masks: (sim folder,
    result folder). Shared by the single-side tests and the node graph's."""
    from orchard_mapping.config import load_config
    from orchard_mapping.pipeline import run
    from orchard_mapping.sim.scenario import load_scenario
    from orchard_mapping.sim.simulate import simulate

    with _made_once(tmp_path_factory, "loop") as (root, made):
        sim, out = root / "loop", root / "result"
        if not made:
            sc = load_scenario("loop", {"row.n_trees": 2, "camera.rate_hz": 15, "masks_every": 1})
            sim = simulate(sc, 11 + seed_offset, sim).out_dir
            # with the trunk worker process, as `orchard-map run` does: the drive's sides finish one after the other
            run(sim / "loop", None, out, load_config(overrides={
                "input": {"side_source": "trajectory"},
                "trunks": {"source": "masks", "masks_dir": str(sim / "masks" / "loop")}}), trunk_worker=True)
    return sim, out


class Accuracy:
    """Asserts a measured value against its limit and records both (see the module docstring)."""

    def __init__(self, nodeid: str) -> None:
        self.nodeid = nodeid

    def _record(self, quantity: str, value: float, limit: float, kind: str) -> None:
        value, limit = float(value), float(limit)
        if kind == "max":
            ok, fragile = value <= limit, value > (1 - FRAGILE_FRACTION) * limit
        else:
            ok, fragile = value >= limit, value < (1 + FRAGILE_FRACTION) * limit
        rec = dict(test=self.nodeid, quantity=quantity, value=value, limit=limit, kind=kind, ok=ok,
                   fragile=fragile, switches=switches())
        _RECORDS.append(rec)
        log = os.environ.get("ORCHARD_ACCURACY_LOG")
        if log:
            with open(log, "a") as f:
                f.write(json.dumps(rec) + "\n")
        sign = "<=" if kind == "max" else ">="
        assert ok, f"{quantity}: {value:.6g} not {sign} {limit:.6g}"

    def at_most(self, quantity: str, value: float, limit: float) -> None:
        self._record(quantity, value, limit, "max")

    def at_least(self, quantity: str, value: float, limit: float) -> None:
        self._record(quantity, value, limit, "min")


@pytest.fixture
def accuracy(request) -> Accuracy:
    return Accuracy(request.node.nodeid)


def pytest_sessionfinish(session):
    """On an xdist worker: hand this worker's accuracy checks to the controller, which prints them all."""
    if _WORKER and hasattr(session.config, "workeroutput"):
        session.config.workeroutput["orchard_accuracy"] = json.dumps(_RECORDS)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """On the xdist controller: a worker's accuracy checks (pytest_sessionfinish above)."""
    _RECORDS.extend(json.loads(getattr(node, "workeroutput", {}).get("orchard_accuracy", "[]")))


def pytest_terminal_summary(terminalreporter):
    if not _RECORDS:
        return
    tr = terminalreporter
    tr.section(f"accuracy checks ({switches()})")
    for r in _RECORDS:
        sign = "<=" if r["kind"] == "max" else ">="
        used = r["value"] / r["limit"] if r["limit"] else float("inf")
        flag = "FAIL" if not r["ok"] else ("FRAGILE" if r["fragile"] else "ok")
        name = r["test"].split("::", 1)[-1]
        tr.write_line(f"{flag:8s} {name[:60]:60s} {r['quantity'][:40]:40s} {r['value']:10.4g} {sign} "
                      f"{r['limit']:<8.4g} ({100 * used:5.1f} % of limit)")


@pytest.fixture
def out_dir(tmp_path):
    """An empty folder for a test's outputs (removed by pytest's tmp_path policy)."""
    d = tmp_path / "out"
    d.mkdir()
    return d


def write_constant_detector(path, values, *, outputs=("boxes", "labels", "scores", "masks"), input_shape=None,
                            input_type=None):
    """An ONNX model that follows docs/detector.md's contract and returns fixed detections: values maps
    boxes, labels, scores, masks to arrays (written as outputs named `outputs`, in that order). The input
    ("image", (3, H, W) float32 unless said) feeds nothing, so the runtime's pre- and post-processing and
    whatever scores its output are checked exactly."""
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper, save

    names = ("boxes", "labels", "scores", "masks")
    if input_shape is None:
        input_shape = [3, 48, 64]
    nodes = [helper.make_node("Constant", [], [out], value=numpy_helper.from_array(np.asarray(values[src]), src))
             for out, src in zip(outputs, names, strict=False)]  # strict=False: a shorter `outputs` leaves the last out
    outs = [helper.make_tensor_value_info(o, TensorProto.INT64 if s == "labels" else TensorProto.FLOAT,
                                          list(np.shape(values[s]))) for o, s in zip(outputs, names, strict=False)]
    graph = helper.make_graph(nodes, "const_detector", [helper.make_tensor_value_info(
        "image", TensorProto.FLOAT if input_type is None else input_type, input_shape)], outs)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    save(model, path)
    return path


@pytest.fixture
def constant_detector():
    """write_constant_detector (needs the onnx package: tests using it importorskip it)."""
    return write_constant_detector
