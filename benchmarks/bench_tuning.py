"""Time to tune all Figure 3.6 controllers of one arm to the joint-space settling time.

Reports, per controller: optimiser iterations, compile time (the first iteration's excess over the
median of the others: tracing + XLA compilation of value_and_grad through the simulator), run time
of the iterations (wall, after compilation), per-iteration time, and the settling times before and
after. The target (joint space, K_p 1000, K_d 100) is timed separately (one forward compile + run).

    .venv/bin/python benchmarks/bench_tuning.py --arm 9 --steps 40
    .venv/bin/python benchmarks/bench_tuning.py --arm 7 --controllers acceleration --steps 10
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import numpy as np

import redman_jax  # noqa: F401  (x64)
from redman_jax._controllers import make_controller
from redman_jax._robot import thesis_arm
from redman_jax._tuning import experiment_settling_time, step_experiment, target_settling_time, tune_gains


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arm", type=int, default=9)
    ap.add_argument("--controllers", default="velocity,acceleration")
    ap.add_argument("--steps", type=int, default=40)
    args = ap.parse_args(argv)
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} cpus, "
          f"python {platform.python_version()}, x64={jax.config.jax_enable_x64}")
    arm = thesis_arm(args.arm)
    exp = step_experiment(arm)
    t0 = time.perf_counter()
    target = target_settling_time(arm, exp)
    t_target = time.perf_counter() - t0
    print(f"target (joint space 1000/100): {target:.4f} s  [first call incl. compile {t_target:.1f} s]")
    total = t_target
    print(f"{'controller':<14}{'iters':>6}{'compile s':>11}{'run s':>9}{'s/iter':>8}{'T before':>10}"
          f"{'T after':>9}{'rel err':>9}  gains")
    for name in args.controllers.split(","):
        ctrl = make_controller(name)
        Tb, _, _ = experiment_settling_time(arm, ctrl, ctrl.default_gains(), exp)
        t0 = time.perf_counter()
        r = tune_gains(arm, name, target, steps=args.steps, experiment=exp)
        el = time.perf_counter() - t0
        total += el
        gs = ", ".join(f"{f}={float(getattr(r.gains, f)):.4g}" for f in r.fields)
        print(f"{name:<14}{r.iterations:>6d}{r.compile_time:>11.1f}{r.wall_time - r.compile_time:>9.1f}"
              f"{float(np.median(r.history['iteration_time'][1:] if r.iterations > 1 else r.history['iteration_time'])):>8.2f}"
              f"{Tb:>10.4f}"
              f"{float(r.settling_time):>9.4f}{abs(float(r.settling_time) - target) / target:>9.3f}  {gs}")
    print(f"total wall time (target + all tunings, incl. compilation): {total:.1f} s")


if __name__ == "__main__":
    main()
