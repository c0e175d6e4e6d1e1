"""Figures of the scenes and the guidance field (thesis Figures 3.2 A-E and 3.4).

* :func:`plot_scenario`: one scene in 3D: obstacles (boxes as shaded faces, cylinders and spheres as
  surfaces, each with its pose), the reference path (grey where orientation control is off,
  coloured where it is on), start and goal with the goal's tool axis, and the arm's links and
  points of interest at a configuration ``q`` (default ``arm.q0``), as Figure 3.2.
* :func:`plot_field_slice`: a planar slice of the total guidance potential (3.22) with the goal and
  the obstacle outlines, as Figure 3.4.

Matplotlib's Agg backend is used; no window is ever shown.
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from ._scenario import Scenario  # noqa: E402

__all__ = ["plot_scenario", "plot_field_slice", "CASE_TITLES"]

CASE_TITLES = {
    "agriculture": "A: agriculture",
    "warehouse": "B: warehouse",
    "inspection": "C: inspection",
    "welding": "D: welding",
    "simple": "E: simple obstacle",
}

_COLORS = {"sphere": "#c0504d", "box": "#8eaccd", "cylinder": "#6b8e4e", "path_off": "0.45",
           "path_on": "#d9822b", "arm": "0.15", "poi": "#1f5fa8", "goal": "#c0392b",
           "start": "#2e7d32"}
_CASE_BOX_COLORS = {"warehouse": "#c9a46b", "inspection": "#9aa7b5", "welding": "#8c8c8c"}
_CASE_CYL_COLORS = {"agriculture": "#7a5a3a", "inspection": "#b5651d", "welding": "#b0b7bf"}


def _single(scenario: Scenario) -> Scenario:
    if not isinstance(scenario, Scenario):
        raise ValueError(f"scenario: expected a Scenario, got {type(scenario).__name__}")
    if np.ndim(scenario.goal_p) != 1:
        raise ValueError("scenario: expected one scenario; index a stacked batch first, "
                         "e.g. jax.tree.map(lambda x: x[0], batch)")
    return scenario


def _np(x):
    return np.asarray(x, dtype=float)


def _box_faces(R, p, b):
    s = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    v = (s * b) @ R.T + p
    idx = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]
    return [v[i] for i in idx]


def _cylinder_mesh(R, p, r, h, n=24):
    th = np.linspace(0, 2 * math.pi, n)
    z = np.array([-h, h])
    T, Z = np.meshgrid(th, z)
    local = np.stack([r * np.cos(T), r * np.sin(T), Z], -1)
    w = local @ R.T + p
    return w[..., 0], w[..., 1], w[..., 2]


def _sphere_mesh(p, r, n=18):
    u = np.linspace(0, 2 * math.pi, n)
    v = np.linspace(0, math.pi, n // 2 + 1)
    x = p[0] + r * np.outer(np.cos(u), np.sin(v))
    y = p[1] + r * np.outer(np.sin(u), np.sin(v))
    z = p[2] + r * np.outer(np.ones_like(u), np.cos(v))
    return x, y, z


def _draw_obstacles(ax, obs, case):
    pts = []
    faces = []
    for R, p, d, m in zip(_np(obs.boxes.R), _np(obs.boxes.p), _np(obs.boxes.dims), np.asarray(obs.boxes.mask)):
        if m:
            f = _box_faces(R, p, d)
            faces += f
            pts.append(np.concatenate(f))
    if faces:
        col = Poly3DCollection(faces, facecolor=_CASE_BOX_COLORS.get(case, _COLORS["box"]),
                               edgecolor="0.35", linewidths=0.25, alpha=0.22, zorder=1)
        ax.add_collection3d(col)
    for R, p, d, m in zip(_np(obs.cylinders.R), _np(obs.cylinders.p), _np(obs.cylinders.dims),
                          np.asarray(obs.cylinders.mask)):
        if m:
            X, Y, Z = _cylinder_mesh(R, p, d[0], d[1])
            ax.plot_surface(X, Y, Z, color=_CASE_CYL_COLORS.get(case, _COLORS["cylinder"]),
                            alpha=0.85, linewidth=0, shade=True, zorder=2)
            pts.append(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1))
    for p, d, m in zip(_np(obs.spheres.p), _np(obs.spheres.dims), np.asarray(obs.spheres.mask)):
        if m:
            X, Y, Z = _sphere_mesh(p, d[0])
            ax.plot_surface(X, Y, Z, color=_COLORS["sphere"], alpha=0.85, linewidth=0, shade=True, zorder=2)
            pts.append(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1))
    return pts


def _draw_arm(ax, arm, q):
    from ._kinematics import kinematics, poi_positions_from

    q = jnp.asarray(arm.q0 if q is None else q)
    if q.shape != (arm.n_dof,):
        raise ValueError(f"q: expected shape ({arm.n_dof},), got {q.shape}")
    kin = kinematics(arm, q)
    pois = _np(poi_positions_from(arm, kin, q))
    base = np.zeros((1, 3))
    chain = np.concatenate([base, pois])  # POIs lie on the segment axes, the last is the EE
    ax.plot(chain[:, 0], chain[:, 1], chain[:, 2], color=_COLORS["arm"], lw=3.2, solid_capstyle="round",
            zorder=5)
    joints = _np(kin.frames[:, :3, 3])
    ax.scatter(joints[:, 0], joints[:, 1], joints[:, 2], s=16, color="0.05", depthshade=False, zorder=6)
    ax.scatter(pois[:, 0], pois[:, 1], pois[:, 2], s=5, color=_COLORS["poi"], depthshade=False, zorder=7)
    return [chain]


def plot_scenario(scenario: Scenario, arm=None, q=None, ax=None, *, title: str | None = None,
                  elev: float = 28.0, azim: float | None = None):
    """Draw one scenario in 3D (thesis Figure 3.2).

    Arguments:
        scenario: a single (unstacked) :class:`~redman_jax.Scenario`.
        arm: optional :class:`~redman_jax.Arm`; drawn at ``q`` (default ``arm.q0``) as its link
            chain with joints (black) and points of interest (blue).
        ax: a 3D axes to draw into (default: a new figure).
        title: default the case letter and name; elev/azim: view angles (azim default: looking
            at the goal from behind the robot).

    Returns:
        the axes. Raises ``ValueError`` for a stacked scenario or a wrongly shaped ``q``.
    """
    sc = _single(scenario)
    if ax is None:
        fig = plt.figure(figsize=(5.2, 4.8))
        ax = fig.add_subplot(111, projection="3d")
    ax.computed_zorder = False  # draw path and arm over the translucent obstacles
    ref = sc.reference
    n = int(ref.n_samples)
    p = _np(ref.p)[:n]
    rot = _np(ref.rot)[:n] > 0
    pts = _draw_obstacles(ax, sc.obstacles, sc.case)
    off = ~rot
    if off.any():
        k = np.nonzero(off)[0][-1] + 1
        seg = p[: min(k + 1, n)]
        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color=_COLORS["path_off"], lw=1.6, ls="--", zorder=8,
                label="reference (orientation off)")
    if rot.any():
        seg = p[rot]
        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color=_COLORS["path_on"], lw=2.0, zorder=8,
                label="reference (orientation on)")
    pts.append(p)
    ax.scatter(*p[0], s=30, color=_COLORS["start"], depthshade=False, zorder=9, label="start")
    g = _np(sc.goal_p)
    ax.scatter(*g, s=55, color=_COLORS["goal"], marker="*", depthshade=False, zorder=9, label="goal")
    from ._trajectories import rot_from_quat

    a = rot_from_quat(_np(sc.goal_quat))[:, 2]
    ax.quiver(*(g - 0.15 * a), *(0.15 * a), color=_COLORS["goal"], lw=1.4, arrow_length_ratio=0.3, zorder=9)
    if arm is not None:
        pts += _draw_arm(ax, arm, q)
    allp = np.concatenate([x.reshape(-1, 3) for x in pts] + [np.zeros((1, 3))])
    lo, hi = allp.min(0), allp.max(0)
    lo[2] = min(lo[2], 0.0)
    half = 0.5 * max(float(np.max(hi - lo)), 1e-3)  # equal scales: a cube around the scene
    mid = 0.5 * (lo + hi)
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(lo[2], lo[2] + 2 * half)
    ax.set_box_aspect((1, 1, 1))
    if azim is None:
        azim = math.degrees(math.atan2(g[1], g[0])) - 125.0
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x [m]", labelpad=-2)
    ax.set_ylabel("y [m]", labelpad=-2)
    ax.set_zlabel("z [m]", labelpad=-2)
    ax.tick_params(labelsize=7, pad=0)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.pane.set_alpha(0.0)
    ax.set_title(CASE_TITLES.get(sc.case, sc.case) if title is None else title, fontsize=10)
    return ax


def _obstacle_slice_outline(obs, X, Y, Z):
    """Signed distance of every grid point to the nearest obstacle (for the outlines)."""
    from ._obstacles import min_distance

    pts = jnp.asarray(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1))
    d = jax.jit(jax.vmap(min_distance, in_axes=(None, 0)))(obs, pts)
    return np.asarray(d).reshape(X.shape)


def plot_field_slice(scenario: Scenario, params=None, *, normal: str = "z", level: float | None = None,
                     extent: float = 0.8, resolution: int = 120, center=None, virtual_p=None,
                     virtual_mask=None, ax=None, vmax_decades: float = 3.0, title: str | None = None):
    """A planar slice of the total guidance potential ``V = V_g + sum V_o + sum V_v`` (3.22,
    Figure 3.4), through the goal by default.

    Arguments:
        scenario: a single :class:`~redman_jax.Scenario`; params: ``FieldParams`` (default).
        normal: "x", "y" or "z", the slice normal; level: its coordinate (default the goal's).
        extent: half-width of the square window [m] around ``center`` (default the goal).
        resolution: grid points per side. virtual_p (B, 3) / virtual_mask (B,): virtual obstacles
            (default none).
        vmax_decades: colour range, in decades above the potential's minimum on the slice.

    Returns the axes. The colour is ``log10(V - min V + 1e-4)``; obstacle cross-sections are
    outlined in black and the goal is the red circle.
    """
    from ._fields import FieldParams, total_potential

    sc = _single(scenario)
    if normal not in ("x", "y", "z"):
        raise ValueError(f"normal: expected 'x', 'y' or 'z', got {normal!r}")
    if not (isinstance(resolution, int) and resolution >= 8):
        raise ValueError(f"resolution: expected an int >= 8, got {resolution!r}")
    params = FieldParams() if params is None else params
    g = _np(sc.goal_p)
    c = g.copy() if center is None else _np(center)
    k = "xyz".index(normal)
    ia, ib = [i for i in range(3) if i != k]
    if level is None:
        level = g[k]
    u = np.linspace(c[ia] - extent, c[ia] + extent, resolution)
    w = np.linspace(c[ib] - extent, c[ib] + extent, resolution)
    U, W = np.meshgrid(u, w)
    grid = np.zeros(U.shape + (3,))
    grid[..., ia], grid[..., ib], grid[..., k] = U, W, level
    if virtual_p is None:
        virtual_p = jnp.zeros((1, 3))
        virtual_mask = jnp.zeros((1,), bool)
    pts = jnp.asarray(grid.reshape(-1, 3))
    V = jax.jit(jax.vmap(total_potential, in_axes=(0, None, None, None, None, None)))(
        pts, jnp.asarray(g), sc.obstacles, jnp.asarray(virtual_p), jnp.asarray(virtual_mask), params)
    V = np.asarray(V).reshape(U.shape)
    logV = np.log10(V - np.nanmin(V) + 1e-4)
    lo = np.nanmin(logV)
    if ax is None:
        fig, ax = plt.subplots(figsize=(4.8, 4.0))
    im = ax.contourf(U, W, np.clip(logV, lo, lo + vmax_decades + 4), levels=40, cmap="viridis")
    ax.contour(U, W, np.clip(logV, lo, lo + vmax_decades + 4), levels=14, colors="w", linewidths=0.3,
               alpha=0.5)
    d = _obstacle_slice_outline(sc.obstacles, grid[..., 0], grid[..., 1], grid[..., 2])
    if np.nanmin(d) < 0 < np.nanmax(d):
        ax.contourf(U, W, d, levels=[-1e9, 0.0], colors=["0.2"], alpha=0.85)
        ax.contour(U, W, d, levels=[0.0], colors="k", linewidths=0.8)
    ax.add_patch(plt.Circle((g[ia], g[ib]), 0.03, fill=False, color=_COLORS["goal"], lw=1.8))
    ax.set_aspect("equal")
    ax.set_xlabel(f"{'xyz'[ia]} [m]")
    ax.set_ylabel(f"{'xyz'[ib]} [m]")
    cb = ax.figure.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label(r"$\log_{10}(V - V_{\min} + 10^{-4})$", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    name = CASE_TITLES.get(sc.case, sc.case).split(": ")[-1]
    ax.set_title(title if title is not None else f"Potential field, {name} ({normal} = {level:.2f} m)",
                 fontsize=10)
    return ax
