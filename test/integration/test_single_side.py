"""Single-side reconstruction on simulated rows, through bags and `orchard_mapping.pipeline.run`.

Goals (issue: single-side reconstruction; side_goals.py): after bundle adjustment each side drifts <= 0.5 % of
its path (last keyframe, first pose aligned, nothing fitted) and has ATE <= 0.15 % of its path. `make test`
checks them on short rows (2 trees, 15 Hz, both sweeps of the paper's protocol) to stay fast on 2 cores, here
on the standard row, in test_single_side_motion.py on the wind, hand-held and single-bag drives; the 10- and
30-tree rows are measured by benchmarks/single_side.py.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from side_goals import (
    _assert_ba_keeps_front_end_accuracy,
    _assert_sides_within_goals,
    _true_trajectory,
    _with_true_masks,
)
from typer.testing import CliRunner

from orchard_mapping.cli.main import app
from orchard_mapping.config import load_config
from orchard_mapping.core.odometry import RGBDFrontEnd
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.errors import AlignmentError, BagError, BagFormatError
from orchard_mapping.eval import evaluate_result
from orchard_mapping.eval.ground_truth import load_ground_truth
from orchard_mapping.eval.metrics import double_count, trajectory_error
from orchard_mapping.io.bag_writer import BagWriter
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.io.landmarks import read_trunks
from orchard_mapping.io.results import read_trees, read_tum
from orchard_mapping.io.sidemap_codec import decode_side_map, encode_side_map
from orchard_mapping.pipeline import SideSession, SpooledKeyframeImages, Timings, merge_sides, run
from orchard_mapping.pipeline.fruit import add_fruit
from orchard_mapping.pipeline.merge import merge_to_trees
from orchard_mapping.pipeline.traits import measure_trees
from orchard_mapping.ros.finisher import FinishingProcess, finish_in_child
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import simulate


@pytest.fixture(scope="module")
def reconstructed(standard_row) -> tuple[Path, Path]:
    """Both sides of the standard row (SEED, 2 trees) through `run` (bags in, result folder out), trunks from
    true masks (test/conftest.py: the node graph's tests use the same run)."""
    return standard_row


_MODEL_SIDES: dict[str, SideMap] = {}  # the side maps of reconstructed_model, for merges on other inputs


@pytest.fixture(scope="module")
def reconstructed_model(reconstructed, scratch) -> Iterator[tuple[Path, Path]]:
    """The same row through `run` with the default configuration: trunks from the shipped detector."""
    sim, _ = reconstructed
    with scratch("standard_model") as root:
        out = root / "result"
        _MODEL_SIDES.update(run(sim / "front", sim / "back", out, load_config()).sides)
        yield sim, out


@pytest.mark.accuracy
def test_drift_and_ate_within_goals(reconstructed, accuracy):
    sim, out = reconstructed
    _assert_sides_within_goals(evaluate_result(sim / "ground_truth.json", out).to_dict(), accuracy, "")

@pytest.mark.accuracy
def test_bundle_adjustment_keeps_the_front_end_accuracy(reconstructed, accuracy):
    sim, out = reconstructed
    for side in ("front", "back"):
        true = _true_trajectory(sim, side)
        odo = trajectory_error(read_tum(out / f"odometry_{side}.tum"), true)
        ba = trajectory_error(read_tum(out / f"trajectory_{side}.tum"), true)
        _assert_ba_keeps_front_end_accuracy(odo, ba, accuracy, side)





def test_a_failed_run_leaves_no_folder_it_created(tmp_path):
    out = tmp_path / "new" / "result"
    res = CliRunner().invoke(app, ["run", str(tmp_path / "missing_bag"), "--out", str(out)])
    assert res.exit_code == 2 and "missing_bag" in res.output, res.output
    assert not (tmp_path / "new").exists()
    existing = tmp_path / "kept"
    existing.mkdir()
    (existing / "notes.txt").write_text("mine")
    res = CliRunner().invoke(app, ["run", str(tmp_path / "missing_bag"), "--out", str(existing)])
    assert res.exit_code == 2 and sorted(p.name for p in existing.iterdir()) == ["notes.txt"]


def test_a_side_fed_frame_by_frame_with_spooled_keyframes_is_the_side_run_wrote(reconstructed, tmp_path):
    """The live odometry node's way (frames one at a time, each keyframe's images spooled to disk and read
    back for fusion after BA in a child process) gives the side `run` wrote from the same bag: same
    keyframes, cloud, trunks."""
    sim, out = reconstructed
    seq = read_rgbd(sim / "front")
    images = SpooledKeyframeImages(tmp_path)
    process = FinishingProcess()  # as the node does: started as the side begins, waiting for the side's end
    session = SideSession("front", seq.intrinsics, _with_true_masks(sim), images, bag=seq.bag)
    made = sum(session.add(frame)[1] for frame in seq)
    assert len(list(images.dir.glob("*_depth.npy"))) == made > 20
    side = finish_in_child(session, Timings(), process=process)  # as the node finishes a side: in that process
    assert not images.dir.exists()  # the spool goes with the side
    assert not process._proc.is_alive() and process._proc.exitcode == 0  # one side, then it is gone
    tum = read_tum(out / "trajectory_front.tum")
    assert np.array_equal(side.keyframe_stamps, tum.stamps)
    assert np.abs(side.keyframe_poses[:, :3, 3] - tum.positions).max() < 1e-6
    import open3d as o3d

    assert len(side.cloud_points) == len(o3d.io.read_point_cloud(str(out / "front.ply")).points)
    written = [t for t in read_trunks(out / "trunks.json") if t.side == "front"]
    assert len(side.trunks) == len(written) > 0
    for lm, t in zip(side.trunks, written, strict=True):
        assert lm.id == t.id and np.abs(lm.base - t.base).max() < 1e-6
    # the side map as the odometry node sends it to the side merger: back exactly (re-encoded: the same bytes)
    data = encode_side_map(side)
    again = decode_side_map(data)
    assert encode_side_map(again) == data and len(again.trunks) == len(side.trunks)
    assert np.array_equal(again.cloud_points, side.cloud_points) and again.trunks[0].band_views


def test_result_folder_parts(reconstructed):
    sim, out = reconstructed
    timings = json.loads((out / "timings.json").read_text())
    assert timings["frames"] > 400 and timings["recording_duration_s"] > 25
    assert {"front_end_front", "bundle_adjustment_back", "fusion_front", "trunks_back"} <= set(timings["stages"])
    assert load_config(out / "config.effective.yaml") == _with_true_masks(sim)
    trunks = json.loads((out / "trunks.json").read_text())["sides"]
    for side in ("front", "back"):
        assert trunks[side]["frame"] == f"odom_{side}" and trunks[side]["trunks"], side
        for t in trunks[side]["trunks"]:  # what the semantic bundle adjustment will need of each detection
            assert len(t["observations"]) >= 2 and all(o["mask_pixels"] > 0 for o in t["observations"])
            if t["diameter_m"] is not None:
                assert all(o["cylinder_cam"] is not None for o in t["observations"])
    grounds = json.loads((out / "grounds.json").read_text())["sides"]
    assert {g["trunk_id"] for g in grounds["front"]["grounds"]} <= {t["id"] for t in trunks["front"]["trunks"]}
    assert (out / "front.ply").stat().st_size > 100_000 and (out / "back.ply").is_file()
    assert not list(out.glob(".staging-*"))


def test_the_shipped_detector_finds_each_trunk_and_measures_it(reconstructed_model, accuracy):
    """The product's default path: trunk masks from models/trunk_maskrcnn.onnx. Every trunk in view found,
    nothing else taken for a trunk (the row has trellis posts), diameters within the MAE goal (4 mm).
    The bias goal needs more than two trees: benchmarks/trunks.py --source model measures it on ten."""
    sim, out = reconstructed_model
    assert load_config(out / "config.effective.yaml").trunks.source == "model"
    report = evaluate_result(sim / "ground_truth.json", out).to_dict()
    for side in ("front", "back"):
        t = report["trunks"][side]
        assert t["matched"] == t["true_in_view"] == 2 and t["reported"] == 2, t
        assert t["diameter_n"] >= 2, t
        accuracy.at_most(f"{side} trunk diameter MAE (shipped detector), mm", t["diameter_mae_mm"], 4.0)


def test_the_sides_are_merged_on_their_shared_trunks(reconstructed_model, accuracy):
    """Initial alignment, initial transform and semantic BA on the 2-tree row: both trees paired, the two
    halves of each trunk on one axis after the semantic BA (issue goals: median gap <= 5 mm, max <= 15 mm),
    and the initial transform against the truth at the trunk bases. The issue's rigid merge goals (1 cm,
    0.2 deg) are for after semantic BA on 10 and 30 trees; these bounds are the initial transform's: well
    inside the 0.15 m pairing radius, a tilt about the row left for the bundle adjustment."""
    sim, out = reconstructed_model
    sm = json.loads((out / "side_merge.json").read_text())
    assert sm["method"] == "semantic_ba" and sm["overlap"]["pairs"] == 2
    gap = sm["semantic_ba"]["trunk_axis_gap_mm"]["after"]
    accuracy.at_most("trunk axis gap after semantic BA (median), mm", gap["median"], 5.0)
    accuracy.at_most("trunk axis gap after semantic BA (max), mm", gap["max"], 15.0)
    for p in sm["residuals"]["pairs"]:
        accuracy.at_most("paired trunk axes after the merge, deg", p["axis_deg"], 2.0)
        accuracy.at_most("back trunk axis point off the front axis, mm", p["line_mm"], 15.0)
    m = evaluate_result(sim / "ground_truth.json", out).to_dict()["merge"]
    # the evaluator's own measure from the written files (trunks.json carried by the trajectories in map)
    accuracy.at_most("evaluator: trunk axis gap after the merge (median), mm", m["trunk_axis_gap_mm"]["median"], 5.0)
    accuracy.at_most("evaluator: trunk axis gap after the merge (max), mm", m["trunk_axis_gap_mm"]["max"], 15.0)
    accuracy.at_most("initial merge error at the trunk bases (max), mm", m["max_translation_error_mm"], 30.0)
    accuracy.at_most("initial merge rotation error, deg", m["rotation_error_deg"], 2.5)
    assert (out / "trajectory_back_map.tum").is_file()
    _assert_merged_cloud_in_place(sim, out)
    # trees.json: each tree once, in map, with the two-side diameter (eq. objectCylinderFB)
    rep = evaluate_result(sim / "ground_truth.json", out).to_dict()
    assert rep["matching"]["matched"] == rep["matching"]["true_trees"] == rep["matching"]["result_trees"] == 2
    accuracy.at_most("tree position in map (mean), mm", 1000 * rep["matching"]["mean_distance_m"], 30.0)
    accuracy.at_most("two-side trunk diameter MAE, mm", rep["traits"]["trunk_diameter_mae_mm"], 3.0)


def test_swapped_sides_merge_correctly_and_one_side_twice_is_refused(reconstructed_model, accuracy):
    """Bad input: the back bag given as front and the front as back merge into the same row (the inverse
    transform, as accurate); a side's map merged with itself is refused (typed)."""
    sim, out = reconstructed_model
    cfg = load_config()
    truth = json.loads((sim / "ground_truth.json").read_text())
    T_true = np.array(truth["T_front_back"])
    straight = merge_sides(_MODEL_SIDES["front"], _MODEL_SIDES["back"], cfg)
    swapped = merge_sides(_MODEL_SIDES["back"], _MODEL_SIDES["front"], cfg)
    assert sorted((j, i) for i, j in swapped.pairs) == sorted(straight.pairs)
    bases_f = np.array([t.base for t in _MODEL_SIDES["front"].trunks])  # odom_front
    for T, T_ref, pts in ((straight.T_front_back, T_true, np.array([t.base for t in _MODEL_SIDES["back"].trunks])),
                          (swapped.T_front_back, np.linalg.inv(T_true), bases_f)):
        err = np.linalg.norm(pts @ (T[:3, :3] - T_ref[:3, :3]).T + T[:3, 3] - T_ref[:3, 3], axis=1)
        accuracy.at_most("merge error at the trunk bases, sides as given or swapped, mm", 1000 * err.max(), 30.0)
    for side in ("front", "back"):  # (two different recordings of one side: see docs/merge.md)
        with pytest.raises(AlignmentError, match="one recording"):
            merge_sides(_MODEL_SIDES[side], _MODEL_SIDES[side], cfg)


def test_one_recording_given_as_both_sides_is_a_clear_error(short_sim, tmp_path):
    with pytest.raises(BagError, match="same file"):
        run(short_sim / "front", short_sim / "front", tmp_path / "out", load_config())
    shutil.copytree(short_sim / "front", tmp_path / "copy")
    with pytest.raises(BagError, match="same recording"):
        run(short_sim / "front", tmp_path / "copy", tmp_path / "out", load_config())
    assert not (tmp_path / "out").exists()


def _assert_merged_cloud_in_place(sim: Path, out: Path) -> None:
    """merged.ply holds both sides' clouds (labelled) in map; the back side's points sit where the truth
    puts them (each point's own-side position carried into the front frame by the true transform), as
    close as the merge itself (the 30 mm bound above); row.png is a picture."""
    import open3d as o3d

    m = o3d.t.io.read_point_cloud(str(out / "merged.ply"))
    side = m.point.side.numpy().ravel()
    front = o3d.t.io.read_point_cloud(str(out / "front.ply")).point.positions.numpy()
    back = o3d.t.io.read_point_cloud(str(out / "back.ply")).point.positions.numpy()
    assert np.count_nonzero(side == 0) == len(front) and np.count_nonzero(side == 1) == len(back)
    assert m.point.colors.numpy().dtype == np.uint8
    truth = json.loads((sim / "ground_truth.json").read_text())
    T = np.array(truth["T_front_back"])  # odom_front <- odom_back, true
    merged_back = m.point.positions.numpy()[side == 1].astype(float)
    expected = back.astype(float) @ T[:3, :3].T + T[:3, 3]
    err = np.linalg.norm(merged_back - expected, axis=1)
    assert float(np.median(err)) <= 0.030, np.percentile(err, [50, 90])
    assert (out / "row.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_trunk_diameters_of_each_side_within_goals(reconstructed, accuracy):
    """Issue goals (trunks from the simulator's masks): diameter MAE <= 4 mm, bias within +-2 mm, recall
    >= 95 % of the trunks in view, precision >= 98 %; the 2D term of eq. objectCylinder is on."""
    sim, out = reconstructed
    report = evaluate_result(sim / "ground_truth.json", out).to_dict()
    for side in ("front", "back"):
        t = report["trunks"][side]
        assert t["diameter_n"] >= 2, t
        accuracy.at_most(f"{side} trunk diameter MAE, mm", t["diameter_mae_mm"], 4.0)
        accuracy.at_most(f"{side} |trunk diameter bias|, mm", abs(t["diameter_bias_mm"]), 2.0)
        # recall >= 95 % and precision >= 98 % on two trees: no trunk missed, none made up
        assert t["matched"] == t["true_in_view"] == 2 and t["reported"] == 2, t
        accuracy.at_most(f"{side} trunk axis error, deg", t["axis_error_deg"], 2.0)


# --------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def short_sim(scratch) -> Iterator[Path]:
    sc = load_scenario("single_pass", {"row.n_trees": 1, "camera.rate_hz": 15, "masks_every": 0,
                                       "row.margin_m": 0.6})
    with scratch("short") as root:
        yield simulate(sc, 5, root / "sim").out_dir


def _rewrite(src: Path, dst: Path, *, blank: range = range(0), depth_zero: bool = False,
             drop_depth: bool = False) -> None:
    seq = read_rgbd(src)
    cfg = load_config().input.topics
    with BagWriter(dst) as bag:
        for f in seq:
            color, depth = f.color, f.depth
            if f.index in blank:
                color = np.full_like(color, 90)
                depth = np.zeros_like(depth)
            if depth_zero:
                depth = np.zeros_like(depth)
            bag.write_camera_info(cfg.camera_info, f.stamp, f.intrinsics)
            bag.write_color(cfg.color, f.stamp, color)
            if not drop_depth:
                bag.write_depth(cfg.depth, f.stamp, depth)


def test_depth_all_zero_is_a_clear_error(short_sim, tmp_path):
    _rewrite(short_sim / "front", tmp_path / "nodepth", depth_zero=True)
    with pytest.raises(BagFormatError, match="depth"):
        run(tmp_path / "nodepth", short_sim / "back", tmp_path / "out", load_config())
    assert not (tmp_path / "out" / "trajectory_front.tum").exists()


def test_colour_without_depth_is_a_clear_error(short_sim, tmp_path):
    _rewrite(short_sim / "front", tmp_path / "colouronly", drop_depth=True)
    with pytest.raises(Exception, match="aligned_depth_to_color") as exc:
        run(tmp_path / "colouronly", short_sim / "back", tmp_path / "out", load_config())
    assert "colouronly" in str(exc.value)


def _no_masks(root: Path) -> Path:
    """A masks folder (trunks.source masks) in which no frame has a trunk: a detector that sees none."""
    for side in ("front", "back"):
        (root / side).mkdir(parents=True)
        (root / side / "index.csv").write_text("frame,stamp\n")
    return root


def test_sides_without_trunks_keep_their_maps_and_the_merge_is_refused_with_exit_code_2(short_sim, tmp_path,
                                                                                         caplog):
    """No merge is guessed without any trunk (none detected, none from geometry): `orchard-map run` exits 2
    naming why, each side's own results are written, nothing of the merge is (an earlier run's merge outputs
    in the folder go too)."""
    empty = _no_masks(tmp_path / "masks")
    out = tmp_path / "result"
    out.mkdir()
    (out / "side_merge.json").write_text("{}")  # stale, from an earlier run
    res = CliRunner().invoke(app, ["run", str(short_sim / "front"), str(short_sim / "back"), "--out", str(out),
                                   "--set", "trunks.source=masks", "--set", f"trunks.masks_dir={empty}",
                                   "--set", "trunks.geometric=off"])
    assert res.exit_code == 2, res.output
    assert "not merged" in res.output and "seen from both sides" in res.output and "merge.method=off" in res.output
    assert (out / "trajectory_front.tum").is_file() and (out / "front.ply").is_file()
    trunks = json.loads((out / "trunks.json").read_text())["sides"]
    assert trunks["front"]["trunks"] == [] and trunks["back"]["trunks"] == []
    assert "front: no trunk found" in caplog.text
    assert not (out / "side_merge.json").exists() and not (out / "trees.json").exists()
    assert not list(out.glob("trajectory_*_map.tum")) and not list(out.glob(".staging-*"))


def test_a_detector_blind_to_the_trunks_is_stood_in_for_by_geometry_and_the_merge_degrades(short_sim, tmp_path):
    """Unseen data in small: the detector finds no trunk (as on bark it never saw). The geometric trunk finder
    (trunks.geometric fill) finds the row's trunk on each side from the fused cloud alone, models it like a
    detected one, and the two sides, sharing one tree (fewer than alignment.min_pairs), are merged from the
    global features (alignment.fallback): a merged map and a tree, flagged, instead of a refusal."""
    empty = _no_masks(tmp_path / "masks")
    out = tmp_path / "result"
    res = CliRunner().invoke(app, ["run", str(short_sim / "front"), str(short_sim / "back"), "--out", str(out),
                                   "--set", "trunks.source=masks", "--set", f"trunks.masks_dir={empty}"])
    assert res.exit_code == 0, res.output
    truth = load_ground_truth(short_sim / "ground_truth.json")
    true_d = 1000 * truth.trees[0].diameter_m
    trunks = json.loads((out / "trunks.json").read_text())["sides"]
    for side in ("front", "back"):
        (t,) = trunks[side]["trunks"]
        assert "found_by_geometry" in t["flags"]
        assert abs(1000 * t["diameter_m"] - true_d) < 4.0, (side, t["diameter_m"], true_d)  # the MAE goal
    sm = json.loads((out / "side_merge.json").read_text())
    assert sm["method"] == "global_features"
    (tree,) = read_trees(out / "trees.json")
    assert "merged_by_global_features" in tree.flags
    rep = evaluate_result(short_sim / "ground_truth.json", out).to_dict()
    assert rep["matching"]["matched"] == 1
    # the shared trunk pins the merge at the tree (the bound the semantic merge's initial transform has above)
    assert rep["merge"]["max_translation_error_mm"] < 30.0
    assert rep["merge"]["rotation_error_deg"] < 3.0  # the heading from the two camera paths, 1.3 m long here
    # m: each side's foot on this row sits 2-3 cm above the truth's (grass at the foot), as the detector's does
    assert rep["matching"]["mean_distance_m"] < 0.06


def test_blank_frames_do_not_crash_the_front_end(short_sim, tmp_path):
    seq_len = len(read_rgbd(short_sim / "front"))
    blank = range(seq_len // 3, seq_len // 3 + 8)
    _rewrite(short_sim / "front", tmp_path / "blank", blank=blank)
    seq = read_rgbd(tmp_path / "blank")
    fe = RGBDFrontEnd(seq.intrinsics, load_config().odometry)
    for frame in seq:
        fe.track(frame)
    res = fe.result()
    placed = np.isfinite(res.frame_poses[:, 0, 0])
    assert not placed[blank.start + 1: blank.stop].any()  # nothing to track in a blank frame
    assert placed[blank.stop + 5:].all()  # ...and tracking comes back after the blank stretch
    assert any("lost" in e for e in res.events) and any("relocalised" in e or "restarted" in e for e in res.events)
    true = _true_trajectory(short_sim, "front")
    err = trajectory_error(StampedTrajectory(res.frame_stamps[placed], res.frame_poses[placed, :3, 3],
                                             np.tile([0, 0, 0, 1.0], (placed.sum(), 1))), true)
    assert err.n_associated == placed.sum()


def test_each_tree_is_measured_in_the_merged_map(reconstructed_model, accuracy):
    """The traits stage on the 2-tree row: height and canopy volume of both trees against the truth (issue
    goals over ten trees: height MAE <= 2 cm, volume error <= 5 %; measured here 0.4 cm and 3.3 %, each tree
    within 6 %; a 2-tree row's trees are both end trees, so the volume bound is the goal's with room for one
    tree's error), and trees.laz: every point of merged.ply with its tree and class."""
    from orchard_mapping.io.laz import CLASS, read_laz

    sim, out = reconstructed_model
    rep = evaluate_result(sim / "ground_truth.json", out).to_dict()
    assert rep["traits"]["height_n"] == rep["traits"]["canopy_volume_n"] == 2, rep["traits"]
    accuracy.at_most("tree height MAE, cm", rep["traits"]["height_mae_cm"], 2.0)
    accuracy.at_most("canopy volume mean abs error, %", rep["traits"]["canopy_volume_mape_percent"], 8.0)
    for p in rep["per_tree"]:
        err = abs(p["est_canopy_volume_m3"] - p["true_canopy_volume_m3"]) / p["true_canopy_volume_m3"]
        accuracy.at_most("canopy volume error of one tree, %", 100 * err, 15.0)
    trees = read_trees(out / "trees.json")
    # each tree's local ground, fitted to both sides' points (its height is measured along that normal)
    truth = json.loads((sim / "ground_truth.json").read_text())
    R_world_map = np.asarray(truth["sides"]["front"]["T_world_odom"], float)[:3, :3]  # map is the front's odom
    by_id, true_by_id = {t.id: t for t in trees}, {t["id"]: t for t in truth["trees"]}
    for p in rep["per_tree"]:
        n = R_world_map @ np.asarray(by_id[p["result_id"]].extra["local_ground_normal"], float)
        n_true = np.asarray(true_by_id[p["true_id"]]["local_ground"]["normal"], float)
        accuracy.at_most("local ground normal error, deg", float(np.degrees(np.arccos(min(1.0, n @ n_true)))), 5.0)
    laz = read_laz(out / "trees.laz")
    assert set(np.unique(laz["tree_id"])) <= {-1} | {t.id for t in trees}
    for t in trees:  # each tree holds canopy and trunk points
        mine = laz["classification"][laz["tree_id"] == t.id]
        assert np.sum(mine == CLASS["canopy"]) > 1000 and np.sum(mine == CLASS["trunk"]) > 50, t.id
    assert np.sum(laz["classification"] == CLASS["ground"]) > 10_000
    assert sorted(p.name for p in (out / "trees").iterdir()) == [f"{t.id}.png" for t in trees]  # the figures


def test_fruit_of_both_sides_are_counted_once_and_placed(reconstructed_model, accuracy):
    """The fruit stage's geometry on the 2-tree row (fruit.source masks: the simulator's fruit masks stand for
    the pixel model, core.fruit_pixels, measured in its own tests): each side's fruit from its keyframes, both
    sides merged and counted once per tree. Goals of the yield issue: row count within 3 % of the fruit visible
    from either side, at most 2 duplicates per 100 fruit seen from both sides, position error <= 1.5 cm median,
    diameter MAE <= 5 mm; measured on a 3-tree row: -1.2 %, 1.7, 4.6 mm, 2.2 mm. Two trees' ~60 fruit make the
    count bound one fruit coarser: 5 %."""
    sim, _ = reconstructed_model
    base = load_config()
    cfg = base.model_copy(update={"fruit": dataclasses.replace(base.fruit, enabled=True, source="masks",
                                                               masks_dir=str(sim / "masks"))})
    sides = {s: add_fruit(_MODEL_SIDES[s], read_rgbd(sim / s), cfg.fruit)[0] for s in ("front", "back")}
    merged, clouds, trees = merge_to_trees(sides, cfg)
    measured, labels = measure_trees(merged, sides, clouds, trees, cfg)
    gt = load_ground_truth(sim / "ground_truth.json")
    visible = sum(t.fruit_visible["either"] for t in gt.trees)
    with_fruit = [t for t in measured if t.fruit_count is not None]
    assert len(with_fruit) == len(measured) == 2
    est = sum(t.fruit_count for t in with_fruit) + sum(t.extra["fruit_on_ground"] for t in with_fruit)
    accuracy.at_most("fruit count error vs visible, %", 100 * abs(est - visible) / visible, 5.0)
    for t in with_fruit:  # each side's own count is below the two-side one: the association adds, never doubles
        assert max(t.extra["fruit_count_front"], t.extra["fruit_count_back"]) <= t.fruit_count
        assert t.extra["fruit_count_front"] + t.extra["fruit_count_back"] - t.extra["fruit_seen_from_both"] == \
            t.fruit_count
    T = np.linalg.inv(gt.sides["front"].T_world_odom)
    true_xyz = np.concatenate([t.fruit_positions for t in gt.trees]) @ T[:3, :3].T + T[:3, 3]
    dc = double_count(np.concatenate([t.fruit_positions for t in with_fruit]), true_xyz,
                      np.concatenate([t.fruit_radii for t in gt.trees]),
                      est_diameter_m=np.concatenate([t.extra["fruit_diameters_m"] for t in with_fruit]),
                      true_seen_from_both=sum(t.fruit_visible["both"] for t in gt.trees))
    # ~30 fruit seen from both sides: one duplicate is 3 %, so the bound is one duplicate (the goal's 2 % is
    # over a 10-tree row: benchmarks/fruit_rows.py)
    accuracy.at_most("fruit counted twice per 100 seen from both sides", dc.per_both_percent, 4.0)
    accuracy.at_most("fruit position error median, mm", dc.position_error_median_mm, 15.0)
    accuracy.at_most("fruit diameter MAE, mm", dc.diameter_mae_mm, 5.0)
    assert dc.false <= 0.05 * dc.estimated
    assert np.sum(labels.classification == 66) > 100  # fruit points classed for trees.laz
