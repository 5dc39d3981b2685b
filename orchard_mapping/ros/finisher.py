"""Finishing a side in a child process, for the live odometry node (no rclpy here: the child never joins DDS).

While a finished side is bundle-adjusted, fused and its trunks modelled, the node goes on tracking the
next side from the camera topics. In a thread of the node's own process that work took Python's GIL for
whole GTSAM iterations and Open3D calls (up to 1.5 s at a time on the 2-tree test row, measured), the
node's subscriptions stopped taking frames and DDS dropped 16-22 of the next side's (1x, 2 cores). In a
child process it shares only the cores, at a lower priority (`CHILD_NICE`), so tracking the camera
comes first.

The child is started with `spawn` (the node's DDS threads must not be forked) as its side begins
(`FinishingProcess`: it imports the pipeline while the camera is tracked) and, once the side ends, gets the side's
handover (pipeline.SideHandover: the front end's result, the spooled keyframe images' folder, the
configuration, and the trunk detections made beside the front end in the node's process: by the
trunk_detector node or the configured detector, pipeline.EarlyDetections). The side map comes back whole
(pickled between the node's own processes).

With `grounds` given (the graph's local_ground_fitter node fits the trunks' grounds), the child stops once the
side is fused and sends the side's geometry (core.sidemap.SideGeometry, encoded as the message carries it);
`grounds` publishes it and waits for the node's answer, which goes back to the child, and the child fits the
trunk cylinders against it (pipeline.finish_side's `grounds_elsewhere`). An answer of None: the child fits
the grounds itself (the same fit: the same grounds).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import traceback
from collections.abc import Callable

from orchard_mapping.core.sidemap import SideGeometry, SideMap
from orchard_mapping.core.trunks import TrunkGround
from orchard_mapping.errors import OrchardMappingError
from orchard_mapping.io.sidemap_codec import encode_side_geometry
from orchard_mapping.pipeline import SideSession, Timings, finish_side

__all__ = ["CHILD_NICE", "FinishingProcess", "GeometryInfo", "SideFinishError", "finish_in_child"]

# What the parent is told of a side's geometry beside its encoded bytes: side, frame_id, stamp (s),
# keyframes, cloud_points
GeometryInfo = dict
# (the geometry's info, its bytes) -> the trunks' grounds fitted elsewhere, or None to fit them in the child
AskGrounds = Callable[[GeometryInfo, bytes], "list[TrunkGround] | None"]

CHILD_NICE = 5  # niceness added to the child: the camera's frames are tracked first


class SideFinishError(OrchardMappingError):
    """Finishing a side failed in the child process (the message says why; `detail` holds its traceback)."""

    def __init__(self, message: str, detail: str = "", typed: bool = True) -> None:
        super().__init__(message)
        self.detail = detail
        self.typed = typed  # the child raised an OrchardMappingError (bad input), not a bug


def _child(conn) -> None:
    """The finishing process: imports done (spawn imports this module), it waits for its side's handover."""
    try:
        os.nice(CHILD_NICE)
    except OSError:
        pass
    try:
        kind, payload = conn.recv()
    except (EOFError, KeyboardInterrupt):  # closed unused (the node stopped before another side ended)
        return
    if kind != "job":
        return
    job, ask_grounds = payload

    def grounds_from_parent(geometry: SideGeometry) -> "list[TrunkGround] | None":
        info = {"side": geometry.side, "frame_id": geometry.frame_id, "stamp": geometry.stamp,
                "keyframes": len(geometry.keyframe_poses), "cloud_points": len(geometry.cloud_points)}
        conn.send(("geometry", (info, encode_side_geometry(geometry))))
        kind, grounds = conn.recv()
        if kind != "grounds":
            raise SideFinishError(f"{geometry.side} side: the node answered {kind!r} to the side's geometry")
        return grounds

    try:
        timings = Timings()
        sm = finish_side(job, timings, grounds_from_parent if ask_grounds else None)
        conn.send(("done", (sm, dict(timings.stages))))
    except OrchardMappingError as err:
        conn.send(("error", (str(err), traceback.format_exc(), True)))
    except BaseException as err:  # noqa: BLE001 - reported to the parent with its traceback
        conn.send(("error", (f"{type(err).__name__}: {err}", traceback.format_exc(), False)))
    finally:
        conn.close()


class FinishingProcess:
    """A child process that finishes one side, started before that side ends.

    Spawning it and importing the pipeline (GTSAM, Open3D, onnxruntime) took about 5 s of a side's latency
    when the process was started at the side's end; the live node starts one as each side begins, while the
    camera is tracked, so the side's end waits only for the work."""

    def __init__(self, name: str = "finish") -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_child, args=(child,), name=name, daemon=True)
        self._proc.start()
        child.close()
        self._used = False

    def finish(self, session: SideSession, timings: Timings, grounds: AskGrounds | None = None) -> SideMap:
        """session.finish(timings) run in this process (once). Lets go of the keyframe images and stops the
        process. SideFinishError when the child failed or died."""
        if self._used:
            raise RuntimeError("a FinishingProcess finishes one side")
        self._used = True
        parent, proc = self._conn, self._proc
        try:
            try:
                parent.send(("job", (session.handover(), grounds is not None)))
            except (BrokenPipeError, EOFError, OSError):
                raise SideFinishError(f"{session.side} side: the process to finish it had died (exit code "
                                      f"{proc.exitcode})", typed=False) from None
            while True:
                try:
                    kind, payload = parent.recv()
                except EOFError:
                    proc.join(timeout=10)
                    raise SideFinishError(f"{session.side} side: the process finishing it died "
                                          f"(exit code {proc.exitcode})", typed=False) from None
                if kind == "geometry" and grounds is not None:
                    parent.send(("grounds", grounds(*payload)))
                elif kind == "done":
                    sm, stages = payload
                    for stage, seconds in stages.items():
                        timings.add(stage, seconds)
                    return sm
                else:
                    message, detail, typed = payload
                    raise SideFinishError(message, detail, typed)
        finally:
            self.close()
            session.images.close()

    def close(self) -> None:
        """Stop the process: once its imports are done when it waits for a side; at most 30 s when it is
        finishing one."""
        self._conn.close()
        self._proc.join(timeout=30)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()


def finish_in_child(session: SideSession, timings: Timings, grounds: AskGrounds | None = None,
                    process: FinishingProcess | None = None) -> SideMap:
    """session.finish(timings) run in a child process: `process`, started earlier, or else one started now.
    Lets go of the keyframe images. SideFinishError when the child failed or died. grounds: asked for the
    trunks' grounds once the side is fused (the module docstring); None: the child fits them."""
    return (process or FinishingProcess(f"finish-{session.side}")).finish(session, timings, grounds)
