"""Per-sample compute time of every controller with its null-space policies over 40 obstacles.

Thesis figures (MATLAB, per sample): acceleration 2.6 ms, velocity 2.2 ms, joint space 1.7 ms,
gradient-guided 2.3 ms (SPEC R1). Target (issue 4): <= 10 us per state at batch 1024.

For each controller: ``jit`` (batch 1) and ``jit(vmap)`` at batch 20 and 1024, warm, with
``block_until_ready``; compile time separately. With batch 1 also "loop": 1024 (or the largest
batch's) states one after another in one ``jit(lax.map)`` call, per state (a single call is mostly
per-call dispatch; the loop is the control law's own sequential time, what the study reports as
``t_controller_per_sample``). Under JAX's default XLA flags each iteration still runs as a
sequence of kernels; the study's workers compile the loop as one function (XLA flags
``redman_jax._study.WORKER_XLA_FLAGS``: ``--study-flags``) for the study's figure. With ``--devices``
each device runs the loop over its shard of the states. A deliberately naive layout of the acceleration OSC
(separate FK passes for every Jacobian, POI Jacobians by ``jax.jacfwd``, a full SVD for sigma_min, the
reference per-point vmap of ``_fields.obstacle_field_gradient``, ``M`` and ``c + g`` formed
explicitly, ``J_dot q_dot`` by a jvp) is timed in the same run as "before".

Run: ``python benchmarks/bench_controllers.py [--batches 1,20,1024] [--dof 9] [--devices N] [--study-flags]
[--scene mixed|spheres|boxes|cylinders]``
(``JAX_PLATFORMS=cpu taskset -c 0,1`` for the 2-core CPU figure). ``--devices 2`` splits the CPU
into two XLA devices and runs every batch they divide (20, 1024) as one shard per device
(``shard_map``), as a user would spread a batch over the cores; the naive layout stays on one
device (see ``sharded`` in ``main``).
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import redman_jax as rj
from redman_jax._control_types import ControlState, RefSample, make_environment
from redman_jax._controllers import CONTROLLERS
from redman_jax._nullspace import obstacle_gradients
from redman_jax._report import _cpu_model  # the CPU's model name, as the study report's machine row gives it

THESIS_MS = {"acceleration": 2.6, "velocity": 2.2, "joint_space": 1.7, "gradient": 2.3}
LOOP_STATES = 1024  # states of the "loop" row, at least


SCENES = {"mixed": (12, 16, 12), "spheres": (40, 0, 0), "boxes": (0, 40, 0), "cylinders": (0, 0, 40)}


def scene(rng, kind: str = "mixed"):
    """40 obstacles, random poses around the arm: ``mixed`` 12 spheres, 16 boxes, 12 cylinders
    (the issue's scene); ``spheres``, ``boxes`` or ``cylinders`` 40 of one shape (what each shape
    costs)."""
    n_sph, n_box, n_cyl = SCENES[kind]

    def rot():
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        return Q * np.sign(np.linalg.det(Q))

    def pos():
        while True:
            p = rng.uniform([-1, -1, 0], [1, 1, 2])
            if np.hypot(p[0], p[1]) > 0.45:
                return p

    sph = [(rot(), pos(), [rng.uniform(0.05, 0.1)]) for _ in range(n_sph)]
    box = [(rot(), pos(), rng.uniform(0.05, 0.15, 3)) for _ in range(n_box)]
    cyl = [(rot(), pos(), [rng.uniform(0.03, 0.08), rng.uniform(0.1, 0.3)]) for _ in range(n_cyl)]
    return rj.make_obstacles(sph, box, cyl)


def naive_acceleration(arm, obs):
    """The straightforward layout ("before")."""
    from redman_jax._kinematics import poi_positions

    def ctrl(gains, state, ref):
        q, qd = state.q, state.qd
        J = rj.jacobian(arm, q)
        p, quat = rj.end_effector_pose(arm, q)
        Jdqd = rj.jdot_qdot(arm, q, qd)
        M = rj.mass_matrix(arm, q)
        bias = rj.bias_forces(arm, q, qd)
        S = jnp.array([1, 1, 1, 0.2, 0.2, 0.2])
        Js = S[:, None] * J
        smin = jnp.linalg.svd(Js, compute_uv=False)[-1]
        lam = jnp.maximum(0.1 * smin, 0.01)
        Jp = Js.T @ jnp.linalg.inv(Js @ Js.T + lam**2 * jnp.eye(6))
        e_o = rj._math.clip_norm(rj._math.quat_error(ref.quat, quat), 0.075)
        xdd = jnp.concatenate([ref.a + 31 * (ref.v - J[:3] @ qd) + 250 * (ref.p - p),
                               ref.omega_dot + 100 * (ref.omega - J[3:] @ qd) + 2000 * e_o])
        pois = poi_positions(arm, q)
        Jpoi = jax.jacfwd(lambda qq: poi_positions(arm, qq))(q)  # (m, 3, n)
        g = obstacle_gradients(obs, pois, 0.05, 0.75, impl="reference")
        h = jnp.einsum("mjn,mj->n", Jpoi, -1000.0 * g)
        from redman_jax._nullspace import joint_limit_policy

        h = h + joint_limit_policy(arm, q, 100.0, 5000.0) - 800.0 * qd
        qdd = Jp @ (xdd - S * Jdqd) + 0.1 * (jnp.eye(arm.n_dof) - Jp @ Js) @ h
        return M @ qdd + bias

    return ctrl


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batches", default="1,20,1024")
    ap.add_argument("--dof", type=int, default=9)
    ap.add_argument("--controllers", default="joint_space,velocity,acceleration,gradient,pid,velocity_original,impedance")
    ap.add_argument("--calls", type=int, default=2048, help="at least this many states per timing (and >= 10 calls, >= 0.3 s)")
    ap.add_argument("--devices", type=int, default=None,
                    help="CPU: split the host into this many XLA devices (--xla_force_host_platform_device_count) "
                         "and run every batch they divide as one shard per device")
    ap.add_argument("--study-flags", action="store_true",
                    help="start XLA with the study workers' flags (redman_jax._study.WORKER_XLA_FLAGS: the older "
                         "loop emitters, every while loop compiled as one function, LLVM level 1)")
    ap.add_argument("--scene", choices=sorted(SCENES), default="mixed",
                    help="the 40 obstacles: mixed (12 spheres, 16 boxes, 12 cylinders; default, the issue's "
                         "scene) or 40 of one shape")
    args = ap.parse_args()
    if args.devices is not None or args.study_flags:
        from _xla_start import start_with_host_devices, start_with_xla_flags

        from redman_jax._study import WORKER_XLA_FLAGS

        extra = WORKER_XLA_FLAGS if args.study_flags else ()
        if args.devices is not None:
            start_with_host_devices(args.devices, extra)
        else:
            start_with_xla_flags(extra, "--study-flags")
    print(f"jax {jax.__version__}, backend {jax.default_backend()}, devices {jax.devices()}, "
          f"x64 {jax.config.jax_enable_x64}, {_cpu_model()}, scene {args.scene}, "
          f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    devices = jax.devices()
    mesh = Mesh(np.array(devices), ("batch",))
    spec = PartitionSpec("batch")

    def sharded(B, naive):
        """Whether a batch runs as one shard per device: where the devices divide it, and never for
        the naive layout, whose LAPACK calls (SVD, inverse) can deadlock jaxlib's CPU thread pool when
        several host devices run them at once (seen on 2 cores: every pool thread waiting in
        ``jax::ParallelBatchMap`` of the batched SVD kernel)."""
        return len(devices) > 1 and B % len(devices) == 0 and not naive

    def batched(body, args, B, naive):
        """``(jit(body), args)``; sharded, each device runs ``body`` on its own shard of ``args`` (no
        communication; ``shard_map``'s varying-type check on, as a user would have it)."""
        if not sharded(B, naive):
            return jax.jit(body), args
        f = jax.jit(jax.shard_map(body, mesh=mesh, in_specs=spec, out_specs=spec))
        return f, jax.device_put(args, NamedSharding(mesh, spec))
    rng = np.random.default_rng(0)
    arm = rj.thesis_arm(args.dof)
    n = arm.n_dof
    obs = scene(rng, args.scene)
    bmax = max(max(int(b) for b in args.batches.split(",")), LOOP_STATES)  # the batches take the first B
    qs = jnp.asarray(np.asarray(arm.q0) + rng.uniform(-0.3, 0.3, (bmax, n)))
    qds = jnp.asarray(rng.normal(size=(bmax, n)) * 0.1)
    p, quat = jax.vmap(lambda q: rj.end_effector_pose(arm, q))(qs)
    env = make_environment(obs, p[0] + 0.3, quat[0])
    z3 = jnp.zeros((bmax, 3))
    refs = RefSample(p=p + 0.01, v=z3, a=z3, quat=quat, omega=z3, omega_dot=z3, rot=jnp.ones((bmax,)),
                     q=qs + 0.01, qd=jnp.zeros_like(qs), qdd=jnp.zeros_like(qs))

    def timed(f, *a, batch):
        """(median, min) us per state over repeats of at least ``--calls`` states and 0.3 s, and the
        compile + first call time. The median of many repeats, not the mean of a few: on a shared
        2-core machine single calls vary by 30 % or more."""
        t0 = time.perf_counter()
        jax.block_until_ready(f(*a))
        tc = time.perf_counter() - t0
        ts, start = [], time.perf_counter()
        while len(ts) < 10 or ((len(ts) * batch < args.calls or time.perf_counter() - start < 0.3)
                               and len(ts) < 2000):
            t1 = time.perf_counter()
            jax.block_until_ready(f(*a))
            ts.append(time.perf_counter() - t1)
        return float(np.median(ts)) / batch * 1e6, float(np.min(ts)) / batch * 1e6, tc

    rows = []

    def report(name, label, count, us, us_min, tc):
        base = THESIS_MS.get(name.replace("_naive", ""))
        ratio = f"{base * 1e3 / us:8.0f}x" if base else "       -"
        rows.append((name, count if label == "batch" else -count, us, us_min, tc))
        print(f"{name:20s} {label:5s} {count:5d}: {us:9.2f} us/state median, {us_min:7.2f} min  (thesis/this {ratio})"
              f"  compile {tc:5.1f} s", flush=True)

    names = args.controllers.split(",")
    entries = [(nm, CONTROLLERS[nm]()) for nm in names] + [("acceleration_naive", None)]
    for name, ctrl in entries:
        if ctrl is None:
            fn = naive_acceleration(arm, obs)
            gains = None
            zs = jnp.zeros((bmax, 0))
            call = lambda g, q, qd, z, ref: fn(g, ControlState(t=jnp.zeros(()), q=q, qd=qd, z=()), ref)
        else:
            gains = ctrl.default_gains()
            zs = jax.vmap(lambda q: ctrl.init_state(arm, q, q))(qs)
            zs = jnp.zeros((bmax, 0)) if not jax.tree.leaves(zs) else zs
            call = (lambda ctrl: lambda g, q, qd, z, ref: ctrl(
                g, arm, ControlState(t=jnp.zeros(()), q=q, qd=qd, z=() if z.shape == (0,) else z),
                ref, env).tau)(ctrl)
        for B in (int(b) for b in args.batches.split(",")):
            sl = jax.tree.map(lambda x: x[:B], (qs, qds, zs, refs))
            if B == 1:
                one = jax.tree.map(lambda x: x[0], sl)
                f = jax.jit(lambda g, q, qd, z, ref, call=call: call(g, q, qd, z, ref))
                us, us_min, tc = timed(f, gains, *one, batch=1)
                # all the states one after another in one call (lax.map; sharded: each device over
                # its own): the control law's own time per sample, without the per-call dispatch
                # (the study's t_controller_per_sample)
                fl, la = batched(lambda q, qd, z, ref, call=call, gains=gains: jax.lax.map(
                    lambda a: call(gains, *a), (q, qd, z, ref)), (qs, qds, zs, refs), bmax, naive=ctrl is None)
                report(name, "loop", bmax, *timed(fl, *la, batch=bmax))
            else:
                f, a = batched(jax.vmap(lambda q, qd, z, ref, call=call, gains=gains: call(gains, q, qd, z, ref)),
                               sl, B, naive=ctrl is None)
                us, us_min, tc = timed(f, *a, batch=B)
            report(name, "batch", B, us, us_min, tc)
    return rows


if __name__ == "__main__":
    main()
