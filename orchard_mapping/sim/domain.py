"""Domain randomisation of simulated rows: training frames for the trunk detector.

A detector trained on one look of the simulator learns that look, not
trunks. Each training scene draws what a real orchard varies: bark colour and
texture, leaf colour and density, soil and turf, sky and sun, exposure, blur,
weeds, posts, background rows, camera height, distance, roll and tilt, trunk
diameters and lean, slope and cross slope, tree spacing, the trunk's clear
height under the canopy. `training_scenes` writes such scenes and exports
their frames with trunk and post masks as one COCO folder.

Held out by default: the `slope_weeds` scenario and seeds from 100000 on (the
evaluation data), so the detector is scored on scenes it never saw.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["TRAIN_BASE_SCENARIOS", "random_domain", "training_scenes", "wide_domain"]

TRAIN_BASE_SCENARIOS = ("standard", "wind", "tilted", "vehicle", "handheld_walk", "single_pass", "partial_overlap")
_BARK = [(0.36, 0.27, 0.2), (0.40, 0.40, 0.38), (0.20, 0.17, 0.14), (0.42, 0.25, 0.18), (0.45, 0.47, 0.40),
         (0.30, 0.24, 0.22), (0.55, 0.50, 0.45)]


def _rgb(rng: np.random.Generator, base: tuple[float, float, float], spread: float) -> list[float]:
    return [float(np.clip(c * rng.uniform(1 - spread, 1 + spread), 0.02, 0.95)) for c in base]


def random_domain(rng: np.random.Generator, *, wide: bool = False) -> dict[str, Any]:
    """Dotted scenario overrides (load_scenario) for one randomly drawn orchard look and camera.

    wide: also draw the looks the narrow draws never give (`wide_domain`), after the narrow draws, so
    that a seed gives the same narrow look either way."""
    elev, az = np.radians(rng.uniform(15, 85)), rng.uniform(0, 2 * np.pi)
    overcast = rng.uniform(0, 1)
    sky = np.array([0.62, 0.74, 0.9]) * (1 - overcast) + np.array([0.78, 0.78, 0.8]) * overcast
    d_mean = rng.uniform(0.045, 0.11)
    blur = 0.0 if rng.uniform() < 0.5 else rng.uniform(0.3, 1.5)
    leaf_a = [rng.uniform(0.08, 0.25), rng.uniform(0.25, 0.5), rng.uniform(0.04, 0.15)]
    return {
        "appearance.bark_rgb": _rgb(rng, _BARK[rng.integers(len(_BARK))], 0.2),
        "appearance.bark_texture_gain": [rng.uniform(0.2, 0.6), rng.uniform(0.4, 1.5)],
        "appearance.leaf_rgb_a": leaf_a,
        "appearance.leaf_rgb_b": _rgb(rng, (leaf_a[0] * 1.8, leaf_a[1] * 1.2, leaf_a[2] * 1.3), 0.15),
        "appearance.post_rgb": _rgb(rng, (0.55, 0.45, 0.33) if rng.uniform() < 0.6 else (0.6, 0.6, 0.6), 0.2),
        "appearance.weed_rgb": _rgb(rng, (0.28, 0.5, 0.15), 0.3),
        "appearance.hedge_rgb": _rgb(rng, (0.2, 0.36, 0.14), 0.3),
        "appearance.soil_rgb": _rgb(rng, (0.44, 0.35, 0.25), 0.3),
        "appearance.turf_rgb": _rgb(rng, (0.30, 0.44, 0.17), 0.3),
        "appearance.sky_horizon_rgb": [float(c) for c in sky],
        "appearance.sky_zenith_rgb": [float(c) * 0.85 for c in sky],
        "appearance.sun_dir": [float(np.cos(elev) * np.cos(az)), float(np.cos(elev) * np.sin(az)), float(np.sin(elev))],
        "appearance.ambient": rng.uniform(0.25, 0.7),
        "appearance.diffuse": rng.uniform(0.3, 1.0) * (1 - 0.6 * overcast),
        "appearance.texture_scale": rng.uniform(0.6, 1.6),
        "appearance.blur_sigma_px": blur,
        "canopy.leaves_per_m3": rng.uniform(4000, 14000),
        "structure.weeds_per_m2": rng.uniform(0, 60),
        "structure.weed_height_m": [0.05, rng.uniform(0.15, 0.5)],
        "structure.hedge_distance_m": rng.uniform(2.5, 5.0),
        "structure.post_every_n_trees": int(rng.choice([0, 2, 3, 5])),
        "structure.post_diameter_m": rng.uniform(0.06, 0.14),
        "trunk.diameter_mean_m": d_mean,
        "trunk.diameter_min_m": 0.03,
        "trunk.diameter_max_m": 0.15,
        "trunk.lean_deg_max": rng.uniform(0, 10),
        # real trunks are oval by a few per cent and their bark is bumpy (docs/merge.md)
        "trunk.ellipticity": [0.0, rng.uniform(0.0, 0.12)],
        "trunk.bark_roughness_m": rng.uniform(0.0, 0.002),
        "path.low_height_m": rng.uniform(0.4, 0.9),
        "path.distance_m": rng.uniform(0.9, 1.8),
        "path.roll_deg": rng.uniform(-10, 10),
        "path.high_tilt_deg": rng.uniform(20, 50),
        "path.high_height_m": rng.uniform(2.2, 3.2),
        "camera.exposure_jitter": rng.uniform(0.0, 0.15),
        "camera.color_noise_sd": rng.uniform(1.0, 5.0),
        "row.slope_deg": rng.uniform(-4, 4),
        "row.undulation_m": rng.uniform(0.0, 0.1),
        # drawn last, so that the draws above stay those of the scenes simulated before these were added
        "row.cross_slope_deg": rng.uniform(-4, 4),
        "row.spacing_m": rng.uniform(0.7, 1.4),
        # low canopies hide the trunk but for a strip of bark at its foot (or specks through the leaves)
        "trunk.clear_height_m": [clear := rng.uniform(0.3, 0.8), clear + rng.uniform(0.05, 0.25)],
    } | (wide_domain(rng) if wide else {})


def wide_domain(rng: np.random.Generator) -> dict[str, Any]:
    """Overrides for what real orchards show and the narrow draws do not: young smooth light-grey bark,
    white-painted trunks and dark rough bark; bare (dormant) and sparse canopies without fruit; open
    backgrounds (low or far neighbouring rows, sky behind the trunks); the camera 0.5-2.5 m from the
    trunks; 1280x720 frames (a RealSense colour stream) besides 640x480; harder exposure."""
    over: dict[str, Any] = {}
    bark = rng.uniform()
    if bark < 0.35:  # young trunk: smooth, light grey-brown
        g = rng.uniform(0.45, 0.75)
        over["appearance.bark_rgb"] = _rgb(rng, (g, g * rng.uniform(0.9, 1.0), g * rng.uniform(0.8, 0.95)), 0.05)
        over["appearance.bark_texture_gain"] = [rng.uniform(0.7, 0.9), rng.uniform(0.1, 0.4)]
    elif bark < 0.45:  # whitewash against sun scald
        g = rng.uniform(0.8, 0.95)
        over["appearance.bark_rgb"] = [g, g, g * rng.uniform(0.92, 1.0)]
        over["appearance.bark_texture_gain"] = [rng.uniform(0.8, 0.95), rng.uniform(0.05, 0.2)]
    elif bark < 0.6:  # old, dark, deeply furrowed
        over["appearance.bark_rgb"] = _rgb(rng, (0.16, 0.13, 0.11), 0.25)
        over["appearance.bark_texture_gain"] = [rng.uniform(0.1, 0.3), rng.uniform(1.2, 2.0)]
    season = rng.uniform()
    if season < 0.25:  # dormant: bare branches
        over["canopy.leaves_per_m3"] = rng.uniform(5, 150)
        over["fruit.per_tree"] = [0, 0]
    elif season < 0.45:  # spring flush or thin canopy
        over["canopy.leaves_per_m3"] = rng.uniform(800, 3500)
        over["fruit.per_tree"] = [0, int(rng.integers(0, 15))]
    over["structure.hedge_height_m"] = rng.uniform(0.6, 3.5)
    over["structure.hedge_distance_m"] = rng.uniform(2.5, 9.0)
    over["path.distance_m"] = rng.uniform(0.5, 2.5)
    if rng.uniform() < 0.3:  # RealSense colour at 1280x720 (fx ~ 910 px)
        f = rng.uniform(880, 940)
        over.update({"camera.width": 1280, "camera.height": 720, "camera.fx": f, "camera.fy": f,
                     "camera.cx": 639.5, "camera.cy": 359.5})
    over["camera.exposure_jitter"] = rng.uniform(0.0, 0.35)
    over["appearance.ambient"] = rng.uniform(0.15, 0.9)
    return over


def training_scenes(out: str | Path, n_scenes: int, seed: int = 0, *, trees: int = 3, rate_hz: float = 1.0,
                    bases: tuple[str, ...] = TRAIN_BASE_SCENARIOS, wide: bool = False, log=print) -> Path:
    """Simulate n_scenes domain-randomised rows and export every frame with masks into one COCO folder
    (wide: with `wide_domain`'s looks too)."""
    from orchard_mapping.io.coco import export_coco
    from orchard_mapping.sim.scenario import load_scenario
    from orchard_mapping.sim.simulate import simulate

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    images: list[dict] = []
    anns: list[dict] = []
    cats: list[dict] = []
    scenes = []
    for k in range(n_scenes):
        rng = np.random.default_rng([seed, k])
        base = str(bases[rng.integers(len(bases))])
        over = random_domain(rng, wide=wide)
        over.update({"row.n_trees": trees, "camera.rate_hz": rate_hz, "masks_every": 1})
        if base == "partial_overlap":
            over["path.mode"] = "two_sweep"
        sc = load_scenario(base, over)
        with tempfile.TemporaryDirectory(dir=out) as tmp:
            sim = simulate(sc, int(seed * 100003 + k), Path(tmp) / f"scene{k:04d}").out_dir
            coco = export_coco(sim, out, every=1)
        doc = json.loads(coco.read_text())
        shift_i, shift_a = len(images), len(anns)
        for im in doc["images"]:
            im["id"] += shift_i
        for a in doc["annotations"]:
            a["id"] += shift_a
            a["image_id"] += shift_i
        images += doc["images"]
        anns += doc["annotations"]
        cats = doc["categories"]
        scenes.append({"scene": k, "base": base, "overrides": over})
        log(f"scene {k + 1}/{n_scenes} ({base}): {len(doc['images'])} frames, {len(doc['annotations'])} instances")
    (out / "instances.json").write_text(json.dumps({"images": images, "annotations": anns, "categories": cats,
                                                    "info": {"scenes": scenes, "seed": seed, "wide": wide}}))
    for tmp in out.glob("tmp*"):
        shutil.rmtree(tmp, ignore_errors=True)
    return out / "instances.json"
