"""Benchmark: the node graph's Fast DDS profile (config/fastdds_large_messages.xml) against Fast DDS's default,
for the camera stream between two processes on one machine.

A publisher process sends colour (640x480 rgb8, 0.9 MB) and depth (640x480 32FC1, 1.2 MB) images at
`--rate` Hz, reliably (as the bag player does); a subscriber process takes them with the odometry node's
camera QoS (best effort, a queue of 60) and records each image's latency (publish -> callback, the header
stamp is the publish time). Per profile: images sent, received, lost, latency median and 95th percentile,
and the packets the machine's other interfaces sent meanwhile (discovery must stay on loopback:
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST is set here, as in every process the project starts).

Usage: python benchmarks/dds_profile.py [--rate 30] [--seconds 10] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from orchard_mapping.io.results import portable_json
from orchard_mapping.resources import config_dir

CHILD = r"""
import json, sys, time
import numpy as np
import rclpy
from sensor_msgs.msg import Image
from orchard_mapping.ros.qos import CAMERA, REPLAY
role, rate, seconds = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
rclpy.init()
node = rclpy.create_node(f"dds_bench_{role}")
if role == "pub":
    pubs = {t: node.create_publisher(Image, t, REPLAY) for t in ("/bench/color", "/bench/depth")}
    deadline = time.monotonic() + 20
    while min(p.get_subscription_count() for p in pubs.values()) == 0 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    time.sleep(1.0)
    imgs = {}
    for t, (enc, bpp) in {"/bench/color": ("rgb8", 3), "/bench/depth": ("32FC1", 4)}.items():
        m = Image(); m.height, m.width, m.encoding, m.step = 480, 640, enc, 640 * bpp
        m.data = np.random.default_rng(0).integers(0, 256, 480 * 640 * bpp, dtype=np.uint8).tobytes()
        imgs[t] = m
    n = int(rate * seconds); t0 = time.monotonic()
    for i in range(n):
        while time.monotonic() < t0 + i / rate:
            time.sleep(0.0005)
        for t, m in imgs.items():
            ns = time.time_ns(); m.header.stamp.sec, m.header.stamp.nanosec = ns // 10**9, ns % 10**9
            pubs[t].publish(m)
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps({"sent": 2 * n}))
else:
    lat = []
    def cb(m):
        lat.append((time.time_ns() - (m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)) / 1e6)
    for t in ("/bench/color", "/bench/depth"):
        node.create_subscription(Image, t, cb, CAMERA)
    end = time.monotonic() + seconds + 30
    last = [0, time.monotonic()]
    while time.monotonic() < end:  # until 3 s without a new image after the first
        rclpy.spin_once(node, timeout_sec=0.05)
        if len(lat) != last[0]:
            last = [len(lat), time.monotonic()]
        elif lat and time.monotonic() - last[1] > 3.0:
            break
    print(json.dumps({"latency_ms": lat}))
node.destroy_node(); rclpy.try_shutdown()
"""


def _tx_packets() -> int:
    """Packets sent by every interface but loopback."""
    total = 0
    for d in Path("/sys/class/net").iterdir():
        if d.name != "lo":
            try:
                total += int((d / "statistics" / "tx_packets").read_text())
            except OSError:
                pass
    return total


def run(profile: Path | None, rate: float, seconds: float) -> dict:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(60 + os.getpid() % 40))
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    if profile is not None:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
    tx0 = _tx_packets()
    sub = subprocess.Popen([sys.executable, "-c", CHILD, "sub", str(rate), str(seconds)], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pub = subprocess.run([sys.executable, "-c", CHILD, "pub", str(rate), str(seconds)], env=env,
                         capture_output=True, text=True, timeout=seconds + 60)
    out, err = sub.communicate(timeout=60)
    if pub.returncode != 0 or not out.strip():
        raise SystemExit(f"bench child failed:\n{pub.stderr[-2000:]}\n{err[-2000:]}")
    sent = json.loads(pub.stdout.strip().splitlines()[-1])["sent"]
    lat = np.array(json.loads(out.strip().splitlines()[-1])["latency_ms"])
    return {"profile": profile.name if profile else "Fast DDS default", "sent": sent, "received": int(lat.size),
            "lost": sent - int(lat.size), "latency_median_ms": float(np.median(lat)) if lat.size else None,
            "latency_p95_ms": float(np.percentile(lat, 95)) if lat.size else None,
            "other_interfaces_tx_packets": _tx_packets() - tx0, "stderr": (pub.stderr + err)[-500:]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=2, help="runs per profile, alternating")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = []
    for _ in range(args.repeat):
        for profile in (None, config_dir() / "fastdds_large_messages.xml"):
            rows.append(run(profile, args.rate, args.seconds))
            r = rows[-1]
            print(f"{r['profile']:28s} sent {r['sent']:5d} received {r['received']:5d} lost {r['lost']:5d} "
                  f"latency median {r['latency_median_ms'] or float('nan'):7.2f} ms p95 "
                  f"{r['latency_p95_ms'] or float('nan'):7.2f} ms  other interfaces: "
                  f"{r['other_interfaces_tx_packets']} packets", flush=True)
            if "rror" in r["stderr"]:
                print("  stderr:", r["stderr"].strip().replace("\n", " | ")[:300])
    if args.json:
        args.json.write_text(portable_json(rows, indent=1))


if __name__ == "__main__":
    main()
