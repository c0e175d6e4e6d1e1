"""Closed-loop simulation speed (issue 6): redman-jax against a plain NumPy + SciPy version of the
*same* closed loop, for the study's controllers on the study's scenarios.

Run: ``.venv/bin/python benchmarks/bench_sim.py [--cases welding simple] [--controllers velocity]
[--seeds 20] [--scipy-seeds 1] [--scipy-samples 100] [--dof 9] [--threads N | --devices N]
[--xla-flags study]``

What is compared, per case and controller (scenarios and IK joint references from
``redman_jax._pipeline.build_case``, the study's seeds ``1..seeds``):

* **JAX**: ``simulate_batch`` over all seeds in one call, default ``SimParams()`` (Dopri5, rtol
  1e-5, atol 1e-7, one horizon solve with the sample boundaries as jump times) and default
  ``threads`` (one ``jit(vmap)`` program on a chunk of the seeds per core, all at once: two chunks
  of 10 on a 2-core machine; ``--threads 1``: one program over all seeds). ``--devices N``
  instead splits the CPU into ``N`` XLA devices and shards the batch over them, as the sweep does
  on several devices: one call, each device stepping its own seeds (``shard_map``). On 2 cores
  that is the faster layout (9-DOF simple and welding, joint space and velocity OSC, warm: 1.4-1.7x
  less time than two threads in two pairs of runs, in either order, the same steps; a program per
  device runs without the contention of two programs on one device). *Cold* is the first call
  (tracing + compilation + run), *warm* the second call.
  ``--xla-flags study`` starts JAX with the XLA flags the study's workers use
  (``redman_jax._study.WORKER_XLA_FLAGS``: XLA's older CPU loop emitters, no YNNPACK fusions, and
  every while loop XLA can hoist compiled as one function at LLVM level 1), as ``make run``
  simulates; the default is JAX's own flags.
* **NumPy + SciPy**: the closed loop re-implemented below in plain NumPy (nothing jitted, no JAX
  call inside the vector field): forward kinematics, Jacobians, ``J_dot q_dot``, mass matrix and
  Newton-Euler bias forces, joint-limit contact (3.6), points of interest and their Jacobians,
  obstacle signed distances and potential-field gradients, the null-space policies (3.33-3.36),
  the adaptive damped pseudo-inverse (3.29-3.32), the three tracking controllers
  ``joint_space``, ``velocity`` and ``acceleration`` and the gradient-guided one (guidance field
  with its virtual obstacles, 3.18-3.28) with their default (thesis) gains.
  Integrated with ``scipy.integrate.solve_ivp`` (DOP853, same rtol/atol) once per reference
  sample, one seed at a time, as the thesis called ``ode113`` per sample; every call picks its own
  first step. ``tests/test_numpy_baseline.py`` checks that this NumPy vector field equals the
  JAX one (``_sim._closed_loop``) to ~1e-9, so both sides integrate the same ODE.
  Only the first ``--scipy-samples`` samples of ``--scipy-seeds`` seeds are timed and the cost
  is extrapolated per simulated second (the output says so). The cost per sample is far from
  uniform along a run (warehouse, acceleration, seed 1: 4e3 to 2.1e4 evaluations per 25-sample
  window), so the extrapolation can be off by tens of percent either way.
* The collision and joint-limit flags of the NumPy loop are evaluated at every vector-field call
  (same work as JAX) but latched as booleans instead of integrated (they never enter the error
  norm, as in JAX).
* The gradient-guided controller (cases agriculture, warehouse, simple, as in the study): JAX runs
  one adaptive loop over its 6 s horizon with the local-minima estimator updating between steps
  at the sample ends (``_sim._solve_guided_stepper``); the NumPy side (:class:`NumpyGuidedLoop`)
  runs ``solve_ivp`` per sample as above, the estimator (3.24, its Hessian by central differences
  of the analytic field gradient) and the orientation latch at each sample start, and the stop
  rule at each sample end. Its first ``--scipy-samples`` samples are timed against the JAX
  batch's simulated seconds up to each member's stop.

Reported: simulated seconds per wall second (valid samples only, summed over seeds),
vector-field evaluations per simulated second (JAX: ``1 + 6 steps + (n - 1)`` per member for the
FSAL Dopri5 restarted after each of the run's ``n - 1`` jumps, ``n`` its valid samples; a counting
callback, ``--exact-evals``, finds about 1 % more; SciPy: counted), the share of the JAX loop's
iterations that step a member still running (``use``, :func:`batch_use`; a chunk of the batch
iterates until its slowest member is done, so a case whose runs differ in length, such as simple
with 640 to 1877 samples, wastes up to half of them; not given for gradient-guided runs, whose
stragglers move to a smaller batch), and the speed-up of JAX (20 seeds in one call) over SciPy (one
seed at a time) per simulated second.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import scipy
from scipy.integrate import solve_ivp

import redman_jax  # noqa: F401  (float64)
from redman_jax._control_types import AbstractController
from redman_jax._controllers import CONTROLLERS
from redman_jax._report import _cpu_model  # the CPU's model name, as the study report's machine row gives it
from redman_jax._robot import thesis_arm
from redman_jax._scenario import CASES
from redman_jax._sim import SimParams, joint_reference, simulate, simulate_batch, tolerances

NUMPY_CONTROLLERS = ("joint_space", "velocity", "acceleration")  # tracking; NP_CONTROLLERS adds gradient
GRADIENT_CASES = ("agriculture", "warehouse", "simple")  # the study runs "gradient" on these only
BIG_DISTANCE = 1e3


# ----------------------------------------------------------------------------------------------
# NumPy model of the arm


def _cross(a, b):
    """``a x b`` along the last axis (broadcasting); ``np.cross`` costs ~10x more on small arrays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _skew(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


class NumpyArm:
    """The arm's data as NumPy arrays and its kinematics and dynamics in plain NumPy."""

    def __init__(self, arm):
        g = lambda x: np.asarray(x, float)  # noqa: E731
        self.S0, self.home, self.ee_home = g(arm.screw_axes), g(arm.home_frames), g(arm.ee_home)
        self.m, self.com, self.I = g(arm.masses), g(arm.coms), g(arm.inertias)
        self.qmin, self.qmax, self.lim = g(arm.q_min), g(arm.q_max), np.asarray(arm.limited, bool)
        self.widths, self.seg, self.q0, self.grav = g(arm.widths), g(arm.seg_ends), g(arm.q0), g(arm.gravity)
        self.pri = np.asarray(arm.prismatic, bool)
        self.n, self.P = arm.n_dof, arm.points_per_link
        n, P = self.n, self.P
        self.upper = np.arange(n)[:, None] <= np.arange(n)[None, :]
        # points of interest: fractions along each segment, link index, Jacobian column scaling
        self.fracs = np.arange(1, P + 1) / P
        self.axis_local = np.einsum("nji,nj->ni", self.home[:, :3, :3], self.S0[:, 3:])
        link = np.repeat(np.arange(n), P)
        joints = np.arange(n)
        own = (joints[None, :] == link[:, None]) & self.pri[None, :]
        s = np.tile(self.fracs, n)
        self.poi_scale = np.where(own, s[:, None], 1.0) * (joints[None, :] <= link[:, None])  # (m, n)
        self.poi_width = self.widths[link]

    def fk(self, q):
        """Link frames ``(n, 4, 4)``, end-effector frame and spatial Jacobian columns ``(n, 6)``."""
        P = np.eye(4)
        frames, cols = [], []
        for i in range(self.n):
            S = self.S0[i]
            R, p = P[:3, :3], P[:3, 3]
            w = R @ S[:3]
            cols.append(np.concatenate([w, _cross(p, w) + R @ S[3:]]))
            E = np.eye(4)
            if self.pri[i]:
                E[:3, 3] = S[3:] * q[i]
            else:
                W = _skew(S[:3])
                W2 = W @ W
                s, c = np.sin(q[i]), np.cos(q[i])
                E[:3, :3] = np.eye(3) + s * W + (1 - c) * W2
                E[:3, 3] = (q[i] * np.eye(3) + (1 - c) * W + (q[i] - s) * W2) @ S[3:]
            P = P @ E
            frames.append(P @ self.home[i])
        return np.stack(frames), P @ self.ee_home, np.stack(cols)

    @staticmethod
    def jacobian(ee, S):
        """End-effector geometric Jacobian ``(6, n)``, rows ``[linear; angular]``."""
        p = ee[:3, 3]
        return np.vstack([(S[:, 3:] + _cross(S[:, :3], p)).T, S[:, :3].T])

    def body(self, frames):
        """World spatial inertias about the origin, compact: ``m``, ``h = m c``, ``I_o``."""
        R, p = frames[:, :3, :3], frames[:, :3, 3]
        c = np.einsum("nij,nj->ni", R, self.com) + p
        Iw = np.einsum("nij,njk,nlk->nil", R, self.I, R)
        Io = Iw + self.m[:, None, None] * (np.sum(c * c, 1)[:, None, None] * np.eye(3) - c[:, :, None] * c[:, None, :])
        return self.m, self.m[:, None] * c, Io

    def mass_matrix(self, S, body):
        """Composite-rigid-body mass matrix ``M_jk = S_j . (I^c_k S_k)``, ``j <= k``."""
        m, h, Io = body
        mc, hc, Ic = (np.cumsum(x[::-1], axis=0)[::-1] for x in (m, h, Io))
        Sw, Sv = S[:, :3], S[:, 3:]
        Fn = np.einsum("nij,nj->ni", Ic, Sw) + _cross(hc, Sv)
        Ff = mc[:, None] * Sv - _cross(hc, Sw)
        U = Sw @ Fn.T + Sv @ Ff.T
        return np.where(self.upper, U, U.T)

    def rnea(self, S, body, qd, qdd):
        """``M qdd + c + g`` by recursive Newton-Euler in world coordinates."""
        m, h, Io = body
        Sw, Sv = S[:, :3], S[:, 3:]
        V = np.cumsum(S * qd[:, None], axis=0)
        Vp = V - S * qd[:, None]
        wp, vp = Vp[:, :3], Vp[:, 3:]
        Sdot = np.hstack([_cross(wp, Sw), _cross(vp, Sw) + _cross(wp, Sv)])
        A = np.cumsum(S * qdd[:, None] + Sdot * qd[:, None], axis=0)
        A[:, 3:] -= self.grav
        w, v = V[:, :3], V[:, 3:]
        pn = np.einsum("nij,nj->ni", Io, w) + _cross(h, v)
        pf = m[:, None] * v - _cross(h, w)
        an = np.einsum("nij,nj->ni", Io, A[:, :3]) + _cross(h, A[:, 3:])
        af = m[:, None] * A[:, 3:] - _cross(h, A[:, :3])
        Fn = np.cumsum((an + _cross(w, pn) + _cross(v, pf))[::-1], axis=0)[::-1]
        Ff = np.cumsum((af + _cross(w, pf))[::-1], axis=0)[::-1]
        return np.sum(Sw * Fn + Sv * Ff, axis=1)

    def limit_torque(self, q, qd, kp=1000.0, kd=100.0, steep=50.0):
        """Joint-limit contact torque of eq. 3.6 (``LimitContact`` defaults)."""
        s = 1.0 - 1.0 / np.sqrt(1.0 + (steep * qd) ** 2)
        damp = kd * qd * s
        below = kp * (q - self.qmin) + np.where(qd < 0, damp, 0.0)
        above = kp * (q - self.qmax) + np.where(qd > 0, damp, 0.0)
        tau = np.where(q < self.qmin, below, np.where(q > self.qmax, above, 0.0))
        return np.where(self.lim, tau, 0.0)

    def pois(self, frames, q):
        """World points of interest ``(n P, 3)``, link-major."""
        start = np.where(self.pri[:, None], -q[:, None] * self.axis_local, 0.0)
        local = start[:, None, :] + self.fracs[None, :, None] * (self.seg - start)[:, None, :]
        world = np.einsum("nij,nkj->nki", frames[:, :3, :3], local) + frames[:, None, :3, 3]
        return world.reshape(-1, 3)

    def poi_jacobians(self, S, pois):
        """Point Jacobians ``(n P, 3, n)`` (telescoping prismatic segments scaled by ``k / P``)."""
        cols = S[None, :, 3:] + _cross(S[None, :, :3], pois[:, None, :])  # (m, n, 3)
        return np.transpose(cols, (0, 2, 1)) * self.poi_scale[:, None, :]


class Pass(SimpleNamespace):
    """One evaluation's shared quantities: ``q, qd, frames, ee, S, body, M, h`` (``h = c + g``)."""


def state_pass(na: NumpyArm, q, qd) -> Pass:
    frames, ee, S = na.fk(q)
    body = na.body(frames)
    return Pass(q=q, qd=qd, frames=frames, ee=ee, S=S, body=body, M=na.mass_matrix(S, body),
                h=na.rnea(S, body, qd, np.zeros_like(qd)))


# ----------------------------------------------------------------------------------------------
# NumPy quaternions, obstacles, null space


def rot_to_quat(R):
    """Shepperd's method, ``w >= 0`` (as ``redman_jax._math.rot_to_quat``)."""
    t = np.trace(R)
    d = np.diag(R)
    k = int(np.argmax([t, d[0], d[1], d[2]]))
    if k == 0:
        r = np.sqrt(max(1 + t, 1e-12))
        q = [0.5 * r, (R[2, 1] - R[1, 2]) / (2 * r), (R[0, 2] - R[2, 0]) / (2 * r), (R[1, 0] - R[0, 1]) / (2 * r)]
    elif k == 1:
        r = np.sqrt(max(1 + d[0] - d[1] - d[2], 1e-12))
        q = [(R[2, 1] - R[1, 2]) / (2 * r), 0.5 * r, (R[0, 1] + R[1, 0]) / (2 * r), (R[0, 2] + R[2, 0]) / (2 * r)]
    elif k == 2:
        r = np.sqrt(max(1 - d[0] + d[1] - d[2], 1e-12))
        q = [(R[0, 2] - R[2, 0]) / (2 * r), (R[0, 1] + R[1, 0]) / (2 * r), 0.5 * r, (R[1, 2] + R[2, 1]) / (2 * r)]
    else:
        r = np.sqrt(max(1 - d[0] - d[1] + d[2], 1e-12))
        q = [(R[1, 0] - R[0, 1]) / (2 * r), (R[0, 2] + R[2, 0]) / (2 * r), (R[1, 2] + R[2, 1]) / (2 * r), 0.5 * r]
    q = np.asarray(q) / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quat_error(q_d, q):
    """``vec(Q_d (x) Q^-1)`` with ``q`` flipped into the hemisphere of ``q_d`` (E1)."""
    if q_d @ q < 0:
        q = -q
    return q[0] * q_d[1:] - q_d[0] * q[1:] - _cross(q_d[1:], q[1:])


def clip_norm(e, limit):
    n = np.linalg.norm(e)
    return e * (limit / n) if n > limit else e


class NumpyObstacles:
    """The active slots of an (unbatched) ``ObstacleSet``: ``[(kind, R (K,3,3), p (K,3), dims (K,3))]``."""

    def __init__(self, obs):
        self.families = []
        for kind in ("spheres", "boxes", "cylinders"):
            fam = getattr(obs, kind)
            mk = np.asarray(fam.mask, bool)
            if mk.any():
                self.families.append((kind, np.asarray(fam.R)[mk], np.asarray(fam.p)[mk], np.asarray(fam.dims)[mk]))

    def sdf(self, X, normals=False):
        """Per family: signed distances ``(K, m)`` of the points ``X`` (m, 3) and, with ``normals``,
        the sdf gradients ``(K, m, 3)`` (zero where undefined; inside a box the nearest face)."""
        out = []
        for kind, R, p, dims in self.families:
            d = X[None, :, :] - p[:, None, :]
            if kind == "spheres":
                rr = np.sqrt(np.sum(d * d, axis=2))
                sdf = rr - dims[:, :1]
                n = d / np.where(rr > 0, rr, 1.0)[..., None] if normals else None
                out.append((sdf, n))
                continue
            xl = np.einsum("kji,kmj->kmi", R, d)  # R^T (x - p)
            sgn = np.where(xl < 0, -1.0, 1.0)
            if kind == "boxes":
                u = np.abs(xl) - dims[:, None, :]
                o = np.maximum(u, 0.0)
                on = np.sqrt(np.sum(o * o, axis=2))
                out_ = on > 0
                sdf = np.where(out_, on, np.minimum(u.max(axis=2), 0.0))
                n = None
                if normals:
                    face = (np.arange(3) == np.argmax(u, axis=2)[..., None]).astype(float)
                    nl = sgn * np.where(out_[..., None], o / np.where(out_, on, 1.0)[..., None], face)
                    n = np.einsum("kij,kmj->kmi", R, nl)
            else:  # cylinders: radius dims[0], half-height dims[1], local z axis
                rho = np.sqrt(xl[..., 0] ** 2 + xl[..., 1] ** 2)
                d1 = rho - dims[:, :1]
                d2 = np.abs(xl[..., 2]) - dims[:, 1:2]
                o1, o2 = np.maximum(d1, 0.0), np.maximum(d2, 0.0)
                on = np.sqrt(o1 * o1 + o2 * o2)
                out_ = on > 0
                sdf = np.where(out_, on, np.minimum(np.maximum(d1, d2), 0.0))
                n = None
                if normals:
                    den = np.where(out_, on, 1.0)
                    w_rad = np.where(rho > 0, np.where(out_, o1, d1 >= d2) / (den * np.where(rho > 0, rho, 1.0)), 0.0)
                    w_ax = sgn[..., 2] * np.where(out_, o2, d1 < d2) / den
                    nl = np.stack([w_rad * xl[..., 0], w_rad * xl[..., 1], w_ax], axis=-1)
                    n = np.einsum("kij,kmj->kmi", R, nl)
            out.append((sdf, n))
        return out

    def min_distance(self, X):
        """Smallest signed distance of each point to any obstacle ``(m,)`` (1e3 if none)."""
        best = np.full(len(X), BIG_DISTANCE)
        for sdf, _ in self.sdf(X):
            best = np.minimum(best, sdf.min(axis=0))
        return best

    def gradients(self, X, a, D, form="minus", clamp=1e-3):
        """``sum_o grad V_o(x)`` ``(m, 3)``: ``V_o'(max(sdf, clamp))`` along the unclamped sdf
        gradient, zero beyond ``D`` (``redman_jax._nullspace.obstacle_gradients``)."""
        sgn = -1.0 if form == "minus" else 1.0
        g = np.zeros_like(X)
        for sdf, n in self.sdf(X, normals=True):
            r = np.maximum(sdf, clamp)
            slope = np.where(sdf <= D, (-a / D) * (3.0 * D + sgn * 2.0 * r), 0.0) / r ** 4
            g += np.einsum("km,kmi->mi", slope, n)
        return g


def nullspace_policy(na: NumpyArm, ps: Pass, obs: NumpyObstacles, pg):
    """``h = q_dd_obs + q_dd_jl + q_dd_damp`` (3.33-3.36; point Jacobians, form "minus")."""
    pois = na.pois(ps.frames, ps.q)
    f = -pg.gamma * obs.gradients(pois, pg.obs_a, pg.obs_D)
    h_obs = np.einsum("mjn,mj->n", na.poi_jacobians(ps.S, pois), f)
    q_mid, half = 0.5 * (na.qmin + na.qmax), 0.5 * (na.qmax - na.qmin)
    u = ps.q - q_mid
    inside = np.abs(u) < half
    den = np.where(inside, half * half - u * u, 1.0)
    barrier = np.clip(-pg.jl_a * u / (den * np.sqrt(den)), -pg.jl_outside, pg.jl_outside)
    h_jl = np.where(na.lim, np.where(inside, barrier, -np.sign(u) * pg.jl_outside), 0.0)
    return h_obs + h_jl - pg.damping * ps.qd


def task_jacobian(J, rot, s_trans, s_rot):
    """``J_s = diag(S) J`` with the rotational rows zeroed when ``rot`` is 0 (3.13)."""
    m = np.array([True] * 3 + [rot > 0.5] * 3)
    S = np.array([s_trans] * 3 + [s_rot] * 3)
    return np.where(m[:, None], S[:, None] * J, 0.0), m, S


def damping_factor(J_s, m, ratio, floor):
    """``lam = max(ratio sigma_min(J_active), floor)`` (3.31-3.32), ``sigma_min`` by ``eigvalsh``."""
    Ja = J_s[m]
    mu = np.linalg.eigvalsh(Ja @ Ja.T)[0]
    return max(ratio * (np.sqrt(mu) if mu > 0 else 0.0), floor)


def damped_solve(J, B, lam):
    """``J^T (J J^T + lam^2 I)^-1 B`` (3.29)."""
    return J.T @ np.linalg.solve(J @ J.T + lam * lam * np.eye(J.shape[0]), B)


def jdot_qdot(ps: Pass):
    """``J_dot q_dot`` of the end-effector Jacobian from the link twists (3.17)."""
    S, qd = ps.S, ps.qd
    tw = S * qd[:, None]
    V = np.cumsum(tw, axis=0)
    Vp = V - tw
    sd_w = _cross(Vp[:, :3], S[:, :3])
    sd_v = _cross(Vp[:, 3:], S[:, :3]) + _cross(Vp[:, :3], S[:, 3:])
    alpha, a_s = sd_w.T @ qd, sd_v.T @ qd
    omega, v_s = V[-1, :3], V[-1, 3:]
    p = ps.ee[:3, 3]
    pd = v_s + _cross(omega, p)
    return np.concatenate([a_s + _cross(alpha, p) + _cross(omega, pd), alpha])


# ----------------------------------------------------------------------------------------------
# NumPy controllers (``redman_jax._controllers``, default options: rows_only scaling, null space
# in the acceleration domain with point Jacobians). Each returns ``(tau, dz)``.


def np_joint_space(g, na, ps, z, rs, obs):
    """JointSpaceID: ``tau = M(qdd_d + K_d(qd_d - qd) + K_p(q_d - q)) + c + g``."""
    qdd = rs.qdd + g.kd * (rs.qd - ps.qd) + g.kp * (rs.q - ps.q)
    return ps.M @ qdd + ps.h, None


def _osc_frame(ps):
    J = NumpyArm.jacobian(ps.ee, ps.S)
    return J, ps.ee[:3, 3], rot_to_quat(ps.ee[:3, :3])


def np_velocity(g, na, ps, z, rs, obs):
    """VelocityOSC: ``qd_r = J# xd_r``, ``dq_r/dt = qd_r``,
    ``qdd_r = K_pq (q_r - q) + K_dq (qd_r - qd) + alpha N h``, ``tau = M qdd_r + c + g``."""
    pg = g.policy
    J, p, quat = _osc_frame(ps)
    J_s, m, _ = task_jacobian(J, rs.rot, g.s_trans, g.s_rot)
    e_o = clip_norm(quat_error(rs.quat, quat), g.rot_clip)
    b = np.where(m, np.concatenate([rs.v + g.kp * (rs.p - p), rs.omega + g.kpr * e_o]), 0.0)
    lam = damping_factor(J_s, m, pg.lam_ratio, pg.lam_floor)
    h = pg.alpha * nullspace_policy(na, ps, obs, pg)
    X = damped_solve(J_s, np.stack([b, J_s @ h], axis=1), lam)
    qd_r = X[:, 0]
    qdd_r = g.kpq * (z - ps.q) + g.kdq * (qd_r - ps.qd) + (h - X[:, 1])
    return ps.M @ qdd_r + ps.h, qd_r


def np_acceleration(g, na, ps, z, rs, obs):
    """AccelerationOSC: ``qdd_r = alpha h + J_s^T Y^-1 (b - alpha J_s h)`` with
    ``b = xdd_r - S J_dot q_dot`` on the active rows, ``tau = M qdd_r + c + g``."""
    J, p, quat = _osc_frame(ps)
    J_s, m, S = task_jacobian(J, rs.rot, g.s_trans, g.s_rot)
    xd = J @ ps.qd
    e_o = clip_norm(quat_error(rs.quat, quat), g.rot_clip)
    xdd_r = np.concatenate([rs.a + g.kd * (rs.v - xd[:3]) + g.kp * (rs.p - p),
                            rs.omega_dot + g.kdr * (rs.omega - xd[3:]) + g.kpr * e_o])
    return _acc_torque(g, na, ps, obs, J_s, m, np.where(m, xdd_r - S * jdot_qdot(ps), 0.0)), None


def _acc_torque(g, na, ps, obs, J_s, m, b):
    """``M (J# b + alpha N h) + c + g`` for the task acceleration ``b`` (already minus
    ``S J_dot q_dot``): the acceleration-level command of the acceleration and gradient-guided OSC."""
    pg = g.policy
    lam = damping_factor(J_s, m, pg.lam_ratio, pg.lam_floor)
    h = pg.alpha * nullspace_policy(na, ps, obs, pg)
    X = damped_solve(J_s, np.stack([b, J_s @ h], axis=1), lam)
    return ps.M @ (X[:, 0] + h - X[:, 1]) + ps.h


RHO_FLOOR = 1e-6  # redman_jax._fields.RHO_FLOOR


def total_gradient(x, env, obs: NumpyObstacles, fp, A=None):
    """Gradient of the guidance field at ``x`` (3.23): goal ``2 (x - x_g)``, obstacles (``fp.a``,
    ``fp.D``, form, clamp) and the active virtual obstacles' cones ``-A d / (rho (rho + 1)^2)``
    within ``d_v``, ``A = amp |x - x_g|^2`` (``vo_amp="ee"``), or ``A`` as given: the Hessian holds
    it constant (U4)."""
    e = x - env.goal_p
    g = 2.0 * e + obs.gradients(x[None], fp.a, fp.D, fp.form, fp.clamp)[0]
    if len(env.virtual_p):
        A = fp.amp * (e @ e) if A is None else A
        d = x[None, :] - env.virtual_p
        rho = np.sqrt(np.sum(d * d, axis=1))
        coef = np.where(rho <= fp.d_v, -A / (np.maximum(rho, RHO_FLOOR) * (rho + 1.0) ** 2), 0.0)
        g = g + coef @ d
    return g


def np_gradient(g, na, ps, z, rs, obs):
    """GradientGuided: ``xd_g = -a tanh(|x - x_g|/b) grad V/|grad V|`` at the end effector,
    ``xdd_r = [K_d (xd_g - pd); -K_dr w + K_pr clip(e_o)]``, then as the acceleration OSC."""
    J, p, quat = _osc_frame(ps)
    J_s, m, S = task_jacobian(J, rs.rot, g.s_trans, g.s_rot)
    xd = J @ ps.qd
    gr = total_gradient(p, rs, obs, g.field)
    e = p - rs.goal_p
    xd_g = -g.guide_a * np.tanh(np.sqrt(e @ e) / g.guide_b) * gr / (np.sqrt(gr @ gr) + 1e-9)
    e_o = clip_norm(quat_error(rs.quat, quat), g.rot_clip)
    xdd_r = np.concatenate([g.kd * (xd_g - xd[:3]), -g.kdr * xd[3:] + g.kpr * e_o])
    return _acc_torque(g, na, ps, obs, J_s, m, np.where(m, xdd_r - S * jdot_qdot(ps), 0.0)), None


NP_CONTROLLERS = {"joint_space": np_joint_space, "velocity": np_velocity, "acceleration": np_acceleration,
                  "gradient": np_gradient}


def numpy_gains(gains):
    """A JAX gains Module as nested ``SimpleNamespace``s of Python floats."""
    out = {}
    for f in dataclasses.fields(gains):
        v = getattr(gains, f.name)
        out[f.name] = (numpy_gains(v) if dataclasses.is_dataclass(v) else
                       v if isinstance(v, (str, bool)) else float(v))
    return SimpleNamespace(**out)


# ----------------------------------------------------------------------------------------------
# NumPy closed loop, integrated per sample with solve_ivp


def _np(tree):
    return jax.tree.map(np.asarray, tree)


class NumpyLoop:
    """``_sim._closed_loop`` in NumPy for one scenario: ``y = (q, qd[, q_r])``,
    ``q_dot = qd``, ``qd_dot = M^-1 (tau - tau_lim - c - g)``, ``q_r_dot = dz``; the reference
    sample is held per sample as in ``_sim._ref_sample``."""

    def __init__(self, na: NumpyArm, name: str, gains, scenario, ik=None):
        self.na, self.name = na, name
        self.ctrl = NP_CONTROLLERS[name]
        self.g = numpy_gains(gains)
        self.obs = NumpyObstacles(scenario.obstacles)
        ref = _np(scenario.reference)
        self.ref, self.ts, self.n_samples = ref, float(ref.ts), int(ref.n_samples)
        self.jref = None if ik is None else _np(joint_reference(ik, ref.p.shape[0]))
        self.has_z = name == "velocity"
        self.collided = self.outside = False
        self.nfev = 0

    def y0(self):
        na = self.na
        parts = [na.q0, np.zeros(na.n)] + ([na.q0] if self.has_z else [])
        return np.concatenate(parts)

    def ref_sample(self, k):
        r, last = self.ref, self.n_samples - 1
        kk = min(max(k, 0), last)
        n = self.na.n
        if self.jref is None:
            jq = jqd = jqdd = np.zeros(n)
        else:
            moving = k < last
            jq = self.jref.q[kk]
            jqd = self.jref.qd[kk] if moving else np.zeros(n)
            jqdd = self.jref.qdd[kk] if moving else np.zeros(n)
        return SimpleNamespace(p=r.p[kk], v=r.v[kk], a=r.a[kk], quat=r.quat[kk], omega=r.omega[kk],
                               omega_dot=r.omega_dot[kk], rot=float(r.rot[kk]), q=jq, qd=jqd, qdd=jqdd)

    def field(self, t, y, rs):
        self.nfev += 1
        na, n = self.na, self.na.n
        q, qd = y[:n], y[n:2 * n]
        z = y[2 * n:] if self.has_z else None
        ps = state_pass(na, q, qd)
        tau, dz = self.ctrl(self.g, na, ps, z, rs, self.obs)
        qdd = np.linalg.solve(ps.M, tau - ps.h - na.limit_torque(q, qd))
        # flags (thesis 3.5), latched
        dmin = self.obs.min_distance(na.pois(ps.frames, q))
        self.collided |= bool(np.any(dmin < na.poi_width))
        self.outside |= bool(np.any(na.lim & ((q < na.qmin) | (q > na.qmax))))
        return np.concatenate([qd, qdd] + ([dz] if self.has_z else []))

    def run(self, n_samples=None, rtol=1e-5, atol=1e-7, method="DOP853"):
        """Integrate the first ``n_samples`` samples, one ``solve_ivp`` call each; returns the states
        at the sample ends ``(n_samples, len(y))``."""
        ns = self.n_samples if n_samples is None else min(n_samples, self.n_samples)
        y, ys = self.y0(), []
        for k in range(ns):
            sol = solve_ivp(self.field, (k * self.ts, (k + 1) * self.ts), y, method=method, rtol=rtol,
                            atol=atol, args=(self.ref_sample(k),))
            if sol.status < 0:
                raise RuntimeError(f"solve_ivp failed in sample {k}: {sol.message}")
            y = sol.y[:, -1]
            ys.append(y)
        return np.stack(ys)


class NumpyGuidedLoop(NumpyLoop):
    """``_sim._simulate_guided`` (``mode="per_sample"``) in NumPy: at each sample start the
    local-minima estimator (3.24: one Newton step ``x - (H + mu I)^-1 g`` at the end effector, ``H``
    by central differences of the analytic gradient, as a MATLAB script would take it) pushes its
    estimate into the 20-slot virtual-obstacle buffer if finite and within ``lme_max_jump``, and the
    orientation latch switches on within ``guidance_rot_radius`` of the goal; the sample is held at
    the goal pose at rest; the run stops once the end effector has been within ``goal_radius`` at
    ``hold_samples`` consecutive sample ends, or after ``guidance_samples``."""

    def __init__(self, na: NumpyArm, gains, scenario, params):
        self.na, self.name = na, "gradient"
        self.ctrl = np_gradient
        self.g = numpy_gains(gains)
        if self.g.field.vo_amp != "ee" or self.g.field.amp_exact:
            raise ValueError("NumpyGuidedLoop: the default guidance field only (vo_amp='ee', amp_exact=False)")
        self.obs = NumpyObstacles(scenario.obstacles)
        self.goal_p = np.asarray(scenario.goal_p, float)
        self.goal_quat = np.asarray(scenario.goal_quat, float)
        self.ts = float(np.asarray(scenario.reference.ts))
        self.n_samples = int(params.guidance_samples)
        self.p = SimpleNamespace(**{k: float(getattr(params, k)) for k in
                                    ("lme_mu", "lme_max_jump", "guidance_rot_radius", "goal_radius")},
                                 hold=int(params.hold_samples), B=int(params.buffer_size))
        self.has_z = False
        self.collided = self.outside = False
        self.nfev = 0

    def env(self, vp, rot):
        n = self.na.n
        return SimpleNamespace(goal_p=self.goal_p, virtual_p=np.asarray(vp).reshape(-1, 3), p=self.goal_p,
                               v=np.zeros(3), a=np.zeros(3), quat=self.goal_quat, omega=np.zeros(3),
                               omega_dot=np.zeros(3), rot=rot, q=np.zeros(n), qd=np.zeros(n),
                               qdd=np.zeros(n))

    def estimate(self, x, vp, h=1e-6):
        """``(x_min, valid)`` of 3.24 at ``x`` with the virtual obstacles ``vp``."""
        env, fp = self.env(vp, 0.0), self.g.field
        g = total_gradient(x, env, self.obs, fp)
        A = fp.amp * float((x - self.goal_p) @ (x - self.goal_p))  # held constant in H (U4)
        H = np.empty((3, 3))
        for j in range(3):
            dx = np.zeros(3)
            dx[j] = h
            H[:, j] = (total_gradient(x + dx, env, self.obs, fp, A) - total_gradient(x - dx, env, self.obs, fp, A)) / (2 * h)
        with np.errstate(all="ignore"):
            x_min = x - np.linalg.solve(H + self.p.lme_mu * np.eye(3), g)
        valid = bool(np.all(np.isfinite(x_min)) and np.linalg.norm(x_min - x) <= self.p.lme_max_jump)
        return (x_min if np.all(np.isfinite(x_min)) else x), valid

    def run(self, n_samples=None, rtol=1e-5, atol=1e-7, method="DOP853"):
        """Integrate the first ``n_samples`` samples (or up to the stop rule), one ``solve_ivp`` call
        each; returns the states at the sample ends ``(samples run, len(y))``."""
        ns = self.n_samples if n_samples is None else min(n_samples, self.n_samples)
        n = self.na.n
        y, ys, vp, rot, hold = self.y0(), [], [], 0.0, 0
        x = self.na.fk(y[:n])[1][:3, 3]  # the end effector at the sample start
        for k in range(ns):
            x_min, valid = self.estimate(x, vp)
            if valid:
                vp = (vp + [x_min])[-self.p.B:]  # FIFO: the oldest estimate overwritten when full
            if np.linalg.norm(x - self.goal_p) < self.p.guidance_rot_radius:
                rot = 1.0
            sol = solve_ivp(self.field, (k * self.ts, (k + 1) * self.ts), y, method=method, rtol=rtol,
                            atol=atol, args=(self.env(vp, rot),))
            if sol.status < 0:
                raise RuntimeError(f"solve_ivp failed in sample {k}: {sol.message}")
            y = sol.y[:, -1]
            ys.append(y)
            x = self.na.fk(y[:n])[1][:3, 3]  # at the sample end: the stop rule, then the next start
            hold = hold + 1 if np.linalg.norm(x - self.goal_p) < self.p.goal_radius else 0
            if hold >= self.p.hold:
                break
        return np.stack(ys)


# ----------------------------------------------------------------------------------------------
# JAX side


def _block(x):
    return jax.block_until_ready(x)


def time_jax(arm, scen, ik, name, params, threads=None):
    """``(result, cold s, warm s)`` of ``simulate_batch`` over all seeds. With several JAX devices
    (``--devices``) the batch is padded to a multiple of them and sharded over them, as the sweep
    does (``_pipeline.shard_batch``), in one call (each device steps its own rows, ``shard_map``)."""
    c = CONTROLLERS[name]()
    g = c.default_gains()
    ik_arg = ik if c.needs_joint_reference else None
    R = int(np.asarray(scen.reference.n_samples).shape[0])
    if len(jax.devices()) > 1:
        from redman_jax._pipeline import _pad_batch, shard_batch

        (scen, ik_arg), _ = _pad_batch((scen, ik_arg), len(jax.devices()))
        scen, ik_arg = shard_batch((scen, ik_arg))
    t0 = time.perf_counter()
    _block(simulate_batch(arm, scen, c, g, ik=ik_arg, params=params, threads=threads))
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = _block(simulate_batch(arm, scen, c, g, ik=ik_arg, params=params, threads=threads))
    warm = time.perf_counter() - t0
    return jax.tree.map(lambda x: np.asarray(x)[:R], res), cold, warm


def jax_evals(res, N, uses_guidance, params):
    """Vector-field evaluations per member: FSAL Dopri5 or Tsit5 costs 6 per attempted step plus one at the
    start and after every jump (horizon mode: the boundaries of the run's valid samples, none in
    the padding up to the capacity ``N``; gradient runs: every sample end up to the stop rule, where
    each member stops stepping)."""
    steps = np.asarray(res.n_steps, float)
    return 6 * steps + np.asarray(res.n_samples, float)


def batch_use(steps, chunks: int) -> float:
    """The share of the vmapped loop iterations that step a member still running: ``sum(steps) /
    sum over chunks (rows x the chunk's largest step count)``, the chunks as ``simulate_batch``
    splits the batch over threads (``_sim._chunk_rows``: contiguous rows, the last padded with
    copies of its last member). Under ``vmap`` a chunk iterates until its slowest member is done,
    every row each time, so 1 - this is the work spent on members that have finished."""
    from redman_jax._sim import _chunk_rows

    steps = np.asarray(steps, float)
    paid = sum(rows.size * steps[rows].max() for rows in _chunk_rows(steps.size, chunks))
    return float(steps.sum() / paid)


def count_evals(arm, sc, ctrl, gains, params, ik=None):
    """Exact vector-field evaluations of one run (a host callback counts the controller calls)."""
    counter = [0]

    class Counting(AbstractController):
        inner: AbstractController

        def default_gains(self):
            return self.inner.default_gains()

        def init_state(self, a, q0, qd0):
            return self.inner.init_state(a, q0, qd0)

        @property
        def needs_joint_reference(self):
            return self.inner.needs_joint_reference

        @property
        def uses_guidance(self):
            return self.inner.uses_guidance

        def __call__(self, g, a, s, r, e):
            jax.debug.callback(lambda: counter.__setitem__(0, counter[0] + 1))
            return self.inner(g, a, s, r, e)

    r = _block(simulate(arm, sc, Counting(ctrl), gains, ik=ik, params=params))
    return counter[0], int(r.n_steps)


# ----------------------------------------------------------------------------------------------


def _x(v):
    return f"{v:.0f}x" if v >= 10 else f"{v:.1f}x"


def _take(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    ap.add_argument("--controllers", nargs="+", default=list(NUMPY_CONTROLLERS) + ["gradient"],
                    choices=list(NUMPY_CONTROLLERS) + ["gradient"])
    ap.add_argument("--dof", type=int, default=9)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--scipy-seeds", type=int, default=1)
    ap.add_argument("--scipy-samples", type=int, default=100,
                    help="time only the first K samples of each SciPy run (0: all)")
    ap.add_argument("--method", default="DOP853")
    ap.add_argument("--threads", type=int, default=None,
                    help="simulate_batch's threads (default: its own choice, one chunk of the batch per core)")
    ap.add_argument("--devices", type=int, default=None,
                    help="CPU: split the host into this many XLA devices and shard the batch over them "
                         "(instead of threads; --xla_force_host_platform_device_count)")
    ap.add_argument("--exact-evals", action="store_true",
                    help="check the JAX evaluation count of seed 1 with a counting callback (recompiles)")
    ap.add_argument("--xla-flags", choices=("default", "study"), default="default",
                    help="'study': start JAX with the XLA flags the study's workers use "
                         "(redman_jax._study.WORKER_XLA_FLAGS, added to $XLA_FLAGS)")
    args = ap.parse_args(argv)
    if args.devices is not None and args.threads not in (None, 1):
        raise SystemExit(f"--devices: shards the batch over the devices in one call; "
                         f"no --threads {args.threads}")
    if args.xla_flags == "study" or args.devices is not None:
        from _xla_start import start_with_host_devices, start_with_xla_flags

        from redman_jax._study import WORKER_XLA_FLAGS

        extra = WORKER_XLA_FLAGS if args.xla_flags == "study" else ()
        if args.devices is None:
            start_with_xla_flags(extra, "--xla-flags study")
        else:
            start_with_host_devices(args.devices, extra)

    params = SimParams()
    # None (the default) means by the states' precision: float64's unless x64 is off
    rtol, atol = (float(v) for v in tolerances(params, jnp.result_type(float)))
    print(f"machine: {platform.platform()}, {_cpu_model()}, "
          f"{os.cpu_count()} cpus (shared); python {platform.python_version()}")
    print(f"load average at start (1, 5, 15 min): {os.getloadavg()}")
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r} (--xla-flags {args.xla_flags})")
    print(f"jax {jax.__version__} on {jax.devices()[0].platform} ({jax.devices()}), numpy {np.__version__}, "
          f"scipy {scipy.__version__}, x64={jax.config.jax_enable_x64}")
    from redman_jax._sim import _chunks

    ndev = len(jax.devices())
    chunks = ndev if ndev > 1 else _chunks(args.threads, args.seeds, ())
    split = (f"sharded over {ndev} devices ({-(-args.seeds // ndev)} seeds each)" if ndev > 1 else
             f"in {chunks} thread(s) of {-(-args.seeds // chunks)} seeds (threads={args.threads})")
    print(f"JAX: simulate_batch over {args.seeds} seeds {split}; the process may use "
          f"{len(os.sched_getaffinity(0))} core(s); {params.solver} rtol {rtol:g} atol {atol:g}, "
          f"one horizon solve "
          f"(gradient: one stepping loop over its {params.guidance_samples}-sample horizon); "
          f"cold = first call incl. compilation, warm = second call.")
    K = args.scipy_samples
    print(f"SciPy: NumPy closed loop, solve_ivp {args.method} rtol {rtol:g} atol {atol:g} per sample, one seed "
          f"at a time, {args.scipy_seeds} seed(s), "
          + (f"first {K} samples timed and extrapolated per simulated second." if K else "whole runs."))
    print("sim-s/s = simulated seconds per wall second (valid samples, summed over seeds); evals per simulated "
          "second and trajectory; speed-up = JAX sim-s/s (all seeds, one call) / SciPy sim-s/s.\n")

    from redman_jax._pipeline import build_case

    arm = thesis_arm(args.dof)
    na = NumpyArm(arm)
    seeds = list(range(1, args.seeds + 1))
    head = (f"{'case':<12} {'controller':<13} {'sim s':>6} {'JAX cold s':>10} {'cold sim-s/s':>12} "
            f"{'warm s':>7} {'warm sim-s/s':>12} {'JAX evals/sim-s':>15} {'use':>4} {'ok':>5} | {'SciPy sim-s/s':>13} "
            f"{'SciPy evals/sim-s':>17} {'max|dq|':>8} | {'x warm':>7} {'x cold':>7}")
    rows = []
    for case in args.cases:
        t0 = time.perf_counter()
        built = build_case(arm, case, seeds)
        scen, ik = built["scenarios"], built["ik"]
        n_samples = np.asarray(scen.reference.n_samples)
        ts = float(np.asarray(scen.reference.ts)[0])
        N = scen.reference.p.shape[1]
        print(f"[{case}] build_case: {time.perf_counter() - t0:.1f} s, {len(seeds)} seeds, samples "
              f"{n_samples.min()}..{n_samples.max()} (capacity {N}), valid {int(np.asarray(scen.valid).sum())}",
              flush=True)
        for name in args.controllers:
            gradient = name == "gradient"
            if gradient and case not in GRADIENT_CASES:
                continue
            res, cold, warm = time_jax(arm, scen, ik, name, params, args.threads)
            # gradient runs: the samples up to each member's stop rule (it stops stepping there)
            n_run = np.asarray(res.n_samples) if gradient else n_samples
            T = float(n_run.sum() * ts)
            evals = jax_evals(res, N, gradient, params)
            T_member = n_run * ts
            jax_eps = float(np.mean(evals / T_member))
            ok = f"{int(np.asarray(res.success).sum())}/{len(seeds)}"
            row = dict(case=case, ctrl=name, T=T, cold=cold, warm=warm, jax_cold=T / cold, jax_warm=T / warm,
                       jax_eps=jax_eps, ok=ok, use=None if gradient else batch_use(res.n_steps, chunks))
            if args.exact_evals:
                c = CONTROLLERS[name]()
                exact, st = count_evals(arm, _take(scen, 0), c, c.default_gains(), params,
                                        ik=_take(ik, 0) if c.needs_joint_reference else None)
                print(f"  {name}: seed 1 exact evaluations {exact} ({st} steps), formula {evals[0]:.0f}")
            if name in NP_CONTROLLERS:
                t_np = T_np = 0.0
                fe, dq = 0, 0.0
                c = CONTROLLERS[name]()
                for i in range(min(args.scipy_seeds, len(seeds))):
                    if gradient:
                        loop = NumpyGuidedLoop(na, c.default_gains(), _take(scen, i), params)
                    else:
                        loop = NumpyLoop(na, name, c.default_gains(), _take(scen, i),
                                         _take(ik, i) if c.needs_joint_reference else None)
                    ns = loop.n_samples if K <= 0 else min(K, loop.n_samples)
                    t0 = time.perf_counter()
                    ys = loop.run(ns, rtol, atol, args.method)
                    t_np += time.perf_counter() - t0
                    ns = len(ys)  # a gradient-guided run may stop earlier (its stop rule)
                    T_np += ns * ts
                    fe += loop.nfev
                    dq = max(dq, float(np.abs(ys[:, :na.n] - np.asarray(res.q[i, :ns])).max()))
                row.update(np_rate=T_np / t_np, np_eps=fe / T_np, dq=dq)
                row.update(x_warm=row["jax_warm"] / row["np_rate"], x_cold=row["jax_cold"] / row["np_rate"])
            rows.append(row)
            print(f"  {name}: JAX cold {cold:.1f} s, warm {warm:.2f} s"
                  + (f"; SciPy {row['np_rate']:.4f} sim-s/s, speed-up warm {_x(row['x_warm'])}" if "np_rate" in row
                     else ""), flush=True)

    print(f"\n{head}")
    for r in rows:
        line = (f"{r['case']:<12} {r['ctrl']:<13} {r['T']:6.1f} {r['cold']:10.1f} {r['jax_cold']:12.2f} "
                f"{r['warm']:7.2f} {r['jax_warm']:12.2f} {r['jax_eps']:15.0f} {'–' if r['use'] is None else format(r['use'], '4.2f'):>4} {r['ok']:>5} | ")
        if "np_rate" in r:
            line += (f"{r['np_rate']:13.4f} {r['np_eps']:17.0f} {r['dq']:8.1e} | {_x(r['x_warm']):>7} "
                     f"{_x(r['x_cold']):>7}")
        else:
            line += f"{'JAX only':>13} {'':>17} {'':>8} | {'':>7} {'':>7}"
        print(line)
    both = [r for r in rows if "np_rate" in r]
    if both:
        xs = np.array([r["x_warm"] for r in both])
        print(f"\nspeed-up (warm, {args.seeds} seeds) over SciPy: min {xs.min():.0f}x, median {np.median(xs):.0f}x, "
              f"max {xs.max():.0f}x; target >= 100x met in {int((xs >= 100).sum())}/{len(xs)} rows")
        if K:
            print(f"(SciPy timed on the first {K} samples = {K * ts:g} s of {min(args.scipy_seeds, args.seeds)} "
                  f"seed(s) and extrapolated per simulated second; max|dq| = largest |q_numpy - q_jax| [rad or m] at "
                  f"the timed sample ends)")
    print("use = share of the vmapped loop's iterations that step a member still running (batch_use: each "
          "thread's chunk iterates until its slowest member is done)")


if __name__ == "__main__":
    main()
