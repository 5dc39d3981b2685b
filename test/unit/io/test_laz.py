"""io.laz: trees.laz written and read back: coordinates at 0.1 mm, colours, classes, tree ids, sides."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.io.laz import CLASS, LAZ_SCALE_M, SIDE_CODE, LazWriteError, read_laz, write_laz


def _cloud(n: int, seed: int):
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-1.0, -2.0, -0.5], [12.0, 2.0, 3.0], (n, 3))
    cols = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    cls = rng.choice(list(CLASS.values()), n).astype(np.uint8)
    tree = rng.integers(-1, 10, n)
    side = rng.choice(list(SIDE_CODE.values()), n).astype(np.uint8)
    return pts, cols, cls, tree, side


@pytest.mark.parametrize("seed", [0, 1])
def test_trees_laz_round_trips_every_field(tmp_path, seed):
    pts, cols, cls, tree, side = _cloud(5000, seed)
    path = write_laz(tmp_path / "trees.laz", pts, cols, cls, tree, side)
    assert path.stat().st_size < pts.nbytes  # compressed
    got = read_laz(path)
    assert np.max(np.abs(got["points"] - pts)) <= LAZ_SCALE_M / 2 + 1e-9
    assert np.array_equal(got["colors"], cols)
    assert np.array_equal(got["classification"], cls)
    assert np.array_equal(got["tree_id"], tree)
    assert np.array_equal(got["side"], side)
    assert [p.name for p in tmp_path.iterdir()] == ["trees.laz"]  # no temporary file left
    assert path.stat().st_mode & 0o777 == 0o644


def test_the_header_names_the_local_frame_and_no_crs(tmp_path):
    import laspy

    pts, cols, cls, tree, side = _cloud(10, 2)
    las = laspy.read(str(write_laz(tmp_path / "t.laz", pts, cols, cls, tree, side)))
    assert las.header.system_identifier.startswith("orchard_mapping map")
    assert las.header.parse_crs() is None
    assert las.header.version.major == 1 and las.header.version.minor == 4


def test_the_creation_day_is_the_recordings_not_todays(tmp_path):
    """The header's creation day comes from the recording's stamp (UTC), so the same recording gives the same
    bytes on any day (laspy writes today's date unless told)."""
    import datetime

    import laspy

    pts, cols, cls, tree, side = _cloud(10, 4)
    a = write_laz(tmp_path / "a.laz", pts, cols, cls, tree, side, recorded_s=1700000000.0)  # 2023-11-14 22:13 UTC
    assert laspy.read(str(a)).header.creation_date == datetime.date(2023, 11, 14)
    assert write_laz(tmp_path / "b.laz", pts, cols, cls, tree, side, recorded_s=1700000000.0).read_bytes() == a.read_bytes()


def test_arrays_that_disagree_are_named(tmp_path):
    pts, cols, cls, tree, side = _cloud(10, 3)
    with pytest.raises(LazWriteError, match="tree_id has shape"):
        write_laz(tmp_path / "t.laz", pts, cols, cls, tree[:5], side)
    pts[3, 1] = np.nan
    with pytest.raises(LazWriteError, match="non-finite"):
        write_laz(tmp_path / "t.laz", pts, cols, cls, tree, side)
    assert not list(tmp_path.iterdir())
