"""Frames with fruit labels from the simulator, and the training of the fruit pixel models.

Training-only (imports the simulator, scikit-learn for the colour GMM and torch for the network: `make
train-setup`); the runtime reads the model files with `orchard_mapping.core.fruit_pixels` alone. Seeds are
split three ways, never mixed:

  training     TRAIN_SEEDS: domain-randomised scenes (orchard_mapping.sim.domain.random_domain: sun, shade,
               colours, camera), TRAIN_VARIED_SEEDS: the same with the varied fruit look (`fruit.look: varied`:
               blush, streaks, golden and pink varieties), TRAIN_STANDARD_SEEDS: the standard scenario's look;
               each scene with its own colour mix drawn from RED_FRACTIONS (or uniform)
  validation   VALIDATION_SEEDS, VALIDATION_VARIED_SEEDS, VALIDATION_STANDARD_SEEDS: the same draws, used for
               every choice (colour space, components, thresholds, network, instance splitting)
  held out     HELDOUT_SEEDS (benchmarks/fruit_pixels.py, test/unit/core/test_fruit_pixels.py): scored only

Usage (re-makes models/fruit_colour_gmm.json and models/fruit_net.onnx):
  python -m orchard_mapping.train.fruit_pixels [--out models] [--scenes 24] [--frames 4] [--iterations 2000]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orchard_mapping.core import fruit_pixels as fp

TRAIN_SEEDS = tuple(range(0, 24))  # randomised look
TRAIN_STANDARD_SEEDS = tuple(range(100, 112))  # the standard scenario's look
TRAIN_VARIED_SEEDS = tuple(range(200, 224))  # randomised look, varied fruit
VALIDATION_SEEDS = tuple(range(500, 506))  # randomised look
VALIDATION_STANDARD_SEEDS = tuple(range(600, 603))
VALIDATION_VARIED_SEEDS = tuple(range(700, 706))
HELDOUT_SEEDS = tuple(range(1000, 1004))  # both looks, each colour mix
RED_FRACTIONS = (1.0, 0.0, 0.6)  # the three colour mixes scored: red, green, mixed
SEED_TAG = 7  # random_domain's generator: default_rng([SEED_TAG, seed])


@dataclass(frozen=True)
class LabelledFrame:
    rgb: np.ndarray  # (H, W, 3) uint8, with the sensor model's noise and exposure jitter
    instances: np.ndarray  # (H, W) int32: 0 background, 1 + fruit index on fruit pixels
    seed: int
    frame: int
    side: str
    # (F + 1,) share of each fruit's projected disc visible in this frame, indexed by instance id (0: unused)
    visible_fraction: np.ndarray


def scene_overrides(seed: int, red_fraction: float | None, randomise: bool, trees: int,
                    fruit_look: str = "plain") -> dict[str, Any]:
    """Scenario overrides of one scene: random_domain's look when `randomise` (sun, shade, colours, camera),
    the colour mix `red_fraction` (None: drawn from RED_FRACTIONS or uniform, per scene), the fruit's look
    (`fruit.look`: plain or varied)."""
    from orchard_mapping.sim.domain import random_domain

    rng = np.random.default_rng([SEED_TAG, seed])
    over: dict[str, Any] = random_domain(rng) if randomise else {}
    if red_fraction is None:
        k = int(rng.integers(len(RED_FRACTIONS) + 1))
        red_fraction = float(RED_FRACTIONS[k]) if k < len(RED_FRACTIONS) else float(rng.uniform())
    over.update({"row.n_trees": trees, "camera.rate_hz": 2.0, "fruit.red_fraction": red_fraction,
                 "fruit.look": fruit_look, "masks_every": 0})
    return over


def scene_frames(seed: int, *, red_fraction: float | None = None, randomise: bool = True, trees: int = 2,
                 frames_per_side: int = 4, scenario: str = "standard", fruit_look: str = "plain"
                 ) -> list[LabelledFrame]:
    """`frames_per_side` frames evenly spread over each side's path (both sweeps) of one simulated row."""
    from orchard_mapping.sim.scenario import load_scenario
    from orchard_mapping.sim.scene import Cls
    from orchard_mapping.sim.simulate import Rig

    sc = load_scenario(scenario, scene_overrides(seed, red_fraction, randomise, trees, fruit_look))
    rig = Rig.build(sc, seed)
    out: list[LabelledFrame] = []
    centres = np.array([f.position for f in rig.scene.fruit]).reshape(-1, 3)  # (F, 3) world
    radii = np.array([f.radius for f in rig.scene.fruit])  # (F,) m
    for k, side in enumerate(("front", "back")):
        path = rig.path(side, np.random.default_rng([seed, 1, k]))
        rng = np.random.default_rng([seed, 2, k])
        n = len(path.poses)
        # evenly spread, skipping the first and last frames (the camera is past the row's ends there)
        idx = np.unique(np.linspace(0, n - 1, frames_per_side + 2).round().astype(int)[1:-1])
        for i in idx:
            color, _, render = rig.shoot(path.poses[i], rng, float(path.stamps[i] - path.stamps[0]))
            inst = np.where(render.cls == Cls.FRUIT, render.inst + 1, 0).astype(np.int32)
            T_cam_world = np.linalg.inv(path.poses[i])
            z = centres @ T_cam_world[2, :3] + T_cam_world[2, 3]  # (F,) m along the optical axis
            disc = np.pi * (rig.intrinsics.fx * radii / np.maximum(z, 1e-3)) ** 2  # (F,) px, projected area
            seen = np.bincount(inst.ravel(), minlength=len(radii) + 1)[1:] / disc
            frac = np.concatenate([[0.0], np.where(z > 0, seen, 0.0)])
            out.append(LabelledFrame(color, inst, seed, int(i), side, frac))
    return out


def frames_for(seeds: tuple[int, ...], **kw: Any) -> list[LabelledFrame]:
    return [f for s in seeds for f in scene_frames(s, **kw)]


def training_frames(scenes: int, frames_per_side: int) -> tuple[list[LabelledFrame], list[LabelledFrame]]:
    """(training, validation) frames: randomised-look scenes, as many with the varied fruit, then standard-look
    ones (half as many)."""
    std = TRAIN_STANDARD_SEEDS[: max(1, scenes // 2)]
    train = frames_for(TRAIN_SEEDS[:scenes], frames_per_side=frames_per_side)
    train += frames_for(TRAIN_VARIED_SEEDS[:scenes], frames_per_side=frames_per_side, fruit_look="varied")
    train += frames_for(std, frames_per_side=frames_per_side, randomise=False)
    val = frames_for(VALIDATION_SEEDS, frames_per_side=frames_per_side)
    val += frames_for(VALIDATION_VARIED_SEEDS, frames_per_side=frames_per_side, fruit_look="varied")
    val += frames_for(VALIDATION_STANDARD_SEEDS, frames_per_side=frames_per_side, randomise=False)
    return train, val


def pixel_samples(frames: list[LabelledFrame], per_frame: int, seed: int, features: str
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(N, F) float32 features and (N,) bool labels: up to per_frame / 2 fruit and per_frame / 2 other pixels
    per frame (fruit is 1-3 % of a frame's pixels: balanced sampling keeps the rare class's shape)."""
    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for f in frames:
        feat = fp.pixel_features(f.rgb, features)  # (H*W, F)
        lab = (f.instances > 0).ravel()
        for cls in (True, False):
            idx = np.flatnonzero(lab == cls)
            if idx.size:
                take = rng.choice(idx, min(idx.size, per_frame // 2), replace=False)
                xs.append(feat[take])
                ys.append(np.full(take.size, cls))
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys)


def fit_gmm(frames: list[LabelledFrame], space: str, components: tuple[int, int], seed: int = 0,
            per_frame: int = 4000) -> fp.ColourGmm:
    """A GMM per class (fruit, other) on colour alone; threshold 0 on the log-likelihood ratio (set later)."""
    from sklearn.mixture import GaussianMixture

    x, y = pixel_samples(frames, per_frame, seed, space)
    parts = []
    for cls, k in ((True, components[0]), (False, components[1])):
        g = GaussianMixture(k, covariance_type="full", random_state=seed, reg_covar=1e-4, max_iter=300).fit(x[y == cls])
        parts.append(fp.Gaussians(g.weights_.astype(np.float64), g.means_.astype(np.float64),
                                  g.covariances_.astype(np.float64)))
    return fp.ColourGmm(space=space, fruit=parts[0], other=parts[1], threshold=0.0)


def photometric_jitter(img: np.ndarray, rng: np.random.Generator, jitter: str = "wide") -> np.ndarray:
    """img (H, W, 3) float32 in [0, 1], jittered as another camera and light would show it; float32 in [0, 1].

    narrow: saturation 0.8-1.2, exposure 0.7-1.3, white balance +-8 %. wide (chosen before any measurement on
    an unseen domain, from what cameras and orchards vary): saturation 0.35-1.3 (a tone curve or haze washes
    colours out; the simulator's fruit are saturated), contrast 0.6-1.25, gamma 0.6-1.6, exposure 0.6-1.4,
    white balance +-15 %, a hue turn of up to 12 deg (fruit and leaves stay apart by hue), blur up to 1.5 px
    on a third of the crops and sensor noise up to 3 %."""
    import cv2

    if jitter == "narrow":
        grey = img.mean(2, keepdims=True)
        img = grey + (img - grey) * np.float32(rng.uniform(0.8, 1.2))  # saturation
        img = img * np.float32(rng.uniform(0.7, 1.3)) * rng.uniform(0.92, 1.08, 3).astype(np.float32)  # exposure, WB
        return np.clip(img, 0, 1).astype(np.float32)
    a = np.radians(rng.uniform(-12, 12))  # hue turn about the grey axis (Rodrigues, unit axis (1, 1, 1) / sqrt 3)
    k = np.full((3, 3), (1 - np.cos(a)) / 3) + np.cos(a) * np.eye(3)
    k += np.sin(a) / np.sqrt(3) * np.array([[0, -1, 1], [1, 0, -1], [-1, 1, 0]])
    img = img @ k.T.astype(np.float32)
    grey = img.mean(2, keepdims=True)
    img = grey + (img - grey) * np.float32(np.exp(rng.uniform(np.log(0.35), np.log(1.3))))  # saturation
    m = img.mean()
    img = m + (img - m) * np.float32(rng.uniform(0.6, 1.25))  # contrast
    img = np.clip(img, 0, 1) ** np.float32(np.exp(rng.uniform(np.log(0.6), np.log(1.6))))  # gamma
    img = img * np.float32(rng.uniform(0.6, 1.4)) * rng.uniform(0.85, 1.15, 3).astype(np.float32)  # exposure, WB
    if rng.uniform() < 1 / 3:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 1.5))
    img = img + rng.normal(0, rng.uniform(0, 0.03), img.shape).astype(np.float32)
    return np.clip(img, 0, 1).astype(np.float32)


def fit_net(frames: list[LabelledFrame], *, iterations: int = 2000, crop: int = 128, batch: int = 12,
            seed: int = 0, threads: int = 2, scale: tuple[float, float] | None = (0.7, 1.6), jitter: str = "wide",
            arch: str = "unet", log=print) -> Any:
    """A small fully convolutional network (torch, training extra) on RGB crops; returns the torch module.

    Half-resolution trunk (a stride-2 convolution, then dilated 3 x 3 convolutions of dilation 1, 2, 4, 8: a
    receptive field of about 66 px), a 1 x 1 logit and a bilinear upsampling back to full resolution. Crops
    get flips and colour jitter (exposure, per-channel gain, saturation) so the net cannot lean on one
    look's exact colours (`photometric_jitter`), and a random scale (`scale`: None for none)."""
    import cv2
    import torch
    from torch import nn

    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    net = FruitUNet() if arch == "unet" else FruitNet()
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=3e-3, total_steps=iterations, pct_start=0.1)
    loss_fn = nn.BCEWithLogitsLoss()
    fruit_frames = [i for i, f in enumerate(frames) if (f.instances > 0).any()]
    t0 = time.perf_counter()
    for it in range(iterations):
        xs, ys = [], []
        for _ in range(batch):
            # half the crops centred on fruit when the frame has some: fruit is 1-3 % of the pixels
            f = frames[int(rng.choice(fruit_frames)) if rng.uniform() < 0.7 else int(rng.integers(len(frames)))]
            h, w = f.instances.shape
            # scale: fruit from 0.7x to 1.6x the pixels they have at the simulator's range (a nearer camera, a
            # longer lens); the crop taken at crop / scale px and resized to crop
            s = float(np.exp(rng.uniform(np.log(scale[0]), np.log(scale[1])))) if scale else 1.0
            c = min(int(round(crop / s)), h, w)
            yx = np.argwhere(f.instances > 0)
            if len(yx) and rng.uniform() < 0.5:
                cy, cx = yx[rng.integers(len(yx))]
                y0 = int(np.clip(cy - rng.integers(c), 0, h - c))
                x0 = int(np.clip(cx - rng.integers(c), 0, w - c))
            else:
                y0, x0 = int(rng.integers(h - c + 1)), int(rng.integers(w - c + 1))
            img = f.rgb[y0:y0 + c, x0:x0 + c].astype(np.float32) / 255.0
            lab = (f.instances[y0:y0 + c, x0:x0 + c] > 0).astype(np.float32)
            if c != crop:
                img = cv2.resize(img, (crop, crop), interpolation=cv2.INTER_AREA if c > crop else cv2.INTER_LINEAR)
                lab = (cv2.resize(lab, (crop, crop), interpolation=cv2.INTER_LINEAR) >= 0.5).astype(np.float32)
            if rng.uniform() < 0.5:
                img, lab = img[:, ::-1], lab[:, ::-1]
            img = photometric_jitter(np.ascontiguousarray(img), rng, jitter)
            xs.append(img.transpose(2, 0, 1))
            ys.append(lab[None])
        x = torch.from_numpy(np.ascontiguousarray(np.stack(xs)))
        y = torch.from_numpy(np.ascontiguousarray(np.stack(ys)))
        loss = loss_fn(net(x), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if it % 100 == 0 or it == iterations - 1:
            log(f"iteration {it}: loss {loss.item():.4f} ({time.perf_counter() - t0:.0f} s)")
    return net.eval()


def FruitNet() -> Any:  # noqa: N802 (a factory standing for a class: torch is imported only here)
    import torch
    from torch import nn

    class _Net(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            c = 24
            self.body = nn.Sequential(
                nn.Conv2d(3, 16, 3, stride=2, padding=1), nn.ReLU(),
                nn.Conv2d(16, c, 3, padding=1), nn.ReLU(),
                nn.Conv2d(c, c, 3, padding=2, dilation=2), nn.ReLU(),
                nn.Conv2d(c, c, 3, padding=4, dilation=4), nn.ReLU(),
                nn.Conv2d(c, c, 3, padding=8, dilation=8), nn.ReLU(),
                nn.Conv2d(c, 1, 1))

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            y = self.body(x)
            return nn.functional.interpolate(y, size=x.shape[-2:], mode="bilinear", align_corners=False)

    return _Net()


def FruitUNet() -> Any:  # noqa: N802 (a factory standing for a class: torch is imported only here)
    """A small encoder-decoder: three stride-2 stages (16, 32, 64 channels), dilated 3 x 3 convolutions
    (1, 2, 4) at 1/8 resolution (about 230 px seen round each pixel: a fruit's round outline and the leaves
    round it, not only its colour), decoded back to 1/2 resolution with the encoder's features (skips), a
    logit upsampled to full resolution. About the multiply-adds of FruitNet per pixel."""
    import torch
    from torch import nn

    def conv(i: int, o: int, stride: int = 1, dilation: int = 1) -> list[Any]:
        return [nn.Conv2d(i, o, 3, stride=stride, padding=dilation, dilation=dilation, bias=False),
                nn.BatchNorm2d(o), nn.ReLU()]

    class _UNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.e1 = nn.Sequential(*conv(3, 16, 2), *conv(16, 16))
            self.e2 = nn.Sequential(*conv(16, 32, 2), *conv(32, 32))
            self.e3 = nn.Sequential(*conv(32, 64, 2), *conv(64, 64), *conv(64, 64, dilation=2),
                                    *conv(64, 64, dilation=4))
            self.d2 = nn.Sequential(*conv(96, 32))
            self.d1 = nn.Sequential(*conv(48, 16))
            self.head = nn.Conv2d(16, 1, 1)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            up = nn.functional.interpolate
            a = self.e1(x)
            b = self.e2(a)
            c = self.e3(b)
            b = self.d2(torch.cat([up(c, size=b.shape[-2:], mode="bilinear", align_corners=False), b], 1))
            a = self.d1(torch.cat([up(b, size=a.shape[-2:], mode="bilinear", align_corners=False), a], 1))
            return up(self.head(a), size=x.shape[-2:], mode="bilinear", align_corners=False)

    return _UNet()


def export_net(net: Any, path: Path, threshold: float, meta: dict[str, Any]) -> Path:
    """ONNX (opset 17) of net: input `rgb` (1, 3, H, W) float32 in [0, 1], output `logit` (1, 1, H, W); the
    threshold and meta go into the model's metadata (read by core.fruit_pixels.load_model)."""
    import onnx
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(net, torch.zeros(1, 3, 96, 128), str(path), input_names=["rgb"], output_names=["logit"],
                      dynamic_axes={"rgb": {2: "h", 3: "w"}, "logit": {2: "h", 3: "w"}}, opset_version=17,
                      dynamo=False)
    model = onnx.load(str(path))
    for k, v in {"schema": fp.SCHEMA, "threshold": repr(threshold), "meta": json.dumps(meta)}.items():
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, str(path))
    return path


class _TorchScores:
    """A torch module in the pixel model interface (threshold selection before export)."""

    def __init__(self, net: Any) -> None:
        self.net = net
        self.threshold = 0.0

    def scores(self, rgb: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            x = torch.from_numpy(rgb.astype(np.float32).transpose(2, 0, 1)[None] / 255.0)
            return self.net(x)[0, 0].numpy()


def best_threshold(model: Any, frames: list[LabelledFrame]) -> tuple[float, float]:
    """The score threshold of best pixel F1 over frames, and that F1 (validation frames only)."""
    scores = np.concatenate([model.scores(f.rgb).ravel() for f in frames])
    truth = np.concatenate([(f.instances > 0).ravel() for f in frames])
    order = np.argsort(-scores)
    tp = np.cumsum(truth[order])
    k = np.arange(1, tp.size + 1)
    f1 = 2 * tp / (k + truth.sum())
    i = int(np.argmax(f1))
    return float(scores[order[i]]), float(f1[i])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="models")
    ap.add_argument("--scenes", type=int, default=len(TRAIN_SEEDS))
    ap.add_argument("--frames", type=int, default=4, help="frames per side and scene")
    ap.add_argument("--space", default=fp.DEFAULT_GMM_SPACE)
    ap.add_argument("--components", type=int, nargs=2, default=list(fp.DEFAULT_GMM_COMPONENTS))
    ap.add_argument("--iterations", type=int, default=2000, help="network training iterations")
    ap.add_argument("--only", choices=["gmm", "net"], default=None)
    ap.add_argument("--scale", type=float, nargs=2, default=[0.7, 1.6], metavar=("LO", "HI"),
                    help="network crops rescaled by a factor drawn in [LO, HI] (1 1: none)")
    ap.add_argument("--jitter", choices=["narrow", "wide"], default="wide", help="photometric jitter of the crops")
    ap.add_argument("--arch", choices=["unet", "dilated"], default="unet",
                    help="network: FruitUNet or the earlier FruitNet (dilated convolutions at 1/2 resolution)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    train, val = training_frames(a.scenes, a.frames)
    print(f"{len(train)} training frames, {len(val)} validation frames ({time.perf_counter() - t0:.0f} s)")
    out = Path(a.out)
    meta = {"train_seeds": list(TRAIN_SEEDS[: a.scenes]), "train_standard_seeds":
            list(TRAIN_STANDARD_SEEDS[: max(1, a.scenes // 2)]), "validation_seeds": list(VALIDATION_SEEDS),
            "validation_standard_seeds": list(VALIDATION_STANDARD_SEEDS),
            "frames_per_side": a.frames, "seed_tag": SEED_TAG, "trees": 2,
            "train_varied_seeds": list(TRAIN_VARIED_SEEDS[: a.scenes]),
            "validation_varied_seeds": list(VALIDATION_VARIED_SEEDS)}
    if a.only in (None, "gmm"):
        gmm = fit_gmm(train, a.space, tuple(a.components))
        th, f1 = best_threshold(gmm, val)
        gmm = fp.ColourGmm(gmm.space, gmm.fruit, gmm.other, th)
        fp.save_model(gmm, out / "fruit_colour_gmm.json", {**meta, "validation_pixel_f1": round(f1, 4)})
        print(f"GMM {a.space} {a.components}: threshold {th:.3f}, validation pixel F1 {f1:.4f}")
    if a.only in (None, "net"):
        scale = tuple(a.scale) if a.scale != [1.0, 1.0] else None
        net = fit_net(train, iterations=a.iterations, scale=scale, jitter=a.jitter, arch=a.arch)
        th, f1 = best_threshold(_TorchScores(net), val)
        export_net(net, out / "fruit_net.onnx", th, {**meta, "iterations": a.iterations, "scale": scale, "jitter": a.jitter, "arch": a.arch,
                                                     "validation_pixel_f1": round(f1, 4)})
        print(f"network: threshold {th:.3f}, validation pixel F1 {f1:.4f}")
    print(json.dumps({"seconds": round(time.perf_counter() - t0, 1)}))


if __name__ == "__main__":
    main()
