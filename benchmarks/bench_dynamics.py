"""Speed of kinematics and dynamics: redman-jax (jit(vmap)) against Pinocchio's Python bindings.

For the thesis 9-DOF arm and the Franka Panda (example-robot-data, fingers dropped, tip
``panda_hand``) it prints the time per state of forward kinematics, the end-effector Jacobian, the
mass matrix, the bias forces and the forward dynamics at batch sizes 1, 20, 1024 and 16384
(``jax.jit(jax.vmap(f))``, arm passed as an argument, warm-up, ``block_until_ready``, median of
repeats), the compile times apart, and Pinocchio's time per call from Python on the same arm and
states (``forwardKinematics``, ``computeFrameJacobian`` (LOCAL_WORLD_ALIGNED), ``crba``,
``nonLinearEffects``, ``aba``). Pinocchio gets the 9-DOF arm through ``to_urdf``.

The target figure is the last block: forward dynamics at batch 1024 and ``pin.aba`` timed back to back
in 15 rounds, with the median, range and count of the per-round ratios (the machine's speed drifts;
neighbouring measurements give the ratio that holds).

"before" rows time the hot path as first written (same kinematics, CoM-form mass matrix, RNEA
with 6x6 ``ad`` matrices, LAPACK Cholesky) and the Lagrangian formulation, in the same run.

Run: ``nice .venv/bin/python benchmarks/bench_dynamics.py`` (a few minutes; ``--quick`` for a
smoke run).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import numpy as np

import redman_jax  # noqa: F401  (float64)
from redman_jax._dynamics import (
    _forward_dynamics_lapack,
    _mass_matrix_com,
    _rnea_spatial6,
    bias_forces,
    bias_forces_lagrange,
    forward_dynamics,
    mass_matrix,
    mass_matrix_lagrange,
)
from redman_jax._kinematics import forward_kinematics, jacobian, kinematics
from redman_jax._report import _cpu_model  # the CPU's model name, as the study report's machine row gives it
from redman_jax._robot import thesis_arm
from redman_jax._urdf import example_robot_data_file, from_urdf, to_urdf


def fd_before(arm, q, qd, tau):
    """The hot path as first written: CoM-form M, 6x6 RNEA, LAPACK Cholesky."""
    from jax.scipy.linalg import cho_factor, cho_solve

    kin = kinematics(arm, q)
    M = _mass_matrix_com(arm, kin)
    h = _rnea_spatial6(arm, q, qd, jnp.zeros_like(qd), kin=kin)
    return cho_solve(cho_factor(M, lower=True), tau - h)


def fd_lagrange(arm, q, qd, tau):
    M = mass_matrix_lagrange(arm, q)
    return jnp.linalg.solve(M, tau - bias_forces_lagrange(arm, q, qd))


OURS = {
    "fk": (lambda a, q, qd, t: forward_kinematics(a, q)),
    "jacobian": (lambda a, q, qd, t: jacobian(a, q)),
    "mass_matrix": (lambda a, q, qd, t: mass_matrix(a, q)),
    "bias_forces": (lambda a, q, qd, t: bias_forces(a, q, qd)),
    "forward_dyn": (lambda a, q, qd, t: forward_dynamics(a, q, qd, t, limits=False)),
    "fd before": fd_before,
    "fd lapack chol": (lambda a, q, qd, t: _forward_dynamics_lapack(a, q, qd, t, limits=False)),
    "fd lagrange": fd_lagrange,
}
PIN_OF = {"fk": "fk", "jacobian": "jacobian", "mass_matrix": "mass_matrix", "bias_forces": "bias_forces",
          "forward_dyn": "forward_dyn", "fd before": "forward_dyn", "fd lapack chol": "forward_dyn",
          "fd lagrange": "forward_dyn"}


def panda():
    path = os.environ.get("PANDA_URDF") or example_robot_data_file("panda_description/urdf/panda.urdf")
    arm = from_urdf(path, tip_link="panda_hand")
    root = ET.parse(path).getroot()
    for el in list(root):  # the same chain for Pinocchio: drop the finger branches
        if el.tag in ("link", "joint") and "finger" in el.get("name", ""):
            root.remove(el)
    return arm, ET.tostring(root, encoding="unicode"), "panda_hand"


def thesis9():
    arm = thesis_arm(9)
    return arm, to_urdf(arm, tip_link="ee"), "ee"


def random_states(arm, B, rng):
    lo = np.where(np.asarray(arm.limited), np.asarray(arm.q_min), -np.pi)
    hi = np.where(np.asarray(arm.limited), np.asarray(arm.q_max), np.pi)
    q = rng.uniform(lo, hi, (B, arm.n_dof))
    return q, rng.normal(size=(B, arm.n_dof)), rng.normal(size=(B, arm.n_dof))


def time_call(fn, min_time, min_rep=5, max_rep=200, warmup=3):
    """(median, min) seconds per call after ``warmup`` untimed calls (the first calls after a
    compile pay for fresh output buffers: up to 40 % slower at batch 1024)."""
    for _ in range(warmup):
        jax.block_until_ready(fn())
    ts = []
    start = time.perf_counter()
    while len(ts) < min_rep or (time.perf_counter() - start < min_time and len(ts) < max_rep):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), min(ts)


def paired_ratios(ours, B, pin_call, qp, vs, taus, rounds=15):
    """Per-round ratios (ours per state / pin.aba per call), the two timed back to back in each
    round (one loop of ``pin_call`` over the states, then the median of 5 calls of ours): on a
    shared machine whose speed drifts by tens of percent within a minute, the ratio of
    neighbouring measurements is the figure that holds."""
    for _ in range(3):
        jax.block_until_ready(ours())
    out = []
    for _ in range(rounds):
        p, _ = pinocchio_time(pin_call, qp, vs, taus, reps=1)
        t, _ = time_call(ours, 0.0, min_rep=5, max_rep=5, warmup=0)
        out.append(t / B / p)
    return out


def pinocchio_setup(xml, tip, qs):
    """Pinocchio model, data, per-function calls and the states in Pinocchio's coordinates."""
    import pinocchio as pin

    model = pin.buildModelFromXML(xml)
    data = model.createData()
    fid = model.getFrameId(tip)
    qp = []
    for q in qs:  # continuous joints are (cos, sin) in Pinocchio
        parts = [np.array([np.cos(x), np.sin(x)]) if model.joints[j + 1].nq == 2 else np.array([x])
                 for j, x in enumerate(q)]
        qp.append(np.concatenate(parts))
    LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    calls = {
        "fk": lambda q, v, t: pin.forwardKinematics(model, data, q),
        "jacobian": lambda q, v, t: pin.computeFrameJacobian(model, data, q, fid, LWA),
        "mass_matrix": lambda q, v, t: pin.crba(model, data, q),
        "bias_forces": lambda q, v, t: pin.nonLinearEffects(model, data, q, v),
        "forward_dyn": lambda q, v, t: pin.aba(model, data, q, v, t),
    }
    return model, data, calls, qp


def pinocchio_time(f, qp, vs, taus, reps=7):
    """(median, min) over ``reps`` loops of the time per call from Python."""
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        for q, v, t in zip(qp, vs, taus):
            f(q, v, t)
        out.append((time.perf_counter() - t0) / len(qp))
    return statistics.median(out), min(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="batches 1 and 1024, short timings")
    ap.add_argument("--pin-us", default=None,
                    help="no Pinocchio in this environment (e.g. a GPU machine): print ours only and "
                         "compare forward dynamics with these aba times per call, 'thesis,panda' in us")
    args = ap.parse_args()
    batches = [1, 1024] if args.quick else [1, 20, 1024, 16384]
    min_time = 0.05 if args.quick else 0.3

    if args.pin_us is None:
        import pinocchio as pin
    else:
        pin = None
        given = dict(zip(("thesis 9-DOF", "Panda 7-DOF"), (float(x) * 1e-6 for x in args.pin_us.split(","))))

    print("redman-jax dynamics benchmark")
    print(f"python {platform.python_version()}, jax {jax.__version__}, jaxlib {jax.lib.__version__ if hasattr(jax.lib, '__version__') else ''}"
          f", numpy {np.__version__}, pinocchio {pin.__version__ if pin else 'absent (given: ' + args.pin_us + ' us)'}")
    print(f"device {jax.devices()[0]} ({jax.devices()[0].device_kind}), {os.cpu_count()} CPUs visible, "
          f"{_cpu_model()}, x64={jax.config.jax_enable_x64}")
    print("times per state [us]; ours = jit(vmap(f)) with the arm as an argument; pin = per call from Python,")
    print("looped over 500 states, timed right before ours; median and min of repeats (min resists load)\n")

    rng = np.random.default_rng(0)
    summary, paired = [], []
    for label, make in (("thesis 9-DOF", thesis9), ("Panda 7-DOF", panda)):
        arm, xml, tip = make()
        qs, vs, ts = random_states(arm, max(batches), rng)
        n_pin = 500
        if pin is not None:
            model, data, calls, qp = pinocchio_setup(xml, tip, qs[:n_pin])
            # agreement with Pinocchio on one state (a sanity check of the comparison itself)
            ddq = np.asarray(forward_dynamics(arm, qs[0], vs[0], ts[0], limits=False))
            ddq_pin = pin.aba(model, data, qp[0], vs[0], ts[0])  # same states in Pinocchio's coordinates
            print(f"== {label} (n = {arm.n_dof}); |ddq - pin.aba| / |pin.aba| = "
                  f"{np.linalg.norm(ddq - ddq_pin) / np.linalg.norm(ddq_pin):.1e}")
        else:
            print(f"== {label} (n = {arm.n_dof}); Pinocchio aba given: {given[label] * 1e6:.3f} us per call")
        print(f"{'function':<16}{'batch':>7}{'compile [s]':>13}{'ours med':>10}{'pin med':>9}{'ratio':>7}"
              f"{'ours min':>10}{'pin min':>9}{'ratio':>7}")
        for name, f in OURS.items():
            if name in ("fd lagrange",) and args.quick:
                continue
            g = jax.jit(jax.vmap(f, in_axes=(None, 0, 0, 0)))
            for B in batches:
                if name == "fd lagrange" and B > 1024:
                    continue
                q, qd, tau = (jnp.asarray(x[:B]) for x in (qs, vs, ts))
                t0 = time.perf_counter()
                compiled = g.lower(arm, q, qd, tau).compile()
                t_comp = time.perf_counter() - t0
                jax.block_until_ready(compiled(arm, q, qd, tau))  # warm-up
                # Pinocchio timed right before ours, so both see the same machine load
                if pin is not None:
                    p, p_min = pinocchio_time(calls[PIN_OF[name]], qp, vs[:n_pin], ts[:n_pin])
                else:
                    p = p_min = given[label] if PIN_OF[name] == "forward_dyn" else float("nan")
                t, t_min = (x / B for x in time_call(lambda: compiled(arm, q, qd, tau), min_time))
                print(f"{name:<16}{B:>7}{t_comp:>13.2f}{t * 1e6:>10.3f}{p * 1e6:>9.3f}{t / p:>7.2f}"
                      f"{t_min * 1e6:>10.3f}{p_min * 1e6:>9.3f}{t_min / p_min:>7.2f}")
                if B == 1024 and name in ("forward_dyn", "fd before", "fd lapack chol"):
                    summary.append((label, name, t, p, t_min, p_min, t_comp))
                if B == 1024 and name == "forward_dyn" and pin is not None:
                    paired.append((label, paired_ratios(lambda: compiled(arm, q, qd, tau), B,
                                                        calls["forward_dyn"], qp, vs[:n_pin], ts[:n_pin])))
        print()
    print("summary at batch 1024 (target: forward dynamics per state <= Pinocchio aba per call):")
    for label, name, t, p, t_min, p_min, tc in summary:
        print(f"  {label:<14}{name:<15} median: ours {t * 1e6:7.3f} us, pin.aba {p * 1e6:7.3f} us, "
              f"ratio {t / p:5.2f} | min: ratio {t_min / p_min:5.2f} | compile {tc:5.2f} s")
    if paired:
        print("paired rounds at batch 1024 (pin.aba over 500 states, then 5 calls of ours, 15 times):")
    for label, r in paired:
        print(f"  {label:<14}forward_dyn / pin.aba: median {statistics.median(r):5.2f}, "
              f"min {min(r):5.2f}, max {max(r):5.2f}; rounds <= 1: {sum(x <= 1 for x in r)}/{len(r)}")


if __name__ == "__main__":
    main()
