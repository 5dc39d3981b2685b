"""Rebuild the real-photo evaluation set (benchmarks/data/real_photos/) from its upstream git repositories.

Never used for training or tuning: see README.md beside this file. Each source is read from a local git
clone (any clone holding the pinned commit) with `git show`, converted and written under OUT/<source>/:

  agrivision_cherry  MachineLearningVisionRG/AgriVision-Cherry @ 25ab4bb4, "Single Cherry Dataset":
                     RGB crops of single dormant cherry trees (ZED Mini) with hand-drawn class masks
                     (trunk / branch / limb). Every 5th crop (indices 0, 5, 10, ...); the trunk class
                     (mask colour BGR (0, 0, 128)) becomes one "trunk" instance (COCO RLE). Images are
                     re-encoded as JPEG (quality 85) at their own size (all under 640 px wide).
  osu_apple_rgbd     Jostan86/trunk_width_estimator @ cc18f59d, data/trunk_gt_data/row{96,97,98}/N.png + N.npy
                     and data/trunk_gt/row_{96,97,98}_diameters.csv: RealSense frames of apple trees
                     (640x480 in row 96, 1280x720 in rows 97-98), the z of each pixel's point (m), and the
                     caliper diameter of the tree each frame was taken of (the source's evaluator maps frame N
                     to CSV row N). Every 3rd frame (1, 4, 7, ...). Colour -> JPEG 85 at most 640 px wide;
                     depth -> 16-bit PNG in cm at half the JPEG's size (each block: median of its valid
                     pixels; 0: none), to keep the set small;
                     no masks or boxes: the measured tree is the one nearest the image's centre column.

Usage: python benchmarks/data/real_photos/convert.py --cherry-git DIR --osu-git DIR [--out DIR]
(DIR: a git directory or work tree of each repository.)
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import subprocess
from pathlib import Path

import cv2
import numpy as np

CHERRY_COMMIT = "25ab4bb46b82fa601611f4b5106f5f0e00723066"
OSU_COMMIT = "cc18f59d4f4525f3849d01bd0bec4c6054ac3b2f"
CHERRY_TRUNK_BGR = (0, 0, 128)
CHERRY_EVERY = 5
OSU_EVERY = 3
OSU_VFOV_DEG = 42.0  # the source's width estimator: metres per pixel = z * 2 tan(21 deg) / image height
JPEG_QUALITY = 85
MAX_WIDTH = 640
CATEGORIES = [{"id": 1, "name": "trunk"}, {"id": 2, "name": "post"}]


def git_show(git: str, commit: str, path: str) -> bytes:
    return subprocess.run(["git", f"--git-dir={git}", "show", f"{commit}:{path}"], check=True,
                          capture_output=True).stdout


def git_dir(path: str) -> str:
    p = Path(path)
    return str(p / ".git") if (p / ".git").exists() else str(p)


def write_jpeg(path: Path, bgr: np.ndarray) -> None:
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    assert ok
    path.write_bytes(buf.tobytes())


def rle(mask: np.ndarray) -> dict:
    from pycocotools import mask as mask_util

    r = mask_util.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": [int(s) for s in r["size"]], "counts": r["counts"].decode("ascii")}


def convert_cherry(git: str, out: Path) -> None:
    from pycocotools import mask as mask_util

    out.mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    images, anns = [], []
    names = subprocess.run(["git", f"--git-dir={git}", "ls-tree", "--name-only", CHERRY_COMMIT,
                            "Single Cherry Dataset/RGB Imagaes/"], check=True, capture_output=True,
                           text=True).stdout.split("\n")
    indices = sorted(int(Path(n).stem.rsplit("_", 1)[1]) for n in names if n.endswith(".jpg"))
    for k in indices[::CHERRY_EVERY]:
        rgb = cv2.imdecode(np.frombuffer(git_show(git, CHERRY_COMMIT,
                           f"Single Cherry Dataset/RGB Imagaes/RGB_Image_Filename_{k}.jpg"), np.uint8),
                           cv2.IMREAD_COLOR)
        lab = cv2.imdecode(np.frombuffer(git_show(git, CHERRY_COMMIT,
                           f"Single Cherry Dataset/Masks/Mask_Image_Filename_{k}.png"), np.uint8), cv2.IMREAD_COLOR)
        if rgb is None or lab is None or rgb.shape[:2] != lab.shape[:2]:
            print(f"cherry {k}: unreadable or sizes differ, skipped")
            continue
        h, w = rgb.shape[:2]
        scale = min(1.0, MAX_WIDTH / w)
        if scale < 1.0:
            rgb = cv2.resize(rgb, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
            lab = cv2.resize(lab, (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_NEAREST)
            h, w = rgb.shape[:2]
        trunk = np.all(lab == np.array(CHERRY_TRUNK_BGR, np.uint8), axis=2)
        # branch and limb strokes were drawn over the trunk: close those gaps along the trunk (vertical kernel)
        trunk = cv2.morphologyEx(trunk.astype(np.uint8), cv2.MORPH_CLOSE,
                                 cv2.getStructuringElement(cv2.MORPH_RECT, (3, 15))).astype(bool)
        name = f"images/cherry_{k:03d}.jpg"
        write_jpeg(out / name, rgb)
        img_id = len(images) + 1
        images.append({"id": img_id, "file_name": name, "width": w, "height": h,
                       "source_path": f"Single Cherry Dataset/RGB Imagaes/RGB_Image_Filename_{k}.jpg"})
        if trunk.sum():
            r = rle(trunk)
            bbox = [float(v) for v in mask_util.toBbox({"size": r["size"], "counts": r["counts"].encode()})]
            anns.append({"id": len(anns) + 1, "image_id": img_id, "category_id": 1, "segmentation": r,
                         "bbox": bbox, "area": float(trunk.sum()), "iscrowd": 0})
    doc = {"info": {"source": "MachineLearningVisionRG/AgriVision-Cherry", "commit": CHERRY_COMMIT,
                    "annotation": "mask", "note": "one trunk instance per single-tree crop (hand-drawn)"},
           "images": images, "annotations": anns, "categories": CATEGORIES}
    (out / "instances.json").write_text(json.dumps(doc))
    print(f"agrivision_cherry: {len(images)} images, {len(anns)} trunks")


def _pool_depth(z: np.ndarray, f: int) -> np.ndarray:
    """(H/f, W/f): the median of each f x f block's valid (finite, > 0) depths; NaN where none."""
    if f == 1:
        return z
    H, W = z.shape
    blocks = z[:H - H % f, :W - W % f].reshape(H // f, f, W // f, f).transpose(0, 2, 1, 3).reshape(H // f, W // f, -1)
    blocks = np.where(np.isfinite(blocks) & (blocks > 0), blocks, np.nan)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmedian(blocks, axis=2)


def convert_osu(git: str, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    images = []
    for row in (96, 97, 98):
        table = list(csv.reader(io.StringIO(git_show(git, OSU_COMMIT, f"data/trunk_gt/row_{row}_diameters.csv")
                                            .decode("utf-8"))))
        header, rows = table[0], [r for r in table[1:] if r and r[0].strip()]
        avg = header.index("Average")
        names = subprocess.run(["git", f"--git-dir={git}", "ls-tree", "--name-only", OSU_COMMIT,
                                f"data/trunk_gt_data/row{row}/"], check=True, capture_output=True,
                               text=True).stdout.split("\n")
        frames = sorted(int(Path(n).stem) for n in names if n.endswith(".png"))
        for n in frames[::OSU_EVERY]:
            if n - 1 >= len(rows):
                print(f"osu row {row} frame {n}: no caliper row, skipped")
                continue
            rgb = cv2.imdecode(np.frombuffer(git_show(git, OSU_COMMIT, f"data/trunk_gt_data/row{row}/{n}.png"),
                                             np.uint8), cv2.IMREAD_COLOR)
            z = np.load(io.BytesIO(git_show(git, OSU_COMMIT, f"data/trunk_gt_data/row{row}/{n}.npy"))).astype(np.float32)
            H, W = rgb.shape[:2]
            f = max(1, math.ceil(W / MAX_WIDTH))
            if f > 1:
                rgb = cv2.resize(rgb, (W // f, H // f), interpolation=cv2.INTER_AREA)
            zs = _pool_depth(z, 2 * f)
            h, w = rgb.shape[:2]
            depth_cm = np.where(np.isfinite(zs) & (zs > 0), np.clip(np.round(zs * 100.0), 0, 65535), 0).astype(np.uint16)
            name = f"images/row{row}_{n:03d}.jpg"
            dname = f"depth/row{row}_{n:03d}.png"
            write_jpeg(out / name, rgb)
            cv2.imwrite(str(out / dname), depth_cm, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            fpx = (h / 2.0) / math.tan(math.radians(OSU_VFOV_DEG / 2))
            r = rows[n - 1]
            images.append({"id": len(images) + 1, "file_name": name, "width": w, "height": h,
                           "depth_file": dname, "depth_unit": "cm", "fx": fpx, "fy": fpx, "cx": w / 2.0,
                           "cy": h / 2.0, "caliper_diameter_mm": float(r[avg]), "tree": f"row{row}/{r[0]}",
                           "source_path": f"data/trunk_gt_data/row{row}/{n}.png"})
    doc = {"info": {"source": "Jostan86/trunk_width_estimator", "commit": OSU_COMMIT, "annotation": "caliper",
                    "note": "no masks or boxes: one caliper-measured tree per frame, the one nearest the image's "
                            "centre column; fx from the source's 42 deg vertical field of view"},
           "images": images, "annotations": [], "categories": CATEGORIES}
    (out / "instances.json").write_text(json.dumps(doc, indent=0))
    print(f"osu_apple_rgbd: {len(images)} frames")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cherry-git", help="git directory of MachineLearningVisionRG/AgriVision-Cherry")
    ap.add_argument("--osu-git", help="git directory of Jostan86/trunk_width_estimator")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent))
    a = ap.parse_args()
    if a.cherry_git:
        convert_cherry(git_dir(a.cherry_git), Path(a.out) / "agrivision_cherry")
    if a.osu_git:
        convert_osu(git_dir(a.osu_git), Path(a.out) / "osu_apple_rgbd")


if __name__ == "__main__":
    main()
