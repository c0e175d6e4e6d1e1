"""Hangs of jaxlib 0.10's batched CPU LAPACK kernels, and what avoids them (README, "Known issues").

jaxlib 0.10's CPU LAPACK kernels split a large batch over XLA's intra-op thread pool and block
the calling thread until the parts are done. When the program runs as many such calls at once as
the pool has threads (independent calls, run concurrently by XLA's CPU runtime), every pool thread
waits for parts that no thread is left to run: the process hangs, using no CPU. The pool has one
thread per core the process may run on, so a process pinned to one core has a pool of one.

Each row runs in a fresh process with a watchdog (``--timeout`` seconds per call):

* ``4 x cho_solve``: one jitted program of four independent ``vmap``-ed Cholesky solves of 9x9
  matrices, batch ``B``, called ``--reps`` times;
* ``goal_field_minimum``: :func:`redman_jax._guidance.goal_field_minimum` ``vmap``-ed over ``B``
  goals near a sphere, with the step it takes now (unrolled 3x3 ``L D L^T``, no LAPACK) and with
  the one it took before (``jnp.linalg.solve`` and ``jnp.linalg.eigvalsh``: two independent
  LAPACK calls per step).

``pinned``: the process pins itself to one core before importing JAX. Run::

    .venv/bin/python benchmarks/bench_lapack_pool.py            # about 5 minutes on 2 cores
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import textwrap
import time

CHILD = textwrap.dedent(r"""
    import os, sys, time
    what, B, reps, pinned = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
    if pinned:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    import numpy as np, jax, jax.numpy as jnp
    import redman_jax  # noqa: F401  (float64)
    rng = np.random.default_rng(0)
    if what == "cho":
        def spd():
            M = rng.normal(size=(B, 9, 9))
            return M @ np.swapaxes(M, 1, 2) + 9 * np.eye(9)
        args = ([spd() for _ in range(4)], [rng.normal(size=(B, 9)) for _ in range(4)])
        one = lambda A, b: jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(A), b)
        f = jax.jit(lambda As, bs: [jax.vmap(one)(A, b) for A, b in zip(As, bs)])
    else:
        import redman_jax._guidance as G
        from redman_jax._obstacles import make_obstacles
        if what == "gfm_before":
            def before(H, g):
                dx = jnp.linalg.solve(H, g)
                return dx, jnp.all(jnp.linalg.eigvalsh(0.5 * (H + H.T)) > 0) & jnp.all(jnp.isfinite(dx))
            G._newton_step_3 = before
        centre = np.array([0.4, -0.2, 0.6])
        obs = make_obstacles(spheres=[(np.eye(3), centre, (0.1,))], capacities=(2, 1, 1))
        u = rng.normal(size=(B, 3))
        goals = centre + (0.2 + 0.1 * rng.uniform(size=(B, 1))) * u / np.linalg.norm(u, axis=1, keepdims=True)
        args = (jnp.asarray(goals),)
        f = jax.jit(jax.vmap(lambda g: G.goal_field_minimum(g, obs)[1]))
    jax.block_until_ready(f(*args))  # compile
    t0 = time.perf_counter()
    for _ in range(reps):
        out = jax.block_until_ready(f(*args))
    print("OK", (time.perf_counter() - t0) / reps)
""")


def run(what, B, reps, pinned, timeout):
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-c", CHILD, what, str(B), str(reps), "1" if pinned else "0"],
                           capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"hung (no result after {timeout:.0f} s)", None
    if p.returncode != 0 or not p.stdout.startswith("OK"):
        return f"error: {(p.stderr or p.stdout).strip().splitlines()[-1][:80]}", None
    per_call = float(p.stdout.split()[1])
    return f"ok ({time.perf_counter() - t0:.0f} s)", per_call


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=300,
                    help="calls per row of the cho_solve program (default 300; goal_field_minimum: 3)")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds per row before it counts as hung")
    ap.add_argument("--batches", default="200,700,2000,20000", help="batches of the cho_solve program")
    ap.add_argument("--gfm-batches", default="2000,20000", help="batches of goal_field_minimum")
    args = ap.parse_args(argv)
    print(f"cores this process may use: {len(os.sched_getaffinity(0))}; "
          f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}\n")
    cho = [int(b) for b in args.batches.split(",")]
    gfm = [int(b) for b in args.gfm_batches.split(",")]
    # each program again, pinned, at its largest batch
    rows = [("cho", B, False) for B in cho] + [("cho", max(cho), True)]
    rows += [(w, B, False) for B in gfm for w in ("gfm_before", "gfm_now")] + [("gfm_before", max(gfm), True)]
    names = {"cho": "4 x cho_solve (9x9)", "gfm_before": "goal_field_minimum, before",
             "gfm_now": "goal_field_minimum, now"}
    print("| program | batch | pinned | outcome | per call [ms] | per member [us] |")
    print("|---|---:|---|---|---:|---:|")
    hung = 0
    for what, B, pinned in rows:
        reps = args.reps if what == "cho" else 3
        outcome, t = run(what, B, reps, pinned, args.timeout)
        per = "" if t is None else f"{1e3 * t:.2f}"
        per_m = "" if t is None else f"{1e6 * t / B:.2f}"
        print(f"| {names[what]} | {B} | {'yes' if pinned else 'no'} | {outcome} | {per} | {per_m} |", flush=True)
        hung += outcome.startswith("hung")
    print(f"\nrows that hung: {hung} of {len(rows)}")


if __name__ == "__main__":
    main()
