"""Micro-benchmark of the MCAP writer and reader on synthetic simulator arrays.

Writes an episode of ``--steps`` simulation steps with ``--vehicles`` vehicles: ``/vehicles`` and
``/ego/state`` every step (the per-step cost reported), and optionally ``/tf`` every step and the
image, ``/scene`` and ``/rl/step`` every ``--decision-every`` steps. Then reads it back and reports
tracks rows per second. Run from a checkout::

    python tools/bench_mcap_io.py --steps 20000 --vehicles 101
"""

from __future__ import annotations

import argparse
import logging
import pathlib
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lcdata import EpisodeWriter, read_episode  # noqa: E402

log = logging.getLogger("bench_mcap_io")


def synthetic_state(steps: int, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Highway-like (steps, n) arrays: vehicles cruising along x on 4 lanes."""
    rng = np.random.default_rng(seed)
    speed = 6.7 + rng.normal(0, 0.5, (steps, n))
    x = rng.uniform(0, 500, n) + np.cumsum(speed * 0.05, axis=0)
    lane = np.broadcast_to(rng.integers(0, 4, n), (steps, n))
    y = (lane + 0.5) * 3.5 + rng.normal(0, 0.05, (steps, n))
    return {
        "x": x, "y": y, "yaw": rng.normal(0, 0.01, (steps, n)), "speed": speed,
        "accel": rng.normal(0, 0.2, (steps, n)), "lane": np.ascontiguousarray(lane),
        "length": np.full(n, 4.5), "width": np.full(n, 1.9),
    }  # fmt: skip


def bench_write(
    path: pathlib.Path, steps: int, n: int, decision_every: int, extras: bool
) -> tuple[float, float]:
    """Write one episode; return (wall, main-thread CPU) seconds spent in the /vehicles + /ego/state calls."""
    s = synthetic_state(steps, n)
    ids = np.arange(n, dtype=np.int64)
    image = np.random.default_rng(1).integers(0, 255, (3, 120, 120), dtype=np.uint8)
    per_step = cpu = 0.0
    with EpisodeWriter(path, metadata={"config": {"bench": True}, "seed": 0}, overwrite=True) as w:
        for k in range(steps):
            t_s = k * 0.05
            t0, c0 = time.perf_counter(), time.thread_time()
            w.write_vehicles(k, t_s, ids, s["x"][k], s["y"][k], s["yaw"][k], s["speed"][k], s["accel"][k],
                             s["lane"][k], s["lane"][k], s["length"], s["width"])  # fmt: skip
            w.write_ego(k, t_s, speed=s["speed"][k, 0], lane=s["lane"][k, 0], collision_with=-1,
                        lane_invasion=-1, off_road=False, steer=0.01, throttle=0.3, brake=0.0)  # fmt: skip
            per_step += time.perf_counter() - t0
            cpu += time.thread_time() - c0
            if extras:
                w.write_transform(k, t_s, s["x"][k, 0], s["y"][k, 0], s["yaw"][k, 0])
                if k % decision_every == 0:
                    w.write_image(k, t_s, image)
                    w.write_scene(k, t_s, ids, s["x"][k], s["y"][k], s["yaw"][k], s["length"], s["width"])
                    w.write_rl_step(k, t_s, action=1, action_mask=[True, True, True], reward=0.3,
                                    reward_components={"forward": 0.3}, obs_current=np.zeros((9, 9)))  # fmt: skip
    return per_step, cpu


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="MCAP writer/reader micro-benchmark")
    parser.add_argument("--steps", type=int, default=10000)
    parser.add_argument("--vehicles", type=int, default=101)
    parser.add_argument("--decision-every", type=int, default=10)
    parser.add_argument("--out", type=pathlib.Path, default=None, help="keep the file here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory() as tmp:
        path = args.out or pathlib.Path(tmp) / "bench.mcap"
        t0, p0 = time.perf_counter(), time.process_time()
        hot, cpu = bench_write(path, args.steps, args.vehicles, args.decision_every, extras=False)
        total, process = time.perf_counter() - t0, time.process_time() - p0
        log.info("write /vehicles + /ego/state (%d vehicles, %d steps, %.1f MB), per step: %.1f us wall and "
                 "%.1f us main-thread CPU in the calls; %.1f us wall and %.1f us process CPU (compression "
                 "thread included) for the whole episode", args.vehicles, args.steps, path.stat().st_size / 1e6,
                 hot / args.steps * 1e6, cpu / args.steps * 1e6, total / args.steps * 1e6,
                 process / args.steps * 1e6)  # fmt: skip
        t0 = time.perf_counter()
        bench_write(path, args.steps, args.vehicles, args.decision_every, extras=True)
        total = time.perf_counter() - t0
        log.info("write all topics (tf every step; image, scene, rl step every %d): %.1f us/step wall "
                 "(%.1f MB)", args.decision_every, total / args.steps * 1e6, path.stat().st_size / 1e6)  # fmt: skip
        t0 = time.perf_counter()
        episode = read_episode(path)
        tracks = episode.tracks
        dt = time.perf_counter() - t0
        log.info("read tracks: %d rows in %.3f s = %.2f M rows/s", len(tracks), dt, len(tracks) / dt / 1e6)
        t0 = time.perf_counter()
        n_images = sum(1 for _ in episode.images())
        log.info("ego %d rows, steps %d rows, %d images decoded in %.3f s", len(episode.ego), len(episode.steps),
                 n_images, time.perf_counter() - t0)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
