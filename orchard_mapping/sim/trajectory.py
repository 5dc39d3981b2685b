"""Camera paths along the row, as the paper's field protocol records them.

two_sweep (default, one recording per side): a level sweep at trunk height along
the side, then, after raising the camera on a stick at the row end, back along
the same side with the camera high and tilted down over the canopy. The return
sweep revisits the same trees, which gives loop closure something to find.
single_pass: the level sweep alone. loop: one drive around the row. block: one drive along both sides of
every row of a block (`block_path`).
Poses are T_world_cam of the colour optical frame (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from orchard_mapping.sim.scenario import MotionSpec, PathSpec, Scenario
from orchard_mapping.sim.scene import RowLine, Terrain


@dataclass(frozen=True)
class CameraPath:
    stamps: np.ndarray  # (N,) s, message time
    poses: np.ndarray  # (N, 4, 4) T_world_cam
    sides: np.ndarray  # (N,) str "front" / "back"
    path_length_m: float
    rows: np.ndarray | None = None  # (N,) int, the row each frame films (block drives; None: the one row)


def look_rotation(forward: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Optical-frame rotations (N, 3, 3) looking along `forward` (N, 3) with roll (N,) rad about it."""
    f = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(f, up)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(f, x)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    xr = c * x + s * y
    yr = -s * x + c * y
    return np.stack([xr, yr, f], axis=2)  # columns are the camera axes in world


def _smooth_noise(rng: np.random.Generator, t: np.ndarray, amplitude: float, dims: int) -> np.ndarray:
    """Band-limited hand-held motion (N, dims): a few sinusoids between 0.2 and 2.5 Hz."""
    k = 5
    f = rng.uniform(0.2, 2.5, (dims, k))
    ph = rng.uniform(0, 2 * np.pi, (dims, k))
    a = rng.uniform(0.5, 1.0, (dims, k))
    a *= amplitude / np.sqrt(np.sum(a ** 2, axis=1, keepdims=True) / 2)
    return np.sum(a[None] * np.sin(2 * np.pi * f[None] * t[:, None, None] + ph[None]), axis=2)


def carrier_motion(m: MotionSpec, t: np.ndarray, travelled: np.ndarray, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Walking / vehicle motion of the camera's carrier: position offsets (N, 3) m (world, z up) and angle
    offsets (N, 3) deg (yaw, pitch, roll) at times t (N,) s after the sweep start, `travelled` (N,) m along it.

    Draws from `rng` only for the parts that are switched on, so scenarios without them stay as they were.
    """
    n = len(t)
    pos = np.zeros((n, 3))
    ang = np.zeros((n, 3))
    if m.step_hz > 0:
        ph = rng.uniform(0, 2 * np.pi, 3)
        pos[:, 2] += m.bob_m * np.sin(2 * np.pi * m.step_hz * t + ph[0])
        ang[:, 0] += m.sway_deg * np.sin(np.pi * m.step_hz * t + ph[1])  # once per stride
        ang[:, 2] += m.sway_deg * np.sin(np.pi * m.step_hz * t + ph[2])
    if m.reaim_every_s > 0 and m.reaim_deg > 0 and n > 1:
        t_at = np.cumsum(rng.exponential(m.reaim_every_s, int(t[-1] / m.reaim_every_s) + 3))
        for t0 in t_at[t_at < t[-1]]:
            d = rng.normal(size=2)
            size = m.reaim_deg * rng.uniform(0.5, 1.0)
            u = np.clip((t - t0) / m.reaim_s, 0.0, 1.0)
            swing = size * np.sin(np.pi * u) ** 2  # away and back; peak rate pi size / reaim_s
            ang[:, :2] += swing[:, None] * (d / np.linalg.norm(d))[None]
    if m.vibration_deg > 0 or m.vibration_m > 0:
        for k, amp, out in ((3, m.vibration_m, pos), (3, m.vibration_deg, ang)):
            f = rng.uniform(8.0, 20.0, (k, 4))
            phase = rng.uniform(0, 2 * np.pi, (k, 4))
            out += amp / np.sqrt(2.0) * np.sum(np.sin(2 * np.pi * f[None] * t[:, None, None] + phase[None]), axis=2) / 2
    if m.bump_every_m > 0 and n > 1:
        at = np.cumsum(rng.exponential(m.bump_every_m, int(travelled[-1] / m.bump_every_m) + 3))
        for s0 in at[at < travelled[-1]]:
            t0 = float(np.interp(s0, travelled, t))
            dt = np.clip(t - t0, 0.0, None)
            shake = np.where(t >= t0, np.exp(-dt / m.bump_decay_s) * np.sin(2 * np.pi * 2.5 * dt), 0.0)
            kick = rng.normal(size=3)
            pos[:, 2] += m.bump_m * abs(kick[0]) * shake
            ang[:, 1] += m.bump_deg * kick[1] * shake
            ang[:, 2] += m.bump_deg * kick[2] * shake
    return pos, ang


def _hand_shake(p: PathSpec, t: np.ndarray, travelled: np.ndarray, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray]:
    """(position offset (n, 3) m, angle offset (n, 3) rad) of a hand-held camera at times t (n,): smooth jitter
    plus the carrier's motion (carrier_motion) along the distance travelled (n,) m."""
    jit = _smooth_noise(rng, t, p.jitter_m, 3)
    ang = np.radians(_smooth_noise(rng, t, p.jitter_deg, 3))
    c_pos, c_ang = carrier_motion(p.motion, t, travelled, rng)
    return jit + c_pos, ang + np.radians(c_ang)


def _looking_poses(pos: np.ndarray, yaws: np.ndarray, pits: np.ndarray, roll: np.ndarray
                   ) -> tuple[np.ndarray, float]:
    """(T_world_cam (n, 4, 4), path length m) of cameras at pos (n, 3) looking along yaw and pitch (n,) rad,
    rolled by roll (n,) rad."""
    fwd = np.stack([np.cos(pits) * np.cos(yaws), np.cos(pits) * np.sin(yaws), np.sin(pits)], 1)
    T = np.tile(np.eye(4), (len(pos), 1, 1))
    T[:, :3, :3] = look_rotation(fwd, roll)
    T[:, :3, 3] = pos
    return T, float(np.sum(np.linalg.norm(np.diff(pos, axis=0), axis=1)))


def _ease(u: np.ndarray) -> np.ndarray:
    return u * u * (3 - 2 * u)


def side_path(sc: Scenario, side: str, row_x: tuple[float, float], terrain: Terrain,
              rng: np.random.Generator, t0: float) -> CameraPath:
    """The camera path of one side ("front": y < 0 looking +y; "back": y > 0 looking -y)."""
    p = sc.path
    rate = sc.camera.rate_hz
    x_lo = row_x[0] - sc.row.margin_m
    x_hi = row_x[1] + sc.row.margin_m
    span = p.front_span if side == "front" else p.back_span
    xa = x_lo + span[0] * (x_hi - x_lo)
    xb = x_lo + span[1] * (x_hi - x_lo)
    sgn = -1.0 if side == "front" else 1.0  # camera on y = sgn * distance
    yaw = np.pi / 2 if side == "front" else -np.pi / 2
    # The front side is walked towards +x, the back side towards -x (walking around the row), or towards +x
    # too (path.back_direction "same": both passes started at the same row end).
    start, end = (xa, xb) if side == "front" or p.back_direction == "same" else (xb, xa)

    if p.mode == "loop":
        return _loop_path(sc, row_x, terrain, rng, t0, xa, xb)

    t_sweep = abs(end - start) / p.speed_mps
    n_sweep = max(2, int(round(t_sweep * rate)))
    u = _ease(np.linspace(0, 1, n_sweep))
    xs = [start + u * (end - start)]
    hs = [np.full(n_sweep, p.low_height_m)]
    dist = [np.full(n_sweep, p.distance_m)]
    pitch = [np.zeros(n_sweep)]
    if p.mode == "two_sweep":
        n_turn = max(2, int(round(p.turn_s * rate)))
        ut = _ease(np.linspace(0, 1, n_turn + 2)[1:-1])
        xs.append(np.full(n_turn, end))
        hs.append(p.low_height_m + ut * (p.high_height_m - p.low_height_m))
        dist.append(p.distance_m + ut * (p.high_distance_m - p.distance_m))
        pitch.append(-ut * np.radians(p.high_tilt_deg))
        xs.append(end + u * (start - end))
        hs.append(np.full(n_sweep, p.high_height_m))
        dist.append(np.full(n_sweep, p.high_distance_m))
        pitch.append(np.full(n_sweep, -np.radians(p.high_tilt_deg)))
    x = np.concatenate(xs)
    h = np.concatenate(hs)
    pit = np.concatenate(pitch)
    n = len(x)
    t = np.arange(n) / rate
    y = sgn * np.concatenate(dist)
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(h)))])
    jit, ang = _hand_shake(p, t, travelled, rng)
    pos = np.stack([x, y, terrain.height(x, y) + h], 1) + jit
    T, length = _looking_poses(pos, yaw + ang[:, 0], pit + ang[:, 1], np.radians(p.roll_deg) + ang[:, 2])
    return CameraPath(t0 + t, T, np.full(n, side), length)


def _loop_path(sc: Scenario, row_x: tuple[float, float], terrain: Terrain, rng: np.random.Generator,
               t0: float, xa: float, xb: float) -> CameraPath:
    """Front side towards +x, half circle round the row end, back side towards -x; level camera."""
    p = sc.path
    rate = sc.camera.rate_hz
    d = p.distance_m
    ds = p.speed_mps / rate
    s1 = np.arange(0, xb - xa, ds)
    arc = np.arange(0, np.pi * d, ds) / d  # angle swept round the end
    s3 = np.arange(0, xb - xa, ds)
    x = np.concatenate([xa + s1, xb + d * np.sin(arc), xb - s3])
    y = np.concatenate([np.full(len(s1), -d), -d * np.cos(arc), np.full(len(s3), d)])
    # Look at the row: +y on the front side, towards the row end during the turn, -y on the back side.
    yaw = np.concatenate([np.full(len(s1), np.pi / 2), np.pi / 2 + arc, np.full(len(s3), -np.pi / 2)])
    sides = np.array(["front"] * (len(s1) + len(arc) // 2) + ["back"] * (len(arc) - len(arc) // 2 + len(s3)))
    t, T, length = _level_walk_poses(p, x, y, yaw, rate, rng, terrain)
    return CameraPath(t0 + t, T, sides, length)


def block_path(sc: Scenario, rows: tuple[RowLine, ...], terrain: Terrain, rng: np.random.Generator, t0: float
               ) -> CameraPath:
    """One drive along both sides of every row of a block, the camera looking left of the way it goes (at the
    row it drives along), level at trunk height: row k's front side (y_k - distance) towards +x, a half circle
    round the row end (the camera looking at it), its back side (y_k + distance) towards -x; then a half circle
    in the headland that brings it into the same alley the other way round (the camera looking out of the turn),
    on to row k + 1's front side. Every row's passes span the block's length (its longest row and
    row.margin_m). Each frame's side and row: half of each turn to the pass before it, half to the next, as
    the loop path labels its turn."""
    p = sc.path
    rate = sc.camera.rate_hz
    d = p.distance_m
    r_alley = sc.block.row_spacing_m / 2 - d  # radius of the turn into the alley the other way round
    ds = p.speed_mps / rate
    x_lo = min(r.x[0] for r in rows) - sc.row.margin_m
    x_hi = max(r.x[1] for r in rows) + sc.row.margin_m
    s = np.arange(0, x_hi - x_lo, ds)  # along a side
    # Both turns at the heading rate of the one round the row end (speed / distance): a vehicle slows down in
    # the tighter turn in the alley, and the front end sees the same change of view per frame in both.
    arc = np.arange(0, np.pi * d, ds) / d  # rad swept
    xs, ys, yaws, sides, row_no = [], [], [], [], []

    def add(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, side: list[str], row: int) -> None:
        xs.append(x)
        ys.append(y)
        yaws.append(yaw)
        sides.extend(side)
        row_no.extend([row] * len(x))

    half = len(arc) // 2
    for k, line in enumerate(rows):
        y0, n = line.y, line.number
        add(x_lo + s, np.full(len(s), y0 - d), np.full(len(s), np.pi / 2), ["front"] * len(s), n)
        # round the row end, anticlockwise: the camera looks at the turn's centre, the row end
        a = -np.pi / 2 + arc
        add(x_hi + d * np.cos(a), y0 + d * np.sin(a), a + np.pi, ["front"] * half + ["back"] * (len(arc) - half), n)
        add(x_hi - s, np.full(len(s), y0 + d), np.full(len(s), -np.pi / 2), ["back"] * len(s), n)
        if k + 1 == len(rows):
            break
        # into the alley again, clockwise round a centre half way between the two rows: the camera looks out
        a = -np.pi / 2 - arc
        yc = y0 + sc.block.row_spacing_m / 2
        xs_, ys_ = x_lo + r_alley * np.cos(a), yc + r_alley * np.sin(a)
        add(xs_[:half], ys_[:half], a[:half], ["back"] * half, n)
        add(xs_[half:], ys_[half:], a[half:], ["front"] * (len(arc) - half), rows[k + 1].number)
    x = np.concatenate(xs)
    y = np.concatenate(ys)
    yaw = np.concatenate(yaws)
    t, T, length = _level_walk_poses(p, x, y, yaw, rate, rng, terrain)
    return CameraPath(t0 + t, T, np.array(sides), length, np.array(row_no))


def _level_walk_poses(p, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, rate: float, rng: np.random.Generator,
                      terrain) -> tuple[np.ndarray, np.ndarray, float]:
    """A level camera along ground track (x, y) (N,) m looking at yaw (N,) rad, at rate Hz, with the hand's or
    vehicle's shake: times (N,) s from the start, poses (N, 4, 4) world, path length m."""
    t = np.arange(len(x)) / rate
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    jit, ang = _hand_shake(p, t, travelled, rng)
    pos = np.stack([x, y, terrain.height(x, y) + p.low_height_m], 1) + jit
    T, length = _looking_poses(pos, yaw + ang[:, 0], ang[:, 1], np.radians(p.roll_deg) + ang[:, 2])
    return t, T, length
