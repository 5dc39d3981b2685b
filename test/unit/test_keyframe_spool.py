"""Where the live odometry node spools its keyframe images: a folder named after its process, and under a
folder the caller names (the live graph's scratch folder) the folders of processes no longer running are
removed when a new spool is made, so a node killed mid-row and started again leaves nothing behind."""

from __future__ import annotations

import os
import subprocess
import sys

from orchard_mapping.pipeline.sides import SPOOL_PREFIX, SpooledKeyframeImages


def _dead_pid() -> int:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True)
    return int(done.stdout)


def test_a_new_spool_removes_those_of_processes_no_longer_running(tmp_path):
    dead = tmp_path / f"{SPOOL_PREFIX}{_dead_pid()}-abc123"
    dead.mkdir()
    (dead / "00000001_depth.npy").write_bytes(b"x" * 100)
    live = tmp_path / f"{SPOOL_PREFIX}{os.getpid()}-def456"  # this process's: in use
    live.mkdir()
    older = tmp_path / f"{SPOOL_PREFIX}q1w2e3r4"  # named before folders carried their process: not judged
    older.mkdir()
    spool = SpooledKeyframeImages(tmp_path)
    try:
        assert not dead.exists() and live.is_dir() and older.is_dir()
        assert spool.dir.parent == tmp_path and spool.dir.name.startswith(f"{SPOOL_PREFIX}{os.getpid()}-")
    finally:
        spool.close()
    assert not spool.dir.exists()


def test_the_system_temp_folder_is_left_alone(tmp_path, monkeypatch):
    """Without a folder named, the spool goes to the system's temporary folder, which others may share: nothing
    there is removed."""
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)  # read TMPDIR again
    dead = tmp_path / f"{SPOOL_PREFIX}{_dead_pid()}-abc123"
    dead.mkdir()
    spool = SpooledKeyframeImages()
    try:
        assert dead.is_dir() and spool.dir.parent == tmp_path
    finally:
        spool.close()
