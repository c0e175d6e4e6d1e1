"""Planning cost: RRT + smoothing + quartic segments + time scaling (SPEC section 5, thesis 3.2.3).

Two scene families, 20 seeds each, built by hand here (the real generators live in _cases.py):

* simple-obstacle-like: 4 spheres (r 0.07), 3 on a triangle of circumradius 0.16 midway between
  start and goal, perpendicular to the start-goal line (SPEC section 4 "Simple obstacle");
* agriculture-like: 3 trees of tilted cylinders (trunk + 2 branches + 4 twigs) around the arm and
  a goal among the branches with 0.15 m clearance.

For each: a single jitted plan per seed (cold = first call with compilation, warm = mean of the
others) and the 20 seeds at once (``batch="map"``, ``lax.map`` inside one jit, and
``batch="vmap"``), cold and warm; printed per trajectory and per trajectory sample (the thesis's
measure: planning wall time / N_samples).

Run: ``.venv/bin/python benchmarks/bench_planning.py [--seeds 20] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import redman_jax  # noqa: F401  (float64)
from redman_jax._obstacles import make_obstacles, min_distance, stack_obstacles
from redman_jax._planning import RRTParams, plan_reference, plan_reference_batch

START = np.array([0.0, 0.0, 1.2])
CAPS = (4, 1, 21)
TS = 0.01
CAPACITY = 2500


def _frame(axis):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, a), z @ a
    s = np.linalg.norm(v)
    if s < 1e-12:
        return np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K * ((1 - c) / s**2)


def simple_scene(seed):
    rng = np.random.default_rng(seed)
    while True:
        r, th, z = rng.uniform(0.45, 0.7), rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 1.0)
        goal = np.array([r * np.cos(th), r * np.sin(th), z])
        if 0.7 <= np.linalg.norm(goal - START) <= 1.2:
            break
    u = (goal - START) / np.linalg.norm(goal - START)
    e1 = np.cross(u, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    mid, roll = (START + goal) / 2, rng.uniform(0, 2 * np.pi)
    sph = [(np.eye(3), mid + 0.16 * (np.cos(roll + k * 2 * np.pi / 3) * e1
                                    + np.sin(roll + k * 2 * np.pi / 3) * e2), [0.07])
           for k in range(3)]
    sph.append((np.eye(3), START + rng.uniform(0.3, 0.7) * (goal - START)
                + rng.uniform(0.25, 0.35) * e1, [0.07]))
    return make_obstacles(spheres=sph, capacities=CAPS), START, goal


def _random_tilt(rng, d, lo, hi):
    """A unit direction tilted from ``d`` by U[lo, hi] radians about a random perpendicular."""
    d = d / np.linalg.norm(d)
    p = np.cross(d, rng.normal(size=3))
    p /= np.linalg.norm(p)
    t = rng.uniform(lo, hi)
    return np.cos(t) * d + np.sin(t) * p


def agriculture_scene(seed):
    rng = np.random.default_rng(10_000 + seed)
    while True:
        cyl, branches = [], []
        th0 = rng.uniform(0, 2 * np.pi)
        for k in range(3):
            th = th0 + k * 2 * np.pi / 3 + rng.uniform(-np.pi / 6, np.pi / 6)
            base = rng.uniform(0.35, 0.6) * np.array([np.cos(th), np.sin(th), 0.0])
            d = _random_tilt(rng, np.array([0, 0, 1.0]), 0, np.radians(10))
            L, rad = rng.uniform(0.5, 0.8), 0.025
            stack = [(base, d, L, rad)]
            for level in range(3):
                nxt = []
                for (b, dd, LL, rr) in stack:
                    cyl.append((_frame(dd), b + 0.5 * LL * dd, [rr, 0.5 * LL]))
                    if level > 0:
                        branches.append((b, dd, LL))
                    if level < 2:
                        for _ in range(2):
                            for _try in range(20):
                                dc = _random_tilt(rng, dd, np.radians(25), np.radians(50))
                                if dc[2] >= 0.3:
                                    break
                            nxt.append((b + LL * dd, dc, LL * rng.uniform(0.6, 0.8), rr * 0.7))
                stack = nxt
        obs = make_obstacles(cylinders=cyl, capacities=CAPS)
        # start protection (SPEC section 4): 0.20 m from the straight q0 column
        column = jnp.stack([jnp.zeros(25), jnp.zeros(25), jnp.linspace(0.0, 1.2, 25)], 1)
        if float(jax.vmap(lambda x: min_distance(obs, x))(column).min()) < 0.20:
            continue
        for _ in range(50):
            b, dd, LL = branches[rng.integers(len(branches))]
            p = b + rng.uniform(0.3, 1.0) * LL * dd
            off = np.cross(dd, rng.normal(size=3))
            goal = p + rng.uniform(0.15, 0.25) * off / np.linalg.norm(off)
            rho = np.hypot(goal[0], goal[1])
            if 0.25 <= rho <= 0.65 and 0.3 <= goal[2] <= 1.6 and \
                    float(min_distance(obs, jnp.asarray(goal))) >= 0.15:
                return obs, START, goal


def _stack(scenes):
    obs = stack_obstacles([s[0] for s in scenes])
    start = jnp.asarray(np.stack([s[1] for s in scenes]))
    goal = jnp.asarray(np.stack([s[2] for s in scenes]))
    quat = jnp.broadcast_to(jnp.array([1.0, 0, 0, 0]), (len(scenes), 4))
    return obs, start, goal, quat


def _block(x):
    return jax.block_until_ready(x)


def bench_case(name, scenes, params, repeat):
    obs, start, goal, quat = _stack(scenes)
    S = len(scenes)
    keys = jax.random.split(jax.random.PRNGKey(0), S)
    print(f"\n== {name}: {S} seeds, max_nodes {params.max_nodes}, rrt_star {params.rrt_star} ==")

    single = jax.jit(plan_reference, static_argnums=7)
    t0 = time.perf_counter()
    out0 = _block(single(keys[0], scenes[0][0], start[0], goal[0], quat[0], 0.2, TS, CAPACITY, params))
    cold = time.perf_counter() - t0
    times, samples = [], []
    for i in range(S):
        t0 = time.perf_counter()
        o = _block(single(keys[i], scenes[i][0], start[i], goal[i], quat[i], 0.2, TS, CAPACITY, params))
        times.append(time.perf_counter() - t0)
        samples.append(int(o.reference.n_samples))
    times = np.array(times)
    del out0
    print(f"single   cold {cold:7.3f} s | warm {times.mean() * 1e3:8.2f} ms/trajectory "
          f"(min {times.min() * 1e3:.2f}, max {times.max() * 1e3:.2f}) | "
          f"{times.sum() / np.sum(samples) * 1e6:8.2f} us/sample")

    for batch in ("map", "vmap"):
        t0 = time.perf_counter()
        out = _block(plan_reference_batch(keys, obs, start, goal, quat, 0.2, TS, CAPACITY, params,
                                          batch))
        cold = time.perf_counter() - t0
        warm = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            out = _block(plan_reference_batch(keys, obs, start, goal, quat, 0.2, TS, CAPACITY,
                                              params, batch))
            warm.append(time.perf_counter() - t0)
        w = float(np.median(warm))
        n = np.asarray(out.reference.n_samples)
        ok = np.asarray(out.success)
        print(f"batch {batch:4s} cold {cold:7.3f} s | warm {w:7.3f} s = {w / S * 1e3:8.2f} ms/trajectory"
              f" | {w / n.sum() * 1e6:8.2f} us/sample | success {ok.sum()}/{S} | "
              f"iterations mean {np.mean(out.rrt.n_iter):.0f} max {np.max(out.rrt.n_iter)} | "
              f"nodes max {np.max(out.rrt.n_nodes)} | N_samples mean {n[ok].mean():.0f} | "
              f"path {np.mean(out.rrt.cost[ok]):.2f} m | scale c mean {np.mean(out.scale[ok]):.2f}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--star", action="store_true", help="also run rrt_star=True")
    ap.add_argument("--end-factor", type=float, default=1.0)
    args = ap.parse_args()
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, {os.cpu_count()} CPUs, "
          f"python {platform.python_version()}, x64 {jax.config.jax_enable_x64}")
    simple = [simple_scene(s) for s in range(1, args.seeds + 1)]
    agri = [agriculture_scene(s) for s in range(1, args.seeds + 1)]
    params = RRTParams(end_factor=args.end_factor)
    bench_case("simple obstacle", simple, params, args.repeat)
    bench_case("agriculture", agri, params, args.repeat)
    if args.star:
        star = RRTParams(rrt_star=True, end_factor=args.end_factor)
        bench_case("simple obstacle (RRT*)", simple, star, args.repeat)
        bench_case("agriculture (RRT*)", agri, star, args.repeat)


if __name__ == "__main__":
    main()
