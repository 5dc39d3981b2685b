"""Fruit pixels and fruit instances in a colour image (the first step of yield mapping).

Two per-pixel classifiers share one interface (`pixel_scores`: a log-odds-like score per pixel, fruit where
the score is above the model's threshold):

  ColourGmm   a Gaussian mixture per class (fruit, everything else) on the colour of the pixel alone, the
              family of Roy et al. / Häni et al.; the score is the log-likelihood ratio. It is evaluated once
              per model over a 64^3 RGB table (`LUT_LEVELS`), so a frame costs a table look-up.
  FruitNet    a small fully convolutional network on RGB (about 66 px seen round each pixel: colour and
              shape), run with onnxruntime on the CPU; the score is its logit.

The GMM is fitted with scikit-learn and stored as JSON, the network trained with torch and exported to ONNX
(`orchard_mapping.train.fruit_pixels`); running them needs numpy, OpenCV and onnxruntime only.
`segment_fruit` thresholds the scores, cleans the mask and
splits it into instances: connected components, and touching fruit split at the necks of the distance
transform (one instance per distance peak that a neck separates from the higher ones; pixels go to the peak of
least power distance, which cuts two overlapping discs along their common chord).

Nothing here knows the simulator: input is any (H, W, 3) uint8 RGB image.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from orchard_mapping.errors import OrchardMappingError

__all__ = [
    "ColourGmm", "FrameScore", "FruitImageError", "FruitMask", "FruitMaskParams", "FruitModelError",
    "FruitNet", "FruitPixelError", "FruitPixelModel", "Gaussians", "load_model", "pixel_features",
    "pixel_scores", "save_model", "score_frame", "segment_fruit", "split_instances",
]

SCHEMA = "orchard_mapping.fruit_pixels/1"
COLOUR_SPACES = ("rgb", "lab", "ab", "hsv", "ycrcb")
LUT_LEVELS = 64  # RGB quantised to 64 levels per channel (4 grey levels a bin) for the GMM's table
# validation pixel F1 (randomised look, 6 + 12 components): Lab 0.784, RGB 0.783, HSV 0.760, YCrCb 0.725, ab 0.411
DEFAULT_GMM_SPACE = "lab"
DEFAULT_GMM_COMPONENTS = (6, 12)  # (fruit, other): validation F1 0.784 in Lab, (2, 4) 0.778, (4, 8) 0.769


class FruitPixelError(OrchardMappingError):
    """Fruit segmentation cannot run on this input or model."""


class FruitImageError(FruitPixelError):
    """The image is not an (H, W, 3) uint8 RGB array (the message says what it is)."""


class FruitModelError(FruitPixelError):
    """A fruit pixel model file is missing, unreadable or of the wrong schema (the message names the file)."""


# --- features -------------------------------------------------------------------------------------------------


def check_image(rgb: Any) -> np.ndarray:
    """rgb as a (H, W, 3) uint8 array, or FruitImageError naming what it got."""
    if not isinstance(rgb, np.ndarray):
        raise FruitImageError(f"image must be a numpy array, got {type(rgb).__name__}")
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise FruitImageError(f"image must be (H, W, 3) RGB, got shape {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise FruitImageError(f"image must be uint8, got {rgb.dtype} (shape {rgb.shape})")
    return rgb


def _colour(rgb01: np.ndarray, space: str) -> np.ndarray:
    """(..., 3) float32 RGB in [0, 1] -> (..., C) float32 in `space` (hue turned so red is not at the wrap)."""
    img = np.ascontiguousarray(rgb01.reshape(-1, 1, 3), np.float32)  # (N, 1, 3): cvtColor wants an image
    if space == "rgb":
        out = img
    elif space in ("lab", "ab"):
        out = cv2.cvtColor(img, cv2.COLOR_RGB2Lab)  # L 0..100, a b about -128..127
        out = out[..., 1:] if space == "ab" else out
    elif space == "hsv":
        out = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)  # H 0..360 deg, S V 0..1
        out[..., 0] = np.mod(out[..., 0] + 180.0, 360.0) / 360.0  # red at 0.5, cyan at the wrap
    elif space == "ycrcb":
        out = cv2.cvtColor(img, cv2.COLOR_RGB2YCrCb)
    else:
        raise FruitModelError(f"unknown colour space '{space}' (known: {', '.join(COLOUR_SPACES)})")
    return out.reshape(*rgb01.shape[:-1], out.shape[-1])


def pixel_features(rgb: np.ndarray, space: str) -> np.ndarray:
    """(H*W, C) float32 colour of every pixel of rgb (H, W, 3) uint8 in `space` (COLOUR_SPACES)."""
    check_image(rgb)
    x = _colour(rgb.astype(np.float32) * np.float32(1 / 255), space)  # (H, W, C)
    return x.reshape(-1, x.shape[-1])


# --- models ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Gaussians:
    """A Gaussian mixture: K components in D dimensions, full covariances."""

    weights: np.ndarray  # (K,)
    means: np.ndarray  # (K, D)
    covariances: np.ndarray  # (K, D, D)

    def log_likelihood(self, x: np.ndarray) -> np.ndarray:
        """(N,) log density of the mixture at x (N, D), by the Cholesky factor of each covariance."""
        x = np.asarray(x, np.float64)
        terms = np.empty((len(self.weights), len(x)))  # (K, N)
        d = x.shape[1]
        for k, (w, mu, cov) in enumerate(zip(self.weights, self.means, self.covariances, strict=True)):
            chol = np.linalg.cholesky(cov)  # (D, D) lower
            z = np.linalg.solve(chol, (x - mu).T)  # (D, N)
            log_det = 2.0 * np.sum(np.log(np.diag(chol)))
            terms[k] = np.log(w) - 0.5 * (np.sum(z * z, axis=0) + log_det + d * np.log(2 * np.pi))
        top = terms.max(axis=0)
        return top + np.log(np.sum(np.exp(terms - top), axis=0))


@dataclass(frozen=True)
class ColourGmm:
    """Fruit by colour alone: log p(colour | fruit) - log p(colour | other) > threshold."""

    space: str
    fruit: Gaussians
    other: Gaussians
    threshold: float

    @cached_property
    def table(self) -> np.ndarray:
        """(L, L, L) float32 score of every quantised RGB colour (bin centres), L = LUT_LEVELS."""
        step = 256 // LUT_LEVELS
        c = (np.arange(LUT_LEVELS, dtype=np.float32) * step + (step - 1) / 2) / 255.0
        grid = np.stack(np.meshgrid(c, c, c, indexing="ij"), axis=-1).reshape(-1, 3)  # (L^3, 3) RGB
        x = _colour(grid, self.space)
        score = self.fruit.log_likelihood(x) - self.other.log_likelihood(x)
        return score.astype(np.float32).reshape(LUT_LEVELS, LUT_LEVELS, LUT_LEVELS)

    def scores(self, rgb: np.ndarray) -> np.ndarray:
        q = rgb >> np.uint8(8 - int(np.log2(LUT_LEVELS)))  # (H, W, 3) bin index per channel
        return self.table[q[..., 0], q[..., 1], q[..., 2]]


@dataclass(frozen=True)
class FruitNet:
    """Fruit from a small fully convolutional network (ONNX, onnxruntime on the CPU): logit > threshold.

    Contract: input `rgb` (1, 3, H, W) float32 RGB in [0, 1], any H and W; output (1, 1, H, W) logits. The
    threshold is in the ONNX file's metadata (`threshold`), so the file alone is the model."""

    path: Path
    threshold: float
    threads: int = 2

    @cached_property
    def session(self) -> Any:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.threads
        opts.inter_op_num_threads = 1
        try:
            return ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own types for unreadable or invalid graphs
            raise FruitModelError(f"{self.path}: cannot load the fruit network: {err}") from err

    def scores(self, rgb: np.ndarray) -> np.ndarray:
        x = (rgb.astype(np.float32) * np.float32(1 / 255)).transpose(2, 0, 1)[None]  # (1, 3, H, W)
        sess = self.session
        return sess.run(None, {sess.get_inputs()[0].name: np.ascontiguousarray(x)})[0][0, 0]


FruitPixelModel = ColourGmm | FruitNet


def pixel_scores(rgb: np.ndarray, model: FruitPixelModel) -> np.ndarray:
    """(H, W) float32 score per pixel of rgb (H, W, 3) uint8: fruit where it exceeds model.threshold."""
    return model.scores(check_image(rgb))


def _arr(a: np.ndarray) -> list:
    return np.asarray(a).tolist()


def save_model(model: ColourGmm, path: str | Path, meta: dict[str, Any] | None = None) -> Path:
    """Write a colour GMM as JSON (schema SCHEMA), with free-form `meta` (training data, seeds, figures).
    The network is written as ONNX by orchard_mapping.train.fruit_pixels.export_net."""
    body: dict[str, Any] = {"kind": "colour_gmm", "space": model.space, "threshold": model.threshold}
    for name, g in (("fruit", model.fruit), ("other", model.other)):
        body[name] = {"weights": _arr(g.weights), "means": _arr(g.means), "covariances": _arr(g.covariances)}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"schema": SCHEMA, **body, "meta": meta or {}}, separators=(",", ":")) + "\n")
    return path


def load_model(path: str | Path) -> FruitPixelModel:
    """A model written by save_model; FruitModelError naming the file for anything else."""
    path = Path(path)
    if path.suffix == ".onnx":
        return _load_net(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise FruitModelError(f"{path}: cannot read fruit pixel model: {err}") from err
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        raise FruitModelError(f"{path}: not a fruit pixel model (schema must be {SCHEMA})")
    try:
        if doc["kind"] == "colour_gmm":
            g = {k: Gaussians(np.asarray(doc[k]["weights"], float), np.asarray(doc[k]["means"], float),
                              np.asarray(doc[k]["covariances"], float)) for k in ("fruit", "other")}
            model: FruitPixelModel = ColourGmm(str(doc["space"]), g["fruit"], g["other"], float(doc["threshold"]))
            _colour(np.zeros((1, 3), np.float32), model.space)  # unknown space: FruitModelError now, not later
        else:
            raise FruitModelError(f"{path}: unknown model kind '{doc['kind']}'")
    except (KeyError, TypeError, ValueError) as err:
        raise FruitModelError(f"{path}: malformed fruit pixel model: {err!r}") from err
    return model


def _load_net(path: Path) -> FruitNet:
    if not path.is_file():
        raise FruitModelError(f"{path}: fruit network not found")
    net = FruitNet(path, 0.0)
    meta = net.session.get_modelmeta().custom_metadata_map
    if meta.get("schema") != SCHEMA or "threshold" not in meta:
        raise FruitModelError(f"{path}: ONNX file without fruit pixel metadata (schema {SCHEMA}, threshold)")
    try:
        threshold = float(meta["threshold"])
    except ValueError as err:
        raise FruitModelError(f"{path}: bad threshold {meta['threshold']!r}") from err
    out = FruitNet(path, threshold)
    out.__dict__["session"] = net.session  # the session already made (cached_property's slot)
    return out


# --- masks and instances --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FruitMaskParams:
    """Mask cleaning and instance splitting (chosen on the validation seeds of train/fruit_pixels.py)."""

    # Components smaller than this are dropped (px): speckle of fruit-coloured noise; a fruit seen whole is
    # 60-1300 px in the simulated 640 x 480 frames.
    min_area_px: int = 12
    # Opening, then closing of the mask by a disc of this radius (px, 0: none). Closing joins the pieces of a
    # fruit cut by a twig but also touching fruit: with the true mask on the validation seeds it lowered
    # instance recall from 0.732 to 0.712 (1 px), 0.663 (2 px).
    open_radius_px: int = 0
    close_radius_px: int = 0
    # "distance": split touching fruit at the distance transform's necks (see _peaks);
    # "none": one instance per connected component.
    split: Literal["distance", "none"] = "distance"
    # Distance peaks lower than this (px, distance to the background) seed no instance of their own.
    min_peak_px: float = 3.0
    # A lower peak seeds its own fruit only where the distance between it and each higher peak dips below this
    # times its own (a neck between two fruit); two discs of radius r whose centres are 1.9 r apart dip to 0.3.
    neck_ratio: float = 0.5
    # Peaks lower than this times the component's highest peak seed no instance: a lobe of a partly hidden fruit
    # (touching fruit of one size at one distance have about equal peaks).
    peak_ratio: float = 0.75
    # Measured on the validation seeds with the true fruit mask (only the splitting scored), instance recall of
    # all fruit >= 20 px / of fruit >= 50 % visible: one instance per component 0.769 / 0.864; these values
    # 0.780 / 0.895 (instance precision 0.660 -> 0.616); neck_ratio 0.7: 0.773 / 0.880, 0.85: 0.767 / 0.864;
    # peak_ratio 0.5 or min_peak_px 2 split the lobes of fruit seen between leaves (precision 0.35-0.58).


@dataclass(frozen=True)
class FruitMask:
    mask: np.ndarray  # (H, W) bool, fruit pixels after cleaning
    instances: np.ndarray  # (H, W) int32: 0 background, 1..count one per fruit
    count: int


def _peaks(dist: np.ndarray, params: FruitMaskParams) -> np.ndarray:
    """(P, 2) int (row, col) of the distance transform's peaks that seed instances, highest first.

    A lower peak is its own fruit only when the distance dips between it and every higher peak kept: on the
    segment joining them the distance falls below `neck_ratio` times the lower peak's (a neck, as between two
    touching discs). Along the ridge of one elongated or partly hidden fruit it does not dip."""
    local = (dist >= cv2.dilate(dist, np.ones((3, 3), np.uint8))) & (dist >= params.min_peak_px)
    rc = np.argwhere(local)  # (P0, 2)
    if len(rc) <= 1:
        return rc
    height = dist[rc[:, 0], rc[:, 1]]
    order = np.argsort(-height, kind="stable")
    rc, height = rc[order], height[order]
    tall = height >= params.peak_ratio * height[0]  # a second fruit of about the same size, not a lobe
    rc, height = rc[tall], height[tall]
    t = np.linspace(0.0, 1.0, 16)[:, None]  # (16, 1) samples along a segment
    keep: list[int] = []
    for i in range(len(rc)):
        own = True
        for k in keep:
            pts = np.rint(rc[k] + t * (rc[i] - rc[k])).astype(int)  # (16, 2)
            if dist[pts[:, 0], pts[:, 1]].min() >= params.neck_ratio * height[i]:
                own = False
                break
        if own:
            keep.append(i)
    return rc[keep]


def split_instances(mask: np.ndarray, params: FruitMaskParams | None = None) -> tuple[np.ndarray, int]:
    """(instances (H, W) int32, count) of a boolean mask (H, W): its components, touching fruit split."""
    params = params or FruitMaskParams()
    if mask.ndim != 2 or mask.dtype != bool:
        raise FruitImageError(f"mask must be (H, W) bool, got shape {mask.shape} dtype {mask.dtype}")
    m8 = mask.astype(np.uint8)
    n, comp, stats, _ = cv2.connectedComponentsWithStats(m8, connectivity=8)
    small = stats[:, cv2.CC_STAT_AREA] < params.min_area_px  # (n,)
    small[0] = True
    comp[small[comp]] = 0
    if params.split == "none":
        labels = np.cumsum(~small) * ~small  # (n,) new label per component, 0 for dropped
        return labels[comp].astype(np.int32), int((~small).sum())
    m8 = (comp > 0).astype(np.uint8)
    dist = cv2.distanceTransform(m8, cv2.DIST_L2, 5)  # (H, W) px to the background
    markers = np.zeros(mask.shape, np.int32)
    count = 0
    for label in np.flatnonzero(~small):
        x, y, w, h = stats[label, :4]
        sub = dist[y:y + h, x:x + w] * (comp[y:y + h, x:x + w] == label)
        pk = _peaks(sub, params)
        if len(pk) <= 1:  # one fruit: the whole component (nothing to split)
            count += 1
            markers[y:y + h, x:x + w][comp[y:y + h, x:x + w] == label] = count
            continue
        # Each pixel to the peak of least power |p - c|^2 - r^2 (c the peak, r its distance): for two
        # overlapping discs the boundary is the chord through their two intersection points.
        own = comp[y:y + h, x:x + w] == label
        yx = np.argwhere(own)  # (N, 2) in the box
        r = sub[pk[:, 0], pk[:, 1]]  # (P,)
        power = ((yx[:, None, :] - pk[None, :, :]) ** 2).sum(2) - r[None, :] ** 2  # (N, P)
        markers[y + yx[:, 0], x + yx[:, 1]] = count + 1 + np.argmin(power, axis=1)
        count += len(pk)
    return markers, count


def segment_fruit(rgb: np.ndarray, model: FruitPixelModel, params: FruitMaskParams | None = None) -> FruitMask:
    """Fruit pixels and instances of rgb (H, W, 3) uint8 under model (params: FruitMaskParams() when None)."""
    params = params or FruitMaskParams()
    mask = pixel_scores(rgb, model) > model.threshold  # (H, W)
    for r, op in ((params.open_radius_px, cv2.MORPH_OPEN), (params.close_radius_px, cv2.MORPH_CLOSE)):
        if r > 0:
            disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            mask = cv2.morphologyEx(mask.astype(np.uint8), op, disc).astype(bool)
    instances, count = split_instances(mask, params)
    return FruitMask(instances > 0, instances, count)


# --- scoring --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameScore:
    """Pixel counts and instance matches of one frame against its truth."""

    true_positive: int  # fruit pixels predicted fruit
    false_positive: int
    false_negative: int
    true_instances: int  # truth instances with at least min_pixels visible pixels
    found: int  # of those, matched by a predicted instance with IoU >= iou
    predicted: int  # predicted instances
    matched_predictions: int  # predicted instances matched to a counted truth instance


def score_frame(pred: FruitMask, truth: np.ndarray, *, iou: float = 0.5, min_pixels: int = 20,
                counted: np.ndarray | None = None) -> FrameScore:
    """Score pred against truth (H, W) int (0 background, k > 0 one fruit instance).

    A truth instance counts when it has at least `min_pixels` visible pixels (the simulator's visibility rule
    for fruit) and, where `counted` (indexed by truth id, bool) is given, when counted[id]; it is found when one
    predicted instance overlaps it with IoU >= `iou` (above 0.5 at most one can). Predicted instances that
    overlap an uncounted truth instance with IoU >= iou are left out of `predicted`. Pixel counts are over
    all fruit pixels."""
    t = np.asarray(truth).astype(np.int64)
    if t.shape != pred.instances.shape:
        raise FruitImageError(f"truth shape {t.shape} differs from the prediction's {pred.instances.shape}")
    tmask = t > 0
    tp = int(np.count_nonzero(tmask & pred.mask))
    fp = int(np.count_nonzero(~tmask & pred.mask))
    fn = int(np.count_nonzero(tmask & ~pred.mask))
    ids, t_ids = np.unique(np.concatenate([[0], t.ravel()]), return_inverse=True)  # dense ids, 0 background
    t_ids = t_ids[1:].reshape(t.shape)
    nt = int(t_ids.max()) + 1
    p = pred.instances.astype(np.int64)
    npred = int(p.max()) + 1
    inter = np.bincount((p * nt + t_ids).ravel(), minlength=npred * nt).reshape(npred, nt)  # (P+1, T+1)
    t_area = inter.sum(0)
    p_area = inter.sum(1)
    iou_m = inter / np.maximum(p_area[:, None] + t_area[None, :] - inter, 1)
    iou_m = iou_m[1:, 1:]  # (P, T) without background
    use = t_area[1:] >= min_pixels  # (T,)
    if counted is not None:
        use &= np.asarray(counted, bool)[ids[1:]]
    hit = iou_m >= iou
    found = hit.any(0) & use
    ignored = hit[:, ~use].any(1)  # (P,) predictions of fruit that are not counted
    return FrameScore(tp, fp, fn, int(use.sum()), int(found.sum()), int(pred.count - ignored.sum()),
                      int((hit[:, use]).any(1).sum()))
