"""Figure 3.7: the "perfect controller" gradient descent (eq. 3.18) with the local-minima estimator
in a simple-obstacle scene (thesis 3.4; SPEC section 9).

Black: the path of the point; red: the obstacle spheres; cyan: the virtual obstacles active at the
moment the path passes the trap (the 20-slot buffer); grey: every other (earlier) estimate.

Run: ``.venv/bin/python examples/perfect_controller.py [--seed 2] [--out figure_3_7.png]``
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import redman_jax  # noqa: E402,F401
from redman_jax._guidance import PerfectParams, perfect_controller  # noqa: E402
from redman_jax._cases import make_scenario  # noqa: E402
from redman_jax._robot import thesis_arm  # noqa: E402


def simple_scene(seed, dof=9):
    """The simple-obstacle scene of ``seed`` from the case generator (SPEC section 4, U18): the
    obstacle set, start and goal positions, and the four sphere centres."""
    sc = make_scenario("simple", seed, thesis_arm(dof))
    sph = sc.obstacles.spheres
    centres = [np.asarray(c) for c, m in zip(sph.p, sph.mask) if bool(m)]
    return sc.obstacles, np.asarray(sc.reference.p[0]), np.asarray(sc.goal_p), centres


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--out", default="figure_3_7.png")
    args = ap.parse_args()
    obs, xs, xg, centres = simple_scene(args.seed)
    res = perfect_controller(xs, xg, obs, PerfectParams())
    n = int(res.termination.n_samples)
    x = np.asarray(res.x)[:n]
    est = np.asarray(res.estimates)[:n]
    ok = np.asarray(res.estimate_valid)[:n]
    # the moment of closest approach to the trap: show the buffer active then
    mid = np.mean(centres[:3], axis=0)  # the generator places the triangle first
    k = int(np.argmin(np.linalg.norm(x - mid, axis=1)))
    active = np.asarray(res.buffers)[k][np.asarray(res.buffer_masks)[k]]
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    u, v = np.mgrid[0:2 * np.pi:16j, 0:np.pi:8j]
    for c in centres:
        ax.plot_surface(c[0] + 0.07 * np.cos(u) * np.sin(v), c[1] + 0.07 * np.sin(u) * np.sin(v),
                        c[2] + 0.07 * np.cos(v), color="red", alpha=0.5, linewidth=0)
    ax.scatter(*est[ok].T, s=4, color="grey", label="previous estimates")
    ax.scatter(*active.T, s=12, color="cyan", label=f"active buffer (sample {k})")
    ax.plot(*np.vstack([xs, x]).T, color="black", label="path")
    ax.scatter(*xs, color="green", label="start")
    ax.scatter(*xg, color="blue", marker="*", s=80, label="goal")
    ax.set_xlabel("x [m]"), ax.set_ylabel("y [m]"), ax.set_zlabel("z [m]")
    ax.set_title(f"Perfect controller, simple obstacle seed {args.seed}: "
                 f"{'reached' if bool(res.success) else 'not reached'} in {n} samples")
    ax.legend(loc="upper left", fontsize=8)
    fig.savefig(args.out, dpi=120, bbox_inches="tight")
    print(f"wrote {args.out}: success {bool(res.success)}, samples {n}, path {float(res.path_length):.2f} m, "
          f"{int(ok.sum())} valid estimates")


if __name__ == "__main__":
    main()
