"""A recording cut short: every whole message before the cut is read (io.salvage), the rest said lost."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_bags import T, write_rgbd

from orchard_mapping.errors import BagReadError
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.io.salvage import salvage_mcap


def _cut(folder: Path, keep: float, dst: Path) -> Path:
    """The bag folder's MCAP file cut after `keep` of its bytes (a recorder stopped abruptly), as a bare file."""
    src = next(folder.glob("*.mcap"))
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * keep)])
    return dst


def test_a_cut_recording_gives_its_frames_before_the_cut(tmp_path, caplog):
    stamps, colors, depths = write_rgbd(tmp_path / "bag", n=300, seed=3)
    cut = _cut(tmp_path / "bag", 0.6, tmp_path / "cut.mcap")
    with caplog.at_level(logging.WARNING, logger="orchard_mapping.io.salvage"):
        seq = read_rgbd(cut, T)
    n = len(seq)
    assert 50 < n < 300  # whole chunks before the cut, none after it
    np.testing.assert_allclose(seq.stamps, stamps[:n], atol=1e-9)  # a prefix of what was written, in order
    last = list(seq)[-1]
    np.testing.assert_array_equal(last.color, colors[n - 1])
    assert "cut short" in caplog.text and "lost" in caplog.text
    # a rosbag2 folder whose MCAP file was cut reads the same
    folder = tmp_path / "folder"
    folder.mkdir()
    shutil.copy(tmp_path / "bag" / "metadata.yaml", folder)
    _cut(tmp_path / "bag", 0.6, folder / next((tmp_path / "bag").glob("*.mcap")).name)
    assert len(read_rgbd(folder, T)) == n


def test_salvage_reports_what_it_kept_and_refuses_what_is_no_mcap(tmp_path):
    write_rgbd(tmp_path / "bag", n=120, seed=4)
    cut = _cut(tmp_path / "bag", 0.7, tmp_path / "cut.mcap")
    s = salvage_mcap(cut, tmp_path / "fixed.mcap")
    assert s.messages > 0 and s.lost_bytes > 0 and s.path.is_file()
    assert s.last_log_time_ns is not None
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 64)  # the magic, then nothing readable
    with pytest.raises(BagReadError, match="no whole message"):
        salvage_mcap(tmp_path / "junk.mcap", tmp_path / "junk_fixed.mcap")
    assert not (tmp_path / "junk_fixed.mcap").exists()  # no half-written output
    (tmp_path / "text.mcap").write_text("not a bag at all")
    with pytest.raises(BagReadError):
        read_rgbd(tmp_path / "text.mcap", T)
