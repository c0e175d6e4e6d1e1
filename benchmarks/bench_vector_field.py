"""Per-state cost of the simulator's closed-loop vector field and of its obstacle passes.

What diffrax evaluates 6-7 times per step: the controller, forward dynamics with the joint-limit
contact, and the collision flag (smallest point-of-interest distance to every obstacle); timed for
each study controller with ``jit(vmap)`` at batch 20 (the study: one case's seeds) and 1024, on the
9-DOF arm with 40 random obstacles (12 spheres, 16 boxes, 12 cylinders; the scene of
``bench_controllers.py``). Also the two obstacle passes alone: the policy gradient over all points
(``obstacle_gradients``, fused vs the per-point reference) and the flag's distances
(``points_min_distance`` vs the per-point ``(m, K)`` evaluation it replaced).

``--case NAME`` (e.g. ``warehouse``) takes the obstacles of that generated case instead (seed 1,
compacted, laid out for each batch size as the simulator lays them out: the warehouse's boxes in
groups, ``_sim.obstacle_layout``), and times the closed loop only. For the figures of the
study's workers run it on one core: ``taskset -c 0`` with the study's ``XLA_FLAGS``
(``redman_jax._study.WORKER_XLA_FLAGS``).

Run: ``python benchmarks/bench_vector_field.py [--batches 20,1024] [--controllers ...] [--case NAME]``
"""

from __future__ import annotations

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import redman_jax as rj
from bench_controllers import scene
from redman_jax import _sim
from redman_jax._control_types import RefSample, make_environment
from redman_jax._controllers import CONTROLLERS
from redman_jax._kinematics import kinematics, poi_positions_from
from redman_jax._nullspace import obstacle_gradients


def timed(f, B, *args, repeat=7):
    g = jax.jit(jax.vmap(f))
    jax.block_until_ready(g(*args))
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(g(*args))
        ts.append(time.perf_counter() - t)
    return min(ts) / B * 1e6


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batches", default="20,1024")
    ap.add_argument("--controllers", default="joint_space,velocity,acceleration,gradient")
    ap.add_argument("--case", default=None, help="the obstacles of this generated case (seed 1)")
    args = ap.parse_args()
    arm = rj.thesis_arm(9)
    n = arm.n_dof
    obs = scene(np.random.default_rng(0))
    if args.case is not None:
        from redman_jax._obstacles import compact_obstacles

        obs = compact_obstacles(rj.make_scenario(args.case, 1, arm).obstacles)
    rng = np.random.default_rng(1)
    a, D = jnp.asarray(0.05), jnp.asarray(0.75)
    print(f"jax {jax.__version__}, {jax.devices()[0]}, {platform.machine()}, x64={jax.config.jax_enable_x64}; "
          f"us per state (best of 7); obstacles {args.case or 'random 40'} {obs.capacities}")
    for B in (int(b) for b in args.batches.split(",")):
        Q = jnp.asarray(rng.uniform(-1, 1, (B, n)))
        QD = jnp.asarray(rng.uniform(-1, 1, (B, n)))
        o = obs
        if args.case is not None:  # the simulator's layout at this batch size, its used-slot bound
            from redman_jax._obstacles import used_bound, with_used

            o = _sim.obstacle_layout(arm, obs, _sim.SimParams(), B)
            o = with_used(o, used_bound(o))
        env = make_environment(o, jnp.array([0.3, 0.2, 0.8]), jnp.array([1.0, 0, 0, 0]), 20)
        if args.case is None:  # the two obstacle passes alone (random scene)
            pois = lambda q: poi_positions_from(arm, kinematics(arm, q), q)  # noqa: E731
            ref_d = timed(lambda q: jax.vmap(lambda x: jnp.min(rj.obstacle_distances(obs, x)))(pois(q)), B, Q)
            new_d = timed(lambda q: rj.points_min_distance(obs, pois(q)), B, Q)
            ref_g = timed(lambda q: obstacle_gradients(obs, pois(q), a, D, impl="reference"), B, Q)
            new_g = timed(lambda q: obstacle_gradients(obs, pois(q), a, D), B, Q)
            print(f"batch {B:5d}  flag distances: per-point {ref_d:7.2f}  fused {new_d:6.2f}   "
                  f"policy gradients: reference {ref_g:7.2f}  fused {new_g:6.2f}")
        for name in args.controllers.split(","):
            c = CONTROLLERS[name]()
            g = c.default_gains()
            p = _sim.SimParams()

            def vf(q, qd, c=c, g=g, p=p):
                rs = RefSample(p=jnp.array([0.3, 0.2, 0.8]), v=jnp.zeros(3), a=jnp.zeros(3),
                               quat=jnp.array([1.0, 0, 0, 0]), omega=jnp.zeros(3), omega_dot=jnp.zeros(3),
                               rot=jnp.asarray(1.0), q=q, qd=qd, qdd=qd)
                z = _sim._pack_z(c.init_state(arm, q, qd), q.dtype)
                y = _sim._Y(q=q, qd=qd, z=z, f=jnp.zeros(3, q.dtype))
                return _sim._closed_loop(0.0, y, rs, env, True, arm, c, g, p)

            print(f"batch {B:5d}  closed-loop vector field {name:13s} {timed(vf, B, Q, QD):7.2f}")


if __name__ == "__main__":
    main()
