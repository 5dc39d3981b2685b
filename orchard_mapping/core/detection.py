"""Trunk detection (paper: "Trunk Detection"): instance masks of trunks and trellis posts.

Detections come from an instance-segmentation model (the ONNX runtime below,
contract in docs/detector.md) or, to measure the geometry alone, from instance
masks on disk (the simulator's, or a user's annotations).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orchard_mapping.errors import OrchardMappingError

__all__ = ["CLASS_NAMES", "CLASS_POST", "CLASS_TRUNK", "Detection", "DetectorError", "OnnxTrunkDetector", "letterbox",
           "OUTPUT_NAMES", "resolve_model_path"]

# The model contract (docs/detector.md): these outputs, by name.
OUTPUT_NAMES = ("boxes", "labels", "scores", "masks")

CLASS_TRUNK = 1
CLASS_POST = 2  # a trellis post is never a trunk (the merge may still use it as a landmark)
CLASS_NAMES = {CLASS_TRUNK: "trunk", CLASS_POST: "post"}


class DetectorError(OrchardMappingError):
    """A detector model or its input cannot be used (the message names the file and what is wrong)."""


@dataclass(frozen=True)
class Detection:
    """One instance in one colour image (pixels of that image)."""

    class_id: int  # CLASS_TRUNK or CLASS_POST
    score: float  # 0..1
    box: np.ndarray  # (4,) float px: x1 y1 x2 y2
    mask: np.ndarray  # (H, W) bool (an ImagePatch of it once the pipeline keeps the detection: core.types)
    source: str = "model"  # what made it: "model" (the detector or given masks) or "geometry" (core.geometric_trunks)

    @staticmethod
    def from_mask(mask: np.ndarray, class_id: int, score: float = 1.0, source: str = "model") -> "Detection":
        v, u = np.nonzero(mask)
        box = np.array([u.min(), v.min(), u.max() + 1, v.max() + 1], float) if len(u) else np.zeros(4)
        return Detection(class_id, float(score), box, np.asarray(mask, bool), source)


def _paste(prob: np.ndarray, box: np.ndarray, H: int, W: int) -> np.ndarray:
    """(H, W) float32: a box-relative mask (M, M) resized into its box x1 y1 x2 y2 (px) of an H x W image."""
    import cv2

    out = np.zeros((H, W), np.float32)
    x1, y1 = int(np.floor(max(box[0], 0))), int(np.floor(max(box[1], 0)))
    x2, y2 = int(np.ceil(min(box[2], W))), int(np.ceil(min(box[3], H)))
    if x2 <= x1 or y2 <= y1:
        return out
    # the full box in pixels, then the part inside the image
    bw, bh = max(1, int(round(box[2] - box[0]))), max(1, int(round(box[3] - box[1])))
    patch = cv2.resize(prob, (bw, bh), interpolation=cv2.INTER_LINEAR)
    ox, oy = int(round(box[0])), int(round(box[1]))
    sx1, sy1 = max(0, -ox), max(0, -oy)
    tx1, ty1 = max(0, ox), max(0, oy)
    tx2, ty2 = min(W, ox + bw), min(H, oy + bh)
    out[ty1:ty2, tx1:tx2] = patch[sy1:sy1 + (ty2 - ty1), sx1:sx1 + (tx2 - tx1)]
    return out


def resolve_model_path(model: str | Path) -> Path:
    """A relative model path is looked up from the working directory, then beside the package (models/)."""
    p = Path(model)
    if p.is_absolute() or p.exists():
        return p
    from orchard_mapping.resources import resource_candidates

    for root in resource_candidates("."):
        if (root / p).exists():
            return root / p
    return p


def letterbox(img: np.ndarray, h: int, w: int) -> tuple[np.ndarray, tuple[float, float]]:
    """img (H, W, 3) uint8 as an (h, w, 3) network input and the (x, y) scale from frame to input px.

    Of the same aspect (within 1 %) the frame is resized to (h, w). Of another aspect it keeps its own:
    resized to fit, at the top left, the rest filled with its mean colour. Stretched instead, a portrait
    crop 318 x 719 px went into a 640 x 480 input 2x wider and 0.67x as tall, its trunk 3x wider for its
    height than any trunk the network was trained on, and a 16:9 frame came in 1.33x taller.
    """
    import cv2

    H, W = img.shape[:2]
    if (H, W) == (h, w):
        return img, (1.0, 1.0)
    if abs((W / H) / (w / h) - 1.0) <= 0.01:
        return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA), (w / W, h / H)
    s = min(w / W, h / H)
    nw, nh = min(w, max(1, round(W * s))), min(h, max(1, round(H * s)))
    out = np.empty((h, w, 3), np.uint8)
    out[:] = img.reshape(-1, 3).mean(axis=0).astype(np.uint8)
    out[:nh, :nw] = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    return out, (nw / W, nh / H)


class OnnxTrunkDetector:
    """An instance-segmentation model in ONNX that follows the contract of docs/detector.md.

    Input: one float32 tensor (3, H, W) or (1, 3, H, W), RGB scaled to [0, 1]. Outputs by name:
    boxes (N, 4) px x1 y1 x2 y2, labels (N,) int class ids (1 trunk, 2 post), scores (N,),
    masks (N, 1, H, W) probabilities; all in input pixels. Frames are resized to the input size and
    the results mapped back to the frame; a frame of another aspect than a fixed input is letterboxed
    (`letterbox`), not stretched.
    """

    def __init__(self, path: str | Path, *, score_threshold: float = 0.5, mask_threshold: float = 0.5,
                 input_size: tuple[int, int] | None = None, threads: int = 2, max_overlap: float = 0.5,
                 flip: bool = False) -> None:
        self.path = resolve_model_path(path)
        if not self.path.is_file():
            raise DetectorError(f"trunk detector model {self.path}: no such file")
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        # Its threads sleep between frames rather than spin: the pipeline runs the detector on a thread beside
        # the front end, on the same cores (beside fusion, spinning threads had slowed both).
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.log_severity_level = 3  # errors only: torchvision exports warn about every variable-size output
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own exception types for unreadable models
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise DetectorError(f"trunk detector model {self.path}: not a usable ONNX model ({first})") from err
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise DetectorError(f"trunk detector model {self.path}: expected 1 input, found "
                                f"{[i.name for i in inputs]}")
        inp = inputs[0]
        shape = list(inp.shape)
        if len(shape) not in (3, 4) or shape[-3] not in (3, "3") and isinstance(shape[-3], int):
            raise DetectorError(f"trunk detector model {self.path}: input '{inp.name}' must have shape (3, H, W) "
                                f"or (1, 3, H, W), got {shape}")
        if inp.type != "tensor(float)":
            raise DetectorError(f"trunk detector model {self.path}: input '{inp.name}' must be float32, got {inp.type}")
        self.input_name = inp.name
        self.batched = len(shape) == 4
        fixed = (shape[-2], shape[-1]) if all(isinstance(d, int) for d in shape[-2:]) else None
        self.input_hw: tuple[int, int] | None = fixed if fixed is not None else (
            (input_size[1], input_size[0]) if input_size and all(input_size) else None)
        outs = {o.name: o for o in self.session.get_outputs()}
        missing = [n for n in OUTPUT_NAMES if n not in outs]
        if missing:
            raise DetectorError(f"trunk detector model {self.path}: outputs {missing} missing (has {sorted(outs)}; "
                                f"the contract needs {list(OUTPUT_NAMES)})")
        ranks = {"boxes": 2, "labels": 1, "scores": 1, "masks": 4}
        for n, r in ranks.items():
            if outs[n].shape is not None and len(outs[n].shape) != r:
                raise DetectorError(f"trunk detector model {self.path}: output '{n}' must have rank {r}, "
                                    f"got shape {outs[n].shape}")
        self.score_threshold = float(score_threshold)
        self.mask_threshold = float(mask_threshold)
        self.max_overlap = float(max_overlap)
        self.flip = bool(flip)

    @staticmethod
    def from_params(p: Any) -> "OnnxTrunkDetector":
        """From the config section `trunks` (core.trunks.TrunkParams)."""
        return OnnxTrunkDetector(p.model, score_threshold=p.score_threshold, mask_threshold=p.mask_threshold,
                                 input_size=(p.input_width, p.input_height), threads=p.threads,
                                 max_overlap=p.max_mask_overlap, flip=p.flip_test)

    def detect(self, color: np.ndarray, where: str = "frame") -> list[Detection]:
        """Detections in one colour image (H, W, 3) uint8 RGB; `where` names the frame in errors."""
        img = np.asarray(color) if color is not None else None
        if img is None or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            got = "nothing" if img is None else f"{img.dtype} {img.shape}"
            raise DetectorError(f"trunk detector: {where}: expected an (H, W, 3) uint8 RGB image, got {got}")
        H, W = img.shape[:2]
        found = self._candidates(img, where)
        if self.flip:
            # Test-time flip: the model also sees the frame mirrored, its detections mirrored back; the two
            # sets are merged by the duplicate rule below. Held-out rows of an unseen scenario: AP50 +0.02;
            # frames like the training ones: -0.003 (models/README.md); twice the time per frame.
            for score, label, b, m in self._candidates(np.ascontiguousarray(img[:, ::-1]), where):
                found.append((score, label, np.array([W - b[2], b[1], W - b[0], b[3]]), m[:, ::-1]))
        # Box NMS keeps a second detection of part of a trunk (its box overlaps the whole trunk's by
        # less than half); such a mask lies mostly inside a better-scored one. As panoptic merging
        # does, a mask whose pixels are more than max_overlap taken by higher-scored ones is dropped.
        # Measured on the 10-tree standard row: 246 such pairs in 147 frames; kept, they made every
        # other view of a trunk 7 px narrower and the diameters 5 mm too small.
        taken = np.zeros((H, W), bool)
        out = []
        for i in np.argsort([-f[0] for f in found], kind="stable"):
            score, label, b, m = found[i]
            area = int(m.sum())
            if not area or (m & taken).sum() > self.max_overlap * area:
                continue
            taken |= m
            out.append(Detection(label, score, b.astype(float), np.ascontiguousarray(m)))
        return out

    def _candidates(self, img: np.ndarray, where: str) -> list[tuple[float, int, np.ndarray, np.ndarray]]:
        """(score, class id, box (4,) frame px, mask (H, W) bool) of each detection at or above the score
        threshold, in the model's order."""
        import cv2

        H, W = img.shape[:2]
        h, w = self.input_hw or (H, W)
        x, scale = letterbox(img, h, w)
        x = np.ascontiguousarray(x.transpose(2, 0, 1), np.float32) / np.float32(255.0)  # (3, h, w)
        if self.batched:
            x = x[None]
        try:
            res = self.session.run(list(OUTPUT_NAMES), {self.input_name: x})
        except Exception as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise DetectorError(f"trunk detector model {self.path}: {where}: inference failed on input "
                                f"{tuple(x.shape)} ({first})") from err
        boxes, labels, scores, masks = (np.asarray(r) for r in res)
        full = masks.ndim == 4 and masks.shape[-2:] == (h, w)  # else box-relative (N, 1, M, M)
        nh, nw = min(h, round(H * scale[1])), min(w, round(W * scale[0]))  # the frame's part of the input
        found = []
        for i in np.flatnonzero(scores >= self.score_threshold):
            b = boxes[i] / np.array([scale[0], scale[1], scale[0], scale[1]])
            prob = masks[i, 0] if masks.ndim == 4 else masks[i]
            if full:
                prob = prob[:nh, :nw]
                if prob.shape != (H, W):
                    prob = cv2.resize(prob.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
                m = prob >= self.mask_threshold
            else:
                m = _paste(prob.astype(np.float32), b, H, W) >= self.mask_threshold
            found.append((float(scores[i]), int(labels[i]), b, m))
        return found
