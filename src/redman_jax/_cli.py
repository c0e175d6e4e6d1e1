"""Command line: ``redman-jax {study,sweep,plot,tune,demo}`` (also ``python -m redman_jax``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main", "build_parser", "parse_int_list", "parse_name_list"]

DEFAULT_CONTROLLERS = ("joint_space", "velocity", "acceleration", "gradient")


class CLIError(ValueError):
    pass


_MAX_RANGE = 1_000_000


def parse_int_list(text: str, name: str) -> tuple[int, ...]:
    """Parse ``"1-20"``, ``"1,3,5"`` or ``"1-5,9"`` into a tuple of ints (``name`` for messages)."""
    out: list[int] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            if "-" in part[1:]:
                a, b = part.split("-", 1) if not part.startswith("-") else (part, None)
                a, b = int(a), int(b)
                if b < a:
                    raise CLIError(f"--{name}: empty range {part!r}")
                if b - a >= _MAX_RANGE:  # a typo such as 1-20000000000 would fill the memory
                    raise CLIError(f"--{name}: range {part!r} holds more than {_MAX_RANGE:,} values")
                out.extend(range(a, b + 1))
            else:
                out.append(int(part))
    except ValueError as e:
        if isinstance(e, CLIError):
            raise
        raise CLIError(f"--{name}: cannot parse {text!r} (expected e.g. 1-20 or 1,3,5)") from None
    if not out:
        raise CLIError(f"--{name}: no values in {text!r}")
    return tuple(dict.fromkeys(out))


def parse_name_list(text: str, name: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
    items = tuple(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
    bad = [s for s in items if s not in allowed]
    if bad:
        raise CLIError(f"--{name}: unknown value(s) {bad}; choose from {list(allowed)}")
    if not items:
        raise CLIError(f"--{name}: empty")
    return items


def _add_sweep_options(p: argparse.ArgumentParser, *, study: bool) -> None:
    p.add_argument("--out", default="results", help="output folder (resumable; default: results)")
    if not study:
        p.add_argument("--arms", default="7,8,9",
                       help="thesis arms by DOF (7,8,9) and/or URDF arms as urdf:PATH:TIP_LINK (default 7,8,9)")
        p.add_argument("--cases", default="agriculture,warehouse,inspection,welding,simple",
                       help="cases to run (default: all five)")
        p.add_argument("--seeds", default="1-20", help="seeds, e.g. 1-20 or 1,4,7 (default 1-20)")
        p.add_argument("--controllers", default=",".join(DEFAULT_CONTROLLERS),
                       help="controllers: joint_space, velocity, acceleration, gradient, and the optional "
                            "pid, velocity_original, impedance (default: the four of the thesis)")
        p.add_argument("--gains", default=None,
                       help="JSON file of gain overrides {controller: {gain: value}} (e.g. from `tune`)")
        p.add_argument("--ts", type=float, default=0.01, help="sample time in seconds (default 0.01)")
        p.add_argument("--solver", default="auto",
                       help="ODE solver of the simulations: auto, tsit5, dopri5, dopri8 or bosh3 (default "
                            "auto: tsit5 for the acceleration OSC and gradient-guided, dopri5 for the others; "
                            "rtol 1e-5, atol 1e-7 either way; 1e-4, 1e-5 in float32, REDMAN_JAX_X64=0)")
    p.add_argument("--max-retries", type=int, default=20,
                   help="IK-validation retries per seed (seed + 1000 k; default 20)")
    p.add_argument("--jobs", default="auto",
                   help="worker processes for the groups of units: scenario builds per (arm, case), "
                        "simulations per (arm, controller) (default auto: 2 on a CPU machine "
                        "with 2 or more cores, 1 with an accelerator); each worker on one core, and "
                        "--jobs 1 computes in this process on one core, so the table is the same "
                        "for any count")
    p.add_argument("--no-figures", action="store_true", help="skip figures and report")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--distributed", action="store_true",
                   help="join a multi-process run (jax.distributed): start this same command once per "
                        "node (it uses all of the node's devices); every simulation's batch is sharded over the devices of all "
                        "processes and process 0 writes --out. The processes are found from the "
                        "cluster's environment (SLURM, Open MPI, ...) unless --coordinator, "
                        "--num-processes and --process-id say")
    p.add_argument("--coordinator", default=None,
                   help="with --distributed: HOST:PORT of process 0 (default $JAX_COORDINATOR_ADDRESS, "
                        "or detected)")
    p.add_argument("--num-processes", default=None,
                   help="with --distributed: how many processes (default $JAX_NUM_PROCESSES, or detected)")
    p.add_argument("--process-id", default=None,
                   help="with --distributed: this process's index, 0 to N-1 (default $JAX_PROCESS_ID, "
                        "or detected)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="redman-jax",
        description="Joint-space vs operational-space control of redundant arms among obstacles "
                    "(a JAX reproduction of the thesis study). Without a subcommand: `study`.",
    )
    sub = parser.add_subparsers(dest="command")
    p = sub.add_parser("study", help="the whole thesis study: 3 arms x 5 cases x 20 seeds, all controllers")
    _add_sweep_options(p, study=True)
    p.add_argument("--seeds", default="1-20", help="seeds (default 1-20; fewer for a quick look)")
    p = sub.add_parser("sweep", help="any subset of the study (arms, cases, seeds, controllers, gains, ts)")
    _add_sweep_options(p, study=False)
    p = sub.add_parser("plot", help="figures and report.md from an existing results folder")
    p.add_argument("--out", default="results", help="results folder (default: results)")
    p = sub.add_parser("tune", help="auto-tune controller gains to equal settling time")
    p.add_argument("--arm", default="9", help="thesis arm DOF (default 9)")
    p.add_argument("--controllers", default="velocity,acceleration",
                   help="controllers to tune (default velocity,acceleration; the target is joint_space)")
    p.add_argument("--steps", type=int, default=60, help="optimiser steps (default 60)")
    p.add_argument("--out", default="tuned", help="output folder (default: tuned)")
    p = sub.add_parser("demo", help="one scenario end to end: plotted and animated")
    p.add_argument("--arm", default="9", help="thesis arm DOF (default 9)")
    p.add_argument("--case", default="simple", help="case (default simple)")
    p.add_argument("--seed", type=int, default=1, help="seed (default 1)")
    p.add_argument("--controller", default="velocity", help="controller (default velocity)")
    p.add_argument("--out", default="demo", help="output folder (default: demo)")
    p.add_argument("--no-animation", action="store_true", help="skip the GIF")
    return parser


def _join_distributed(args) -> None:
    """``--distributed``: join the multi-process run before any JAX work in this process."""
    given = [f"--{n.replace('_', '-')}" for n in ("coordinator", "num_processes", "process_id")
             if getattr(args, n) is not None]
    if not args.distributed:
        if given:
            raise CLIError(f"{', '.join(given)}: only with --distributed")
        return
    if str(args.jobs) not in ("auto", "1"):
        raise CLIError(f"--jobs: a --distributed sweep runs one process per node; got --jobs {args.jobs}")
    from ._distributed import initialize

    initialize(args.coordinator, args.num_processes, args.process_id)


def _seed_max() -> int:
    from ._study import SEED_MAX

    return SEED_MAX


def main(argv=None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or (argv[0].startswith("-") and argv[0] not in ("-h", "--help")):
        argv = ["study", *argv]  # no subcommand: the study, with any options given
    args = parser.parse_args(argv)
    command = args.command
    try:
        if command in ("study", "sweep"):
            from ._study import SweepConfig, prepare_sweep_process, run_sweep

            # before any JAX work, so that the table is the same for any --jobs: the workers' XLA
            # flags, and for --jobs 1 (units computed here) a worker's one core
            prepare_sweep_process(args.jobs, args.distributed)
            _join_distributed(args)
            cfg = SweepConfig.from_args(args, study=(command == "study"))
            run_sweep(cfg)
        elif command == "plot":
            from ._study import render_report

            render_report(args.out)
        elif command in ("tune", "demo") and Path(args.out).exists() and not Path(args.out).is_dir():
            raise CLIError(f"--out: {args.out!r} is a file, not a folder")
        elif command == "demo" and args.seed > _seed_max():
            raise CLIError(f"--seed: at most {_seed_max()} (a JAX PRNG key), got {args.seed}")
        elif command == "tune":
            from ._tuning import tune_cli

            tune_cli(args)
        elif command == "demo":
            from ._demo import demo_cli

            demo_cli(args)
    except CLIError as e:
        print(f"redman-jax {command}: error: {e}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"redman-jax {command}: error: {e}", file=sys.stderr)
        return 2
    return 0
