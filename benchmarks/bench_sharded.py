"""A simulation batch split over several devices: each device stepping its own members
(``shard_map``, what ``simulate_batch`` does with a batch sharded over a mesh) against ``jit``'s
automatic partitioning of the same program, and against the whole batch on one device.

Under automatic partitioning the batch's one ``while_loop`` asks every device at every iteration
whether any member still steps (a collective per step), and every device iterates as long as the
slowest member of the whole batch; with ``shard_map`` each device runs a loop of its own over its
rows. The study's path is timed: :func:`redman_jax._pipeline.run_controller` on a built case (the
batch padded to a multiple of the devices and sharded over a 1-D mesh), its ``sim_s`` (the
``simulate_batch`` call alone), warm, the variants alternating, best of ``--repeats``.

Run: ``python benchmarks/bench_sharded.py [--devices 2] [--dof 7] [--case simple] [--seeds 20]
[--controllers joint_space,velocity,gradient] [--repeats 3]`` (``JAX_PLATFORMS=cpu``; on a CPU
the host is split into ``--devices`` XLA devices, ``--xla_force_host_platform_device_count``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

VARIANTS = ("one device", "jit partitioning", "shard_map")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=2, help="CPU: XLA devices to split the host into")
    ap.add_argument("--dof", type=int, default=7, choices=(7, 8, 9))
    ap.add_argument("--case", default="simple")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--controllers", default="joint_space,velocity,gradient")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if args.devices < 2:
        raise SystemExit(f"--devices: expected at least 2, got {args.devices}")
    if args.seeds < 1 or args.repeats < 1:
        raise SystemExit("--seeds, --repeats: expected positive counts")
    from _xla_start import start_with_host_devices

    start_with_host_devices(args.devices)
    import jax

    import redman_jax._pipeline as pipe
    import redman_jax._sim as sim
    from redman_jax._report import _cpu_model
    from redman_jax._robot import thesis_arm

    print(f"jax {jax.__version__}, backend {jax.default_backend()}, {len(jax.devices())} devices, "
          f"{_cpu_model()}")
    arm = thesis_arm(args.dof)
    seeds = list(range(1, args.seeds + 1))
    t0 = time.perf_counter()
    payload = pipe.build_case(arm, args.case, seeds)
    print(f"{args.dof}-DOF {args.case}, {len(seeds)} seeds: scenarios built in "
          f"{time.perf_counter() - t0:.1f} s")
    shapes = pipe.study_shapes([args.case])[args.case]
    real_mesh, real_shard = sim._batch_mesh, pipe.shard_batch

    def run(variant, ctrl):
        sim._batch_mesh = (lambda s: None) if variant == "jit partitioning" else real_mesh
        pipe.shard_batch = (lambda tree: tree) if variant == "one device" else real_shard
        try:
            out = pipe.run_controller(arm, payload, ctrl, shapes=shapes, timing_repeats=1)
        finally:
            sim._batch_mesh, pipe.shard_batch = real_mesh, real_shard
        return out["timings"]["sim_s"], out["rows"]

    print(f"\n{'controller':<14}{'variant':<18}{'cold s':>9}{'warm s':>9}{'vs one device':>15}"
          f"{'max rel. dev.':>15}{'steps equal':>13}")
    for ctrl in [c.strip() for c in args.controllers.split(",") if c.strip()]:
        cold, warm, rows = {}, {v: [] for v in VARIANTS}, {}
        for v in VARIANTS:
            cold[v], rows[v] = run(v, ctrl)
        for _ in range(args.repeats):
            for v in VARIANTS:
                warm[v].append(run(v, ctrl)[0])
        base = rows["one device"]
        for v in VARIANTS:
            dev = max(abs(a["final_pos_error"] - b["final_pos_error"])
                      / max(abs(b["final_pos_error"]), 1e-300) for a, b in zip(rows[v], base))
            steps = all(a["n_steps"] == b["n_steps"] for a, b in zip(rows[v], base))
            w = min(warm[v])
            print(f"{ctrl:<14}{v:<18}{cold[v]:9.2f}{w:9.3f}{min(warm['one device']) / w:14.2f}x"
                  f"{dev:15.1e}{str(steps):>13}")
    print("\n(warm: best of the repeats; 'vs one device': the one-device batch's warm time over the "
          "variant's; deviation: final position error against the one-device batch)")


if __name__ == "__main__":
    main()
