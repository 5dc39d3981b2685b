"""The side map's bytes (io.sidemap_codec): exact round trip, and clear errors for bytes that are not one."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from orchard_mapping.core.cylinder import Cylinder, CylinderFit, CylinderView
from orchard_mapping.core.detection import Detection
from orchard_mapping.core.fruit import SideFruit
from orchard_mapping.core.ground import LocalGroundFit
from orchard_mapping.core.posts import PostLandmark, PostObservation
from orchard_mapping.core.sidemap import LoopClosure, Observations, SideMap
from orchard_mapping.core.trunks import TrunkLandmark, TrunkObservation
from orchard_mapping.core.types import CameraIntrinsics, ImagePatch
from orchard_mapping.io.sidemap_codec import SideMapFormatError, decode_side_map, encode_side_map


def _side_map(rng: np.random.Generator) -> SideMap:
    K = 5
    poses = np.repeat(np.eye(4)[None], K, axis=0)
    poses[:, 0, 3] = np.linspace(0, 1, K)
    mask = np.zeros((48, 64), bool)
    mask[10:40, 20:30] = True
    depth = rng.uniform(0.5, 2.0, (48, 64)).astype(np.float32)
    det = Detection(0, 0.93, np.array([20.0, 10.0, 30.0, 40.0]), ImagePatch.crop(mask, (8, 18, 42, 32)))
    cyl = Cylinder(np.array([0.0, -1.0, 0.0]), np.array([0.1, 0.2, 1.5]), 0.041)
    fit = CylinderFit(cyl, 120, 0.002, 0.8, 300, True)
    ground = LocalGroundFit(np.array([0.0, -1.0, 0.0]), 0.9, np.array([0.1, 0.9, 1.5]), 200, 0.004, 400,
                            support_offset_m=float("nan"))
    lm = TrunkLandmark(
        id=0, axis=np.array([0.0, -1.0, 0.0]), base=np.array([0.1, 0.9, 1.5]), length_m=0.7, ground=ground,
        band=fit, diameter_m=0.082, baseline_band=None, n_points=900,
        observations=[TrunkObservation(2, 0.4, det, cyl, 250)], flags=["no_ground"],
        band_points=rng.normal(size=(30, 3)), band_normals=rng.normal(size=(30, 3)),
        band_views=[CylinderView(np.eye(4), ImagePatch.crop(mask, (8, 18, 42, 32)),
                                 ImagePatch.crop(depth, (8, 18, 42, 32)))],
        merge_axis=np.array([0.0, -0.99, 0.01]), taper=-0.01)
    return SideMap(
        side="front", frame_id="odom_front",
        intrinsics=CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5, (0.01, 0.0, 0.0, 0.0, 0.0)),
        keyframe_stamps=np.arange(K) * 0.2 + 100.0, keyframe_poses=poses,
        landmarks=rng.normal(size=(7, 3)),
        observations=Observations(np.array([0, 1], np.int64), np.array([3, 4], np.int64), rng.normal(size=(2, 2)),
                                  np.array([1.0, 0.0])),
        loops=[LoopClosure(0, 4, np.eye(4), 40, 0.7)],
        cloud_points=rng.normal(size=(100, 3)).astype(np.float32),
        cloud_colors=rng.integers(0, 255, (100, 3), dtype=np.uint8),
        odometry_poses=poses.copy(), trunks=[lm],
        posts=[PostLandmark(0, np.array([1.0, 0.5, 2.0]), 0.049, [PostObservation(
            3, np.array([0.0, -1.0, 0.0]), np.array([0.2, 0.1, 2.0]), 0.047, 1.2, 800,
            rng.normal(size=(20, 3)).astype(np.float32))])],
        fruit=SideFruit("front", rng.normal(size=(5, 3)), rng.uniform(0.06, 0.09, 5), np.arange(3, 8)))


def _same(a, b, at: str = "side_map") -> None:
    """Equal down to the bits and dtypes (NaN equal to NaN), field by field."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, at
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), at
    elif hasattr(a, "__dataclass_fields__"):
        assert type(a) is type(b), at
        for name in a.__dataclass_fields__:
            _same(getattr(a, name), getattr(b, name), f"{at}.{name}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), at
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{at}[{i}]")
    elif isinstance(a, float) and np.isnan(a):
        assert isinstance(b, float) and np.isnan(b), at
    else:
        assert a == b and type(a) is type(b), (at, a, b)


def test_a_side_map_comes_back_exactly():
    sm = _side_map(np.random.default_rng(0))
    _same(sm, decode_side_map(encode_side_map(sm)))


def _npz(**entries) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **entries)
    return buf.getvalue()


def _tree(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj).encode(), np.uint8)


@pytest.mark.parametrize("data, says", [
    (b"not a zip at all", "not a orchard_mapping.side_map/1+npz payload"),
    (_npz(a0=np.zeros(3)), "no __tree__ entry"),
    (_npz(__tree__=np.frombuffer(b"{oops", np.uint8)), "__tree__ is not JSON"),
    (_npz(__tree__=_tree({"$type": "Popen", "fields": {}})), "side_map is not a side map type ('Popen')"),
    (_npz(__tree__=_tree({"$type": "Cylinder", "fields": {"axis": 1}})), "side_map (Cylinder) has fields ['axis']"),
    (_npz(__tree__=_tree({"$type": "Cylinder", "fields": {"axis": {"$array": "a9"}, "origin": 0, "radius": 1}})),
     "side_map.axis refers to a missing array entry 'a9'"),
    (_npz(__tree__=_tree({"$type": "Cylinder", "fields": {"axis": 0, "origin": 0, "radius": 1}})),
     "the payload is a Cylinder, not a SideMap"),
])
def test_bytes_that_are_not_a_side_map_are_a_clear_error(data, says):
    with pytest.raises(SideMapFormatError) as err:
        decode_side_map(data, "/orchard/front/side_map")
    assert str(err.value).startswith("/orchard/front/side_map: ") and says in str(err.value), str(err.value)


def test_an_object_array_or_a_foreign_type_is_not_encoded():
    sm = _side_map(np.random.default_rng(1))
    import dataclasses

    with pytest.raises(SideMapFormatError, match=r"side_map\.landmarks: an object array"):
        encode_side_map(dataclasses.replace(sm, landmarks=np.array([object()], dtype=object)))
    with pytest.raises(SideMapFormatError, match=r"side_map\.loops\[0\]: a dict cannot be encoded"):
        encode_side_map(dataclasses.replace(sm, loops=[{"kf_a": 0}]))


def test_bytes_written_before_a_field_was_added_decode_with_its_default():
    """A side map recorded before `fruit` existed (no such field in its tree) decodes with fruit None; a field
    the type does not know is still refused."""
    data = encode_side_map(_side_map(np.random.default_rng(0)))
    with np.load(io.BytesIO(data)) as z:
        entries = {k: z[k] for k in z.files}
    tree = json.loads(entries["__tree__"].tobytes().decode())
    del tree["fields"]["fruit"]
    buf = io.BytesIO()
    np.savez(buf, **{**entries, "__tree__": np.frombuffer(json.dumps(tree).encode(), np.uint8)})
    assert decode_side_map(buf.getvalue()).fruit is None
    tree["fields"]["colour_of_sky"] = 1
    buf = io.BytesIO()
    np.savez(buf, **{**entries, "__tree__": np.frombuffer(json.dumps(tree).encode(), np.uint8)})
    with pytest.raises(SideMapFormatError, match="colour_of_sky"):
        decode_side_map(buf.getvalue())
