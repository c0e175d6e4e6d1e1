"""Closed-loop simulation speed: redman-jax (diffrax, jit(vmap) over 20 seeds) against a plain
NumPy + SciPy ``solve_ivp`` version of the same closed loop run one seed at a time (what a MATLAB
``ode113``-per-sample workflow does), plus the tolerance study (metrics at rtol 1e-5 vs 1e-9).

Run: ``.venv/bin/python benchmarks/bench_sim.py [--case welding] [--seeds 20] [--scipy-seeds 2]``

* Controller for the side-by-side: an operational-space PD of our own (``OSCPD`` below:
  computed torque on the position rows with a damped pseudo-inverse and null-space damping),
  written twice: in JAX and in NumPy. The NumPy loop reuses nothing jitted: forward kinematics,
  mass matrix, recursive Newton-Euler, joint-limit contact, points of interest, signed distances
  and the flags are re-implemented with NumPy here. The SciPy side integrates each sample with
  ``solve_ivp`` (default DOP853, same rtol/atol), as ode113 was called once per sample.
* Also timed (JAX only): the real controllers of ``redman_jax._controllers`` when importable.
* Reported: simulated seconds per wall second (cold = first call incl. compilation, warm =
  second call), vector-field evaluations and rejected steps per trajectory.
"""

from __future__ import annotations

import argparse
import platform
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import redman_jax  # noqa: F401
from redman_jax._control_types import AbstractController, ControlOutput
from redman_jax._dynamics import dynamics_terms
from redman_jax._kinematics import jacobian_from, jdot_qdot, kinematics
from redman_jax._robot import thesis_arm
from redman_jax._sim import SimParams, simulate, simulate_batch


# ----------------------------------------------------------------------------------------------
# the JAX controller


class PDGains(eqx.Module):
    kp: jax.Array = eqx.field(default=250.0, converter=jnp.asarray)
    kd: jax.Array = eqx.field(default=31.0, converter=jnp.asarray)
    kn: jax.Array = eqx.field(default=10.0, converter=jnp.asarray)


class OSCPD(AbstractController):
    """``qdd = J#(a_d + K_d(v_d - v) + K_p(p_d - p) - Jdot qd) - N k_n qd``, ``tau = M qdd + c + g``."""

    def default_gains(self):
        return PDGains()

    def init_state(self, arm, q0, qd0):
        return ()

    def __call__(self, gains, arm, state, ref, env):
        q, qd = state.q, state.qd
        kin = kinematics(arm, q)
        M, h = dynamics_terms(arm, q, qd, kin)
        J = jacobian_from(kin)[:3]
        eye3 = jnp.eye(3, dtype=J.dtype)
        Jp = J.T @ jnp.linalg.solve(J @ J.T + 1e-4 * eye3, eye3)
        xdd = ref.a + gains.kd * (ref.v - J @ qd) + gains.kp * (ref.p - kin.ee[:3, 3])
        N = jnp.eye(arm.n_dof, dtype=J.dtype) - Jp @ J
        qdd = Jp @ (xdd - jdot_qdot(arm, q, qd)[:3]) - N @ (gains.kn * qd)
        return ControlOutput(tau=M @ qdd + h, dz=(), diag={})


# ----------------------------------------------------------------------------------------------
# the NumPy closed loop


def _skew(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def _ad(V):
    W, Vv = _skew(V[:3]), _skew(V[3:])
    return np.block([[W, np.zeros((3, 3))], [Vv, W]])


class NumpyArm:
    def __init__(self, arm):
        g = lambda x: np.asarray(x, float)
        self.S0, self.home, self.ee_home = g(arm.screw_axes), g(arm.home_frames), g(arm.ee_home)
        self.m, self.com, self.I = g(arm.masses), g(arm.coms), g(arm.inertias)
        self.qmin, self.qmax, self.lim = g(arm.q_min), g(arm.q_max), np.asarray(arm.limited)
        self.widths, self.seg, self.q0, self.grav = g(arm.widths), g(arm.seg_ends), g(arm.q0), g(arm.gravity)
        self.pri = np.asarray(arm.prismatic, bool)
        self.n, self.P = arm.n_dof, arm.points_per_link

    def fk(self, q):
        P = np.eye(4)
        frames, cols = [], []
        for i in range(self.n):
            S = self.S0[i]
            R, p = P[:3, :3], P[:3, 3]
            w = R @ S[:3]
            cols.append(np.concatenate([w, np.cross(p, w) + R @ S[3:]]))
            E = np.eye(4)
            if self.pri[i]:
                E[:3, 3] = S[3:] * q[i]
            else:
                W = _skew(S[:3])
                s, c = np.sin(q[i]), np.cos(q[i])
                E[:3, :3] = np.eye(3) + s * W + (1 - c) * W @ W
                E[:3, 3] = (q[i] * np.eye(3) + (1 - c) * W + (q[i] - s) * W @ W) @ S[3:]
            P = P @ E
            frames.append(P @ self.home[i])
        return np.stack(frames), P @ self.ee_home, np.stack(cols)

    def jac(self, ee, S):
        p = ee[:3, 3]
        return np.vstack([(S[:, 3:] + np.cross(S[:, :3], p)).T, S[:, :3].T])

    def dynamics(self, frames, S, qd):
        R, p = frames[:, :3, :3], frames[:, :3, 3]
        c = np.einsum("nij,nj->ni", R, self.com) + p
        Iw = np.einsum("nij,njk,nlk->nil", R, self.I, R)
        mask = (np.arange(self.n)[None, :] <= np.arange(self.n)[:, None]).astype(float)
        Jw = S[None, :, :3] * mask[:, :, None]
        Jc = (S[None, :, 3:] + np.cross(S[None, :, :3], c[:, None, :])) * mask[:, :, None]
        M = np.einsum("l,lja,lka->jk", self.m, Jc, Jc) + np.einsum("lja,lab,lkb->jk", Jw, Iw, Jw)
        # RNEA with qdd = 0: c + g
        G = []
        for i in range(self.n):
            C = _skew(c[i])
            G.append(np.block([[Iw[i] - self.m[i] * C @ C, self.m[i] * C], [-self.m[i] * C, self.m[i] * np.eye(3)]]))
        V = np.cumsum(S * qd[:, None], axis=0)
        Vp = np.vstack([np.zeros(6), V[:-1]])
        Sdot = np.stack([_ad(Vp[i]) @ S[i] for i in range(self.n)])
        a0 = np.concatenate([np.zeros(3), -self.grav])
        A = a0 + np.cumsum(Sdot * qd[:, None], axis=0)
        F = np.stack([G[i] @ A[i] - _ad(V[i]).T @ (G[i] @ V[i]) for i in range(self.n)])
        Ft = np.cumsum(F[::-1], axis=0)[::-1]
        return 0.5 * (M + M.T), np.sum(S * Ft, axis=1)

    def limit_torque(self, q, qd, kp=1000.0, kd=100.0):
        s = 1.0 - 1.0 / np.sqrt(1.0 + (50.0 * qd) ** 2)
        damp = kd * qd * s
        below = kp * (q - self.qmin) + np.where(qd < 0, damp, 0.0)
        above = kp * (q - self.qmax) + np.where(qd > 0, damp, 0.0)
        tau = np.where(q < self.qmin, below, np.where(q > self.qmax, above, 0.0))
        return np.where(self.lim, tau, 0.0)

    def pois(self, frames, q):
        s = np.arange(1, self.P + 1) / self.P
        R0 = self.home[:, :3, :3]
        axis_local = np.einsum("nji,nj->ni", R0, self.S0[:, 3:])
        start = np.where(self.pri[:, None], -q[:, None] * axis_local, 0.0)
        local = start[:, None, :] + s[None, :, None] * (self.seg - start)[:, None, :]
        world = np.einsum("nij,nkj->nki", frames[:, :3, :3], local) + frames[:, None, :3, 3]
        return world.reshape(-1, 3)


def np_sdf(obs, x):
    """Smallest signed distance of the points ``x`` (m, 3) to the obstacles (NumPy)."""
    out = [np.full(len(x), 1e3)]
    for fam, kind in ((obs.spheres, 0), (obs.boxes, 1), (obs.cylinders, 2)):
        R, p, d, mk = (np.asarray(a) for a in (fam.R, fam.p, fam.dims, fam.mask))
        for k in np.nonzero(mk)[0]:
            xl = (x - p[k]) @ R[k]
            if kind == 0:
                out.append(np.linalg.norm(xl, axis=1) - d[k, 0])
            else:
                u = (np.abs(xl) - d[k]) if kind == 1 else np.stack(
                    [np.linalg.norm(xl[:, :2], axis=1) - d[k, 0], np.abs(xl[:, 2]) - d[k, 1]], axis=1)
                out.append(np.linalg.norm(np.maximum(u, 0), axis=1) + np.minimum(u.max(axis=1), 0))
    return np.min(np.stack(out), axis=0)


def numpy_run(na: NumpyArm, sc, rtol, atol, method="DOP853", kp=250.0, kd=31.0, kn=10.0):
    ref = sc.reference
    P, Vd, A = np.asarray(ref.p), np.asarray(ref.v), np.asarray(ref.a)
    ts, ns = float(ref.ts), int(ref.n_samples)
    n = na.n
    thr = np.repeat(na.widths, na.P)
    nfev = [0]

    def f(t, y, k):
        nfev[0] += 1
        q, qd = y[:n], y[n:2 * n]
        frames, ee, S = na.fk(q)
        J = na.jac(ee, S)[:3]
        h = 1e-6
        Jp_ = na.jac(*na.fk(q + h * qd)[1:])[:3]
        Jm_ = na.jac(*na.fk(q - h * qd)[1:])[:3]
        jdqd = (Jp_ - Jm_) / (2 * h) @ qd
        M, hb = na.dynamics(frames, S, qd)
        Jpinv = J.T @ np.linalg.inv(J @ J.T + 1e-4 * np.eye(3))
        xdd = A[k] + kd * (Vd[k] - J @ qd) + kp * (P[k] - ee[:3, 3])
        qdd_r = Jpinv @ (xdd - jdqd) - (np.eye(n) - Jpinv @ J) @ (kn * qd)
        tau = M @ qdd_r + hb
        qdd = np.linalg.solve(M, tau - hb - na.limit_torque(q, qd))
        dmin = np_sdf(sc.obstacles, na.pois(frames, q))
        outside = np.any(na.lim & ((q < na.qmin) | (q > na.qmax)))
        return np.concatenate([qd, qdd, [float(np.any(dmin < thr)), float(outside)]])

    y = np.concatenate([na.q0, np.zeros(n), [0.0, 0.0]])
    ys = []
    for k in range(ns):
        sol = solve_ivp(f, (k * ts, (k + 1) * ts), y, method=method, rtol=rtol, atol=atol, args=(k,))
        y = sol.y[:, -1]
        ys.append(y)
    return np.stack(ys), nfev[0]


# ----------------------------------------------------------------------------------------------


def _block(x):
    return jax.block_until_ready(x)


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

        def __call__(self, g, a, s, r, e):
            jax.debug.callback(lambda: counter.__setitem__(0, counter[0] + 1))
            return self.inner(g, a, s, r, e)

    r = _block(simulate(arm, sc, Counting(ctrl), gains, ik=ik, params=params))
    return counter[0], int(r.n_steps), int(r.n_rejected)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", default="welding")
    ap.add_argument("--dof", type=int, default=9)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--scipy-seeds", type=int, default=2)
    ap.add_argument("--method", default="DOP853")
    ap.add_argument("--real", action="store_true", help="also time the real controllers")
    args = ap.parse_args()
    print(f"jax {jax.__version__}, devices {jax.devices()}, {platform.processor() or platform.machine()}")
    arm = thesis_arm(args.dof)
    from redman_jax._cases import make_scenarios

    t0 = time.perf_counter()
    scs = make_scenarios(args.case, range(1, args.seeds + 1), arm)
    print(f"{args.seeds} {args.case} scenarios in {time.perf_counter() - t0:.1f} s; "
          f"n_samples {np.asarray(scs.reference.n_samples).tolist()}")
    T_sim = float(np.sum(np.asarray(scs.reference.n_samples)) * float(scs.reference.ts[0]))
    params = SimParams()
    ctrl, gains = OSCPD(), OSCPD().default_gains()

    t0 = time.perf_counter()
    res = _block(simulate_batch(arm, scs, ctrl, gains, params=params))
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = _block(simulate_batch(arm, scs, ctrl, gains, params=params))
    warm = time.perf_counter() - t0
    steps, rej = np.asarray(res.n_steps), np.asarray(res.n_rejected)
    one = jax.tree.map(lambda x: x[0], scs)
    nfev, st, rj = count_evals(arm, one, ctrl, gains, params)
    print(f"\n[JAX OSC-PD, {args.seeds} seeds, Tsit5 rtol 1e-5 atol 1e-7] simulated {T_sim:.2f} s")
    print(f"  cold {cold:.2f} s -> {T_sim / cold:.2f} sim-s/wall-s ; warm {warm:.3f} s -> {T_sim / warm:.1f} sim-s/wall-s")
    print(f"  steps/trajectory mean {steps.mean():.0f} (max {steps.max()}), rejected mean {rej.mean():.1f}; "
          f"seed 1: {nfev} vector-field evaluations for {int(one.reference.n_samples)} samples "
          f"({st} steps, {rj} rejected)")
    print(f"  collided {np.asarray(res.metrics.collided).sum()}, success {np.asarray(res.success).sum()}, "
          f"diverged {np.asarray(res.diverged).sum()}")

    # tolerance study: the study's metrics at rtol 1e-5 against rtol 1e-9
    ref_params = SimParams(rtol=1e-9, atol=1e-11)
    tight = _block(simulate_batch(arm, scs, ctrl, gains, params=ref_params))
    for name in ("mean_pos_err", "mean_ori_err", "final_pos_err"):
        a, b = np.asarray(getattr(res.metrics, name)), np.asarray(getattr(tight.metrics, name))
        ok = np.isfinite(b)
        rel = np.abs(a[ok] - b[ok]) / np.abs(b[ok])
        print(f"  tolerance study {name}: max rel. diff {rel.max():.2e} (pooled mean rel. diff "
              f"{abs(a[ok].mean() - b[ok].mean()) / b[ok].mean():.2e})")
    same = np.all(np.asarray(res.metrics.success) == np.asarray(tight.metrics.success))
    same &= np.all(np.asarray(res.metrics.collided) == np.asarray(tight.metrics.collided))
    print(f"  same success/collision verdicts: {bool(same)}; steps at 1e-9: {np.asarray(tight.n_steps).mean():.0f}")

    # SciPy baseline, one seed at a time
    na = NumpyArm(arm)
    t_np, fe = 0.0, []
    for i in range(args.scipy_seeds):
        sc = jax.tree.map(lambda x: x[i], scs)
        t0 = time.perf_counter()
        ys, nf = numpy_run(na, sc, 1e-5, 1e-7, method=args.method)
        t_np += time.perf_counter() - t0
        fe.append(nf)
        q_jax = np.asarray(res.q[i, : int(sc.reference.n_samples)])
        print(f"  scipy seed {i + 1}: {nf} evaluations, max |q_numpy - q_jax| = {np.abs(ys[:, :arm.n_dof] - q_jax).max():.1e}")
    per_seed = t_np / args.scipy_seeds
    T_np = T_sim / args.seeds
    print(f"\n[NumPy + SciPy solve_ivp {args.method}, per sample, one seed at a time] "
          f"{per_seed:.1f} s per seed -> {T_np / per_seed:.3f} sim-s/wall-s "
          f"(mean of {args.scipy_seeds} seeds, {np.mean(fe):.0f} evaluations/trajectory)")
    print(f"  speed-up for {args.seeds} seeds: warm {per_seed * args.seeds / warm:.0f}x, cold (incl. compile) "
          f"{per_seed * args.seeds / cold:.0f}x")

    if args.real:
        from redman_jax import _controllers as C

        for name in ("acceleration", "velocity"):
            c = C.CONTROLLERS[name]()
            g = c.default_gains()
            t0 = time.perf_counter()
            r = _block(simulate_batch(arm, scs, c, g, params=params))
            cold = time.perf_counter() - t0
            t0 = time.perf_counter()
            r = _block(simulate_batch(arm, scs, c, g, params=params))
            warm = time.perf_counter() - t0
            nfev, st, rj = count_evals(arm, one, c, g, params)
            print(f"[JAX {name} OSC] cold {cold:.1f} s, warm {warm:.2f} s -> {T_sim / warm:.1f} sim-s/wall-s; "
                  f"steps mean {np.asarray(r.n_steps).mean():.0f}, rejected {np.asarray(r.n_rejected).mean():.1f}; "
                  f"seed 1 {nfev} evaluations; success {np.asarray(r.success).sum()}/{args.seeds}")


if __name__ == "__main__":
    main()
