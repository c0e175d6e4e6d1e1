"""``redman-jax demo``: one scenario end to end, plotted and animated.

Generates and IK-validates one scenario, simulates one controller on it, and writes

* ``scene.png``: the scene with the reference (and, for the run, the end-effector path) and the
  arm at its final configuration;
* ``errors.png``: position and orientation error per sample, with the orientation switch;
* ``animation.gif`` (unless ``--no-animation``): the arm moving through the scene;
* ``summary.json``: the run's metrics (strict JSON: a value that is not a finite number, such as
  the IK time of a controller that uses none, is ``null``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ._store import json_ready

__all__ = ["run_demo", "demo_cli"]


def run_demo(arm_spec: str = "9", case: str = "simple", seed: int = 1, controller: str = "velocity",
             out: str | Path = "demo", animation: bool = True, max_retries: int = 20) -> dict:
    """Run one scenario end to end and write its figures to ``out``; returns the summary dict."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ._controllers import CONTROLLERS
    from ._pipeline import build_case, run_controller
    from ._plots import plot_scenario
    from ._scenario import CASES
    from ._study import arm_from_spec

    if case not in CASES:
        raise ValueError(f"--case: unknown case {case!r}; choose from {list(CASES)}")
    if controller not in CONTROLLERS:
        raise ValueError(f"--controller: unknown controller {controller!r}; choose from {sorted(CONTROLLERS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    arm = arm_from_spec(arm_spec, option="--arm")
    built = build_case(arm, case, [seed], max_retries=max_retries)
    run = run_controller(arm, built, controller, timing_repeats=2)
    row, tr = run["rows"][0], run["traces"]
    import jax

    scen = jax.tree.map(lambda x: np.asarray(x)[0], built["scenarios"])
    n = int(row["n_samples"])
    summary = json_ready(dict(row))  # first: a figure that fails leaves the run's numbers
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str, allow_nan=False))

    # a run that diverged is drawn up to its last finite sample (its state is inf after it)
    q_traj = _joint_path(arm, built, controller)
    finite = np.all(np.isfinite(q_traj[:n]), axis=1) & np.all(np.isfinite(tr["p"][0][:n]), axis=1)
    m = int(np.argmin(finite)) if not finite.all() else n
    ax = plot_scenario(scen, arm=arm, q=q_traj[m - 1] if m > 0 else np.asarray(arm.q0))
    p = tr["p"][0][:m]
    label = f"{controller} (actual)" + ("" if m == n else f", diverged after {m} samples")
    ax.plot(p[:, 0], p[:, 1], p[:, 2], color="crimson", lw=1.6, label=label)
    ax.legend(loc="upper left", fontsize=7)
    ax.figure.savefig(out / "scene.png", dpi=130, bbox_inches="tight")
    plt.close(ax.figure)

    fig, axs = plt.subplots(2, 1, figsize=(6.4, 4.6), sharex=True)
    t = np.arange(1, n + 1) * float(np.asarray(scen.reference.ts))
    shown = lambda x: np.where(np.isfinite(x), x, np.nan)  # noqa: E731 -- inf after a divergence
    axs[0].plot(t, 1e3 * shown(tr["pos_err"][0][:n]), color="C0")
    axs[0].set_ylabel("|e_p| [mm]")
    rot = tr["rot"][0][:n] > 0.5
    ori = np.where(rot, shown(tr["ori_err"][0][:n]), np.nan)
    axs[1].plot(t, ori, color="C1")
    axs[1].set_ylabel("|e_o| (rot on)")
    axs[1].set_xlabel("t [s]")
    for a in axs:
        a.grid(alpha=0.3)
        if rot.any():
            a.axvline(t[np.argmax(rot)], color="k", ls=":", lw=0.8)
    fig.suptitle(f"{case}, seed {row['seed_used']}, {arm.name}, {controller}: "
                 f"{'success' if row['success'] else 'failure'}")
    fig.tight_layout()
    fig.savefig(out / "errors.png", dpi=130)
    plt.close(fig)

    if animation and m > 0:
        _animate(arm, scen, q_traj[:m], out / "animation.gif")
    return summary


def _joint_path(arm, built, controller_name):
    """Re-simulate the run to get its joint path (the traces keep task-space data only)."""
    import jax
    import jax.numpy as jnp

    from ._controllers import CONTROLLERS
    from ._sim import simulate

    ctrl = CONTROLLERS[controller_name]()
    scen = jax.tree.map(lambda x: jnp.asarray(x)[0], built["scenarios"])
    ik = jax.tree.map(lambda x: jnp.asarray(x)[0], built["ik"])
    res = simulate(arm, scen, ctrl, ctrl.default_gains(), ik=ik if ctrl.needs_joint_reference else None)
    return np.asarray(res.q)


def _animate(arm, scen, q_traj, path: Path, frames: int = 40) -> None:
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    from ._plots import plot_scenario

    idx = np.linspace(0, len(q_traj) - 1, min(frames, len(q_traj))).astype(int)
    fig = plt.figure(figsize=(4.8, 4.4))
    ax = fig.add_subplot(111, projection="3d")

    def draw(i):
        ax.cla()
        plot_scenario(scen, arm=arm, q=q_traj[idx[i]], ax=ax, title=f"t = {idx[i] * float(scen.reference.ts):.2f} s")

    anim = FuncAnimation(fig, draw, frames=len(idx))
    anim.save(path, writer=PillowWriter(fps=10))
    plt.close(fig)


def demo_cli(args) -> None:
    summary = run_demo(args.arm, args.case, args.seed, args.controller, args.out,
                       animation=not args.no_animation)
    print(json.dumps(summary, indent=2, default=str, allow_nan=False))
    print(f"figures written to {args.out}/")
