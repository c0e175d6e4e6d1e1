"""Case generators (SPEC section 4): every rule over many seeds, determinism, batching, errors, plots.

Rule checks use independent references: the JAX sdf of ``_obstacles`` (not the host copy the
generators use), plain geometry recomputed from the obstacle poses, and the arm's own POIs.
Many-seed checks run on the host (geometry only); one small test plans two RRT scenes.
"""

import collections
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import redman_jax
from redman_jax._cases import (
    AgricultureParams,
    CaseParams,
    InspectionParams,
    SimpleParams,
    WarehouseParams,
    _arm_info,
    _draw,
    _draw_fourth_sphere,
    _GENERATORS,
    _Reject,
    _q0_geometry,
    host_distances,
    make_scenario,
    make_scenarios,
    make_valid_scenario,
    obstacle_capacities,
    reach_ok,
)
from redman_jax._obstacles import make_obstacles, obstacle_distances
from redman_jax._scenario import CASES
from redman_jax._trajectories import rot_from_quat

PRM = CaseParams()
TOL = 1e-9  # [m] rules that hold with equality (0.12 m slot clearance) up to round-off
SEEDS = range(1, 31)


@pytest.fixture(scope="module")
def arms():
    return {d: redman_jax.thesis_arm(d) for d in (7, 9)}


@pytest.fixture(scope="module")
def geometric(arms):
    """40 scenarios of each geometric case for the 7- and 9-DOF arms."""
    return {(c, d): make_scenarios(c, SEEDS, arms[d]) for c in ("warehouse", "inspection", "welding")
            for d in (7, 9)}


def _one(batch, i):
    return jax.tree.map(lambda x: x[i], batch)


_dist = jax.jit(jax.vmap(jax.vmap(obstacle_distances, in_axes=(None, 0)), in_axes=(0, 0)))


def _clearances(batch, pts):
    """Least signed distance (JAX sdf) of points ``(B, m, 3)`` to each scene's obstacles."""
    return np.asarray(_dist(batch.obstacles, jnp.asarray(pts))).min(-1)


def _check_common(batch, arm, case):
    B = batch.goal_p.shape[0]
    assert bool(np.all(np.asarray(batch.valid)))
    ref = batch.reference
    n = np.asarray(ref.n_samples)
    p, v, a = np.asarray(ref.p), np.asarray(ref.v), np.asarray(ref.a)
    p0, q0, pois, _ = (np.asarray(x) for x in _q0_geometry(arm))  # jitted FK at q0 (the arm's own)
    np.testing.assert_allclose(p[:, 0], np.broadcast_to(p0, (B, 3)), atol=1e-12)  # start pose
    assert np.all(v[:, 0] == 0)
    for b in range(B):
        k = n[b]
        assert np.all(v[b, k - 1 :] == 0) and np.all(a[b, k - 1 :] == 0)  # ends (and pads) at rest
        np.testing.assert_allclose(p[b, k - 1], np.asarray(batch.goal_p[b]), atol=1e-12)
    speed = np.linalg.norm(v, axis=-1)
    acc = np.linalg.norm(a, axis=-1)
    assert speed.max() <= PRM.v_max + TOL
    # the welding circle adds the centripetal v^2/r <= 0.1^2/0.16 to the 2 m/s^2 ramps
    assert acc.max() <= math.hypot(PRM.a_max, 0.1**2 / 0.16) + TOL
    rot = np.asarray(ref.rot)
    assert np.all(np.diff(rot, axis=1) >= 0)  # latched
    # start protection against the arm's own q0 points of interest (JAX sdf)
    d = _clearances(batch, np.broadcast_to(pois, (B,) + pois.shape))
    assert d.min() >= PRM.start_clearance - TOL
    # geometric EE path clearance, on every valid sample
    dp = _clearances(batch, p)
    dp = np.where(np.asarray(ref.mask), dp, np.inf)
    assert dp.min() >= PRM.geometric_clearance - TOL
    # reach rule on every oriented sample
    L_h = _arm_info(arm).L_h
    on = rot > 0
    assert np.all(reach_ok(p[on], np.asarray(ref.quat)[on], L_h))
    # quaternion continuity along the valid samples
    qt = np.asarray(ref.quat)
    dots = np.sum(qt[:, 1:] * qt[:, :-1], -1)
    assert dots.min() > math.cos(0.2 / 2)
    assert batch.case == case


@pytest.mark.parametrize("dof", [7, 9])
@pytest.mark.parametrize("case", ["warehouse", "inspection", "welding"])
def test_geometric_cases_common_rules(geometric, arms, case, dof):
    _check_common(geometric[(case, dof)], arms[dof], case)


def test_warehouse_rules(geometric):
    P = PRM.warehouse
    for dof in (7, 9):
        batch = geometric[("warehouse", dof)]
        for i in range(batch.goal_p.shape[0]):
            sc = _one(batch, i)
            m = np.asarray(sc.obstacles.boxes.mask)
            dims = np.asarray(sc.obstacles.boxes.dims)[m]
            cent = np.asarray(sc.obstacles.boxes.p)[m]
            is_box = np.all(np.isclose(dims, P.box_size / 2), axis=1)
            assert (~is_box).sum() == 2 * (len(P.plank_tops) + P.n_segments + 2)  # shelf parts
            boxes = cent[is_box]
            g = np.asarray(sc.goal_p)
            for side in (1, -1):
                for lev in range(P.n_levels):
                    for j in range(P.n_segments):
                        xc = -P.pitch * P.n_segments / 2 + P.pitch * (j + 0.5)
                        inside = ((np.sign(boxes[:, 1]) == side) & (np.abs(boxes[:, 0] - xc) < P.pitch / 2)
                                  & (boxes[:, 2] > P.plank_tops[lev]) & (boxes[:, 2] < P.plank_tops[lev + 1]))
                        comp = boxes[inside]
                        assert len(comp) <= P.max_boxes
                        top = comp[:, 2] > P.plank_tops[lev] + 0.24
                        assert np.all(comp[:, 2] - P.plank_tops[lev] < 0.37)  # at most 2 high
                        for b in comp[top]:  # a top box stands on a box
                            below = b - np.array([0, 0, 0.24])
                            assert np.min(np.linalg.norm(comp - below, axis=1)) < 1e-9
            # goal: an empty front-row slot that could hold a box, within reach radius
            assert np.min(np.linalg.norm(boxes - g, axis=1)) > 0.2
            assert abs(abs(g[1]) - (P.front + P.slot_depth[0])) < 1e-9
            assert math.hypot(g[0], g[1]) <= P.goal_max_radius + 1e-9
            h = g[2] - np.array(P.plank_tops)
            lev_h = h[(h > 0) & (h < 0.5)].min()
            if abs(lev_h - P.slot_height[1]) < 1e-9:
                below = g - np.array([0, 0, 0.24])
                assert np.min(np.linalg.norm(boxes - below, axis=1)) < 1e-9
            else:
                assert abs(lev_h - P.slot_height[0]) < 1e-9
            # orientation: tool axis along the inward normal; off on segment 1, on for segment 2
            a = rot_from_quat(np.asarray(sc.goal_quat))[:, 2]
            np.testing.assert_allclose(a, [0, np.sign(g[1]), 0], atol=1e-12)
            n = int(sc.reference.n_samples)
            p = np.asarray(sc.reference.p)[:n]
            rot = np.asarray(sc.reference.rot)[:n]
            approach = g - 0.25 * a
            j = np.nonzero(np.linalg.norm(p - approach, axis=1) < 1e-12)[0]
            assert len(j) == 1 and rot[j[0] - 1] == 0 and np.all(rot[j[0] :] == 1)


def test_inspection_rules(geometric):
    P = PRM.inspection
    for dof in (7, 9):
        batch = geometric[("inspection", dof)]
        for i in range(batch.goal_p.shape[0]):
            sc = _one(batch, i)
            boxes = sc.obstacles.boxes
            assert int(np.asarray(boxes.mask).sum()) == 5 and int(np.asarray(sc.obstacles.cylinders.mask).sum()) == 1
            R = np.asarray(boxes.R)[0]
            u, w = R[:, 0], R[:, 1]  # room depth and lateral axes
            c = np.asarray(sc.obstacles.cylinders.p)[0]
            r, hh = np.asarray(sc.obstacles.cylinders.dims)[0, :2]
            depth, lat = c @ u - P.opening_distance, c @ w
            assert P.cyl_radius[0] <= r <= P.cyl_radius[1]
            assert P.cyl_depth[0] - TOL <= depth <= P.cyl_depth[1] + TOL
            assert P.cyl_lateral[0] - TOL <= abs(lat) <= P.cyl_lateral[1] + TOL
            assert abs(2 * hh - P.room_height) < 1e-12 and abs(c[2] - (P.floor_z + P.room_height / 2)) < 1e-12
            # the scan: the last legs lie in the plane 0.12 m from the back wall, on the larger-gap
            # side, at a constant orientation with the tool axis toward the back wall
            n = int(sc.reference.n_samples)
            p = np.asarray(sc.reference.p)[:n]
            q = np.asarray(sc.reference.quat)[:n]
            rot = np.asarray(sc.reference.rot)[:n]
            scan_d = P.opening_distance + P.room_depth - P.scan_back
            on_plane = np.abs(p @ u - scan_d) < 1e-9
            k0 = np.nonzero(on_plane)[0][0]
            assert np.all(on_plane[k0:])
            np.testing.assert_allclose(rot_from_quat(q[k0:])[:, :, 2], np.broadcast_to(u, (n - k0, 3)), atol=1e-12)
            s_lat = p[k0:] @ w
            assert np.all(np.sign(s_lat) == -np.sign(lat))
            assert np.all(-np.sign(lat) * s_lat >= -(abs(lat) - r) + P.band_cyl_margin - TOL)
            assert np.all(np.abs(s_lat) <= P.room_width / 2 - P.band_wall_margin + TOL)
            zs = np.unique(np.round(p[k0:, 2], 9))
            assert set(np.round(P.scan_rows, 9)) <= set(zs)
            # orientation on exactly from 0.20 m of the scan pattern
            first = np.nonzero(rot)[0][0]
            scan = p[k0:]
            dist = np.min(np.linalg.norm(p[:, None] - scan[None], axis=-1), axis=1)
            assert dist[first] <= P.rot_radius + 0.01 and np.all(dist[:first] > P.rot_radius - 0.01)


def test_welding_rules(geometric):
    P = PRM.welding
    for dof in (7, 9):
        batch = geometric[("welding", dof)]
        for i in range(batch.goal_p.shape[0]):
            sc = _one(batch, i)
            Rp = np.asarray(sc.obstacles.boxes.R)[0]
            cp = np.asarray(sc.obstacles.boxes.p)[0]
            nrm = Rp[:, 2]
            rho = math.hypot(cp[0], cp[1])
            assert P.plate_radius[0] - TOL <= rho <= P.plate_radius[1] + TOL
            assert P.plate_z[0] - TOL <= cp[2] <= P.plate_z[1] + TOL
            e_rho = np.array([cp[0], cp[1], 0]) / rho
            eps = math.atan2(nrm[2], -(nrm @ e_rho))
            assert -TOL <= eps <= P.plate_tilt[1] + TOL  # faces the robot, tilted up by <= 30 deg
            np.testing.assert_allclose(np.asarray(sc.obstacles.boxes.dims)[0], [0.25, 0.25, 0.01])
            cc = np.asarray(sc.obstacles.cylinders.p)[0]
            rc, hc = np.asarray(sc.obstacles.cylinders.dims)[0, :2]
            surf = cp + 0.01 * nrm
            np.testing.assert_allclose(cc, surf + hc * nrm, atol=1e-12)  # on the plate centre along n
            assert P.cyl_radius[0] <= rc <= P.cyl_radius[1] and P.cyl_height[0] <= 2 * hc <= P.cyl_height[1]
            # the circle: radius rc + 0.12 about the cylinder axis, 0.12 above the plate, constant speed
            n = int(sc.reference.n_samples)
            p = np.asarray(sc.reference.p)[:n]
            v = np.asarray(sc.reference.v)[:n]
            q = np.asarray(sc.reference.quat)[:n]
            rel = p - surf
            height = rel @ nrm
            radial = np.linalg.norm(rel - height[:, None] * nrm, axis=1)
            on = (np.abs(height - 0.12) < 1e-9) & (np.abs(radial - (rc + 0.12)) < 1e-9)
            k0 = np.nonzero(on)[0][0]
            assert np.all(on[k0:])
            arc = np.linalg.norm(np.diff(p[k0:], axis=0), axis=1).sum()
            assert arc == pytest.approx(2 * math.pi * (rc + 0.12), rel=1e-4)
            speed = np.linalg.norm(v[k0:], axis=1)
            assert np.sum(np.abs(speed - 0.10) < 1e-12) > 0.95 * (n - k0)
            # the tool axis points into the seam: p + 0.12 sqrt(2) a lies on the seam circle
            a = rot_from_quat(q[k0:])[:, :, 2]
            hit = p[k0:] + 0.12 * math.sqrt(2) * a - surf
            np.testing.assert_allclose(hit @ nrm, 0, atol=1e-9)
            np.testing.assert_allclose(np.linalg.norm(hit, axis=1), rc, atol=1e-9)
            assert np.all(np.asarray(sc.reference.rot)[:n] == 1)


def _host_scenes(case, dof, seeds):
    arm = redman_jax.thesis_arm(dof)
    info = _arm_info(arm)
    out = []
    for s in seeds:
        drawn = _draw(_GENERATORS[case], s, info, PRM, PRM.case(case).capacity, collections.Counter())
        assert drawn is not None
        out.append(drawn[0])
    return info, out


def _start_ok(sc, info):
    d = host_distances(sc.spheres, sc.boxes, sc.cylinders, info.column).min(1)
    low = info.column[:, 2] <= PRM.base_clearance_z
    return d.min() >= PRM.start_clearance - TOL and d[low].min() >= PRM.base_clearance - TOL


@pytest.mark.parametrize("dof", [7, 9])
def test_agriculture_rules_many_seeds(dof):
    P = PRM.agriculture
    info, scenes = _host_scenes("agriculture", dof, range(1, 61))
    for sc in scenes:
        assert len(sc.cylinders) == 21
        R = np.stack([c[0] for c in sc.cylinders])
        dims = np.stack([c[2] for c in sc.cylinders])
        ctr = np.stack([c[1] for c in sc.cylinders])
        d = R[:, :, 2]
        base = ctr - dims[:, 1:2] * d
        tip = ctr + dims[:, 1:2] * d
        for t in range(3):  # per tree: trunk, 2 children, 4 grandchildren
            k = 7 * t
            assert abs(base[k, 2]) < 1e-12 and P.root_radius[0] - TOL <= np.hypot(*base[k, :2]) <= P.root_radius[1] + TOL
            assert math.acos(min(1.0, d[k, 2])) <= P.trunk_tilt_max + 1e-9
            assert abs(dims[k, 0] - 0.025) < 1e-15
            parent = {k + 1: k, k + 2: k, k + 3: k + 1, k + 4: k + 1, k + 5: k + 2, k + 6: k + 2}
            for c, pa in parent.items():
                np.testing.assert_allclose(base[c], tip[pa], atol=1e-12)  # grows from the parent's end
                tilt = math.acos(np.clip(d[c] @ d[pa], -1, 1))
                assert P.branch_tilt[0] - 1e-9 <= tilt <= P.branch_tilt[1] + 1e-9
                assert d[c, 2] >= P.branch_min_dir_z - 1e-12
                ratio = dims[c, 1] / dims[pa, 1]
                assert P.branch_length_factor[0] - 1e-9 <= ratio <= P.branch_length_factor[1] + 1e-9
                assert dims[c, 0] == pytest.approx(0.7 * dims[pa, 0])
        g = sc.goal_p
        assert host_distances([], [], sc.cylinders, g[None]).min() >= PRM.goal_clearance
        assert P.goal_radius[0] <= math.hypot(g[0], g[1]) <= P.goal_radius[1] and P.goal_z[0] <= g[2] <= P.goal_z[1]
        a = rot_from_quat(sc.goal_quat)[:, 2]
        e_rho = np.array([g[0], g[1], 0]) / math.hypot(g[0], g[1])
        pitch = math.asin(a[2])
        assert abs(pitch) <= 30 * math.pi / 180 + 1e-9
        np.testing.assert_allclose(a[:2] / np.linalg.norm(a[:2]), e_rho[:2], atol=1e-9)  # radial
        assert _start_ok(sc, info) and reach_ok(g, sc.goal_quat, info.L_h)


@pytest.mark.parametrize("dof", [7, 9])
def test_simple_rules_many_seeds(dof):
    P = PRM.simple
    info, scenes = _host_scenes("simple", dof, range(1, 61))
    x0 = info.start_p
    for sc in scenes:
        g = sc.goal_p
        assert len(sc.spheres) == 4
        c = np.stack([s[1] for s in sc.spheres])
        r = np.array([s[2][0] for s in sc.spheres])
        assert np.all(r == P.sphere_radius)
        assert P.goal_radius[0] <= math.hypot(g[0], g[1]) <= P.goal_radius[1] and P.goal_z[0] <= g[2] <= P.goal_z[1]
        assert P.goal_distance[0] <= np.linalg.norm(g - np.array(PRM.sizing_start)) <= P.goal_distance[1]
        tri = c[:3]
        m = 0.5 * (x0 + g)
        u = (g - x0) / np.linalg.norm(g - x0)
        np.testing.assert_allclose(tri.mean(0), m, atol=1e-12)  # exactly midway
        np.testing.assert_allclose((tri - m) @ u, 0, atol=1e-12)  # in the perpendicular plane
        np.testing.assert_allclose(np.linalg.norm(tri - m, axis=1), P.circumradius, atol=1e-12)
        # impassable: brute force over the triangle's interior, the best clearance is < 0.10
        w = np.random.default_rng(0).dirichlet(np.ones(3), 4000)
        inner = w @ tri
        best = host_distances(sc.spheres[:3], [], [], inner).min(1).max()
        assert best < 0.10
        assert best == pytest.approx(P.circumradius - P.sphere_radius, abs=5e-3)  # the centroid
        c4 = c[3]
        assert min(np.linalg.norm(c4 - x0), np.linalg.norm(c4 - g)) - P.sphere_radius >= P.fourth_min_distance
        assert np.min(np.linalg.norm(tri - c4, axis=1)) - 2 * P.sphere_radius >= P.fourth_gap
        f = (c4 - x0) @ (g - x0) / np.linalg.norm(g - x0) ** 2
        assert P.fourth_fraction[0] - 1e-9 <= f <= P.fourth_fraction[1] + 1e-9
        side = np.linalg.norm((c4 - x0) - f * (g - x0))
        assert P.fourth_offset[0] - 1e-9 <= side <= P.fourth_offset[1] + 1e-9
        a = rot_from_quat(sc.goal_quat)[:, 2]
        np.testing.assert_allclose(a, np.array([g[0], g[1], 0]) / math.hypot(g[0], g[1]), atol=1e-12)
        assert _start_ok(sc, info)
        assert host_distances(sc.spheres, [], [], g[None]).min() >= PRM.goal_clearance


def _fourth_sphere_one_at_a_time(rng, P, tries, x0, g, b1, b2, tri):
    """The simple case's fourth sphere as the generator first drew it: one candidate at a time."""
    rs = P.sphere_radius
    for _ in range(tries):
        f = rng.uniform(*P.fourth_fraction)
        off = rng.uniform(*P.fourth_offset)
        beta = rng.uniform(0, 2 * math.pi)
        c4 = x0 + f * (g - x0) + off * (math.cos(beta) * b1 + math.sin(beta) * b2)
        if min(np.linalg.norm(c4 - x0), np.linalg.norm(c4 - g)) - rs < P.fourth_min_distance:
            continue
        if min(np.linalg.norm(c4 - c) for c in tri) - 2 * rs < P.fourth_gap:
            continue
        return c4
    return None


@pytest.mark.parametrize("margin", [None, 10.0])
def test_fourth_sphere_equals_drawing_one_at_a_time(monkeypatch, margin):
    """The vectorised draw of the simple case's fourth sphere accepts the same candidate, to the bit,
    and leaves the generator where the one-at-a-time loop does; also when no candidate passes (few
    tries), and with every candidate decided by the scalar rule (a screening margin of 10 m)."""
    import redman_jax._cases as cases

    if margin is not None:
        monkeypatch.setattr(cases, "_SCREEN_MARGIN", margin)
    P = PRM.simple
    setup = np.random.default_rng(7)
    outcomes = collections.Counter()
    for trial in range(300):
        x0 = setup.uniform(-0.3, 0.3, 3) + np.array([0.0, 0.0, 0.8])
        g = x0 + setup.uniform(0.6, 1.2) * cases._unit(setup.normal(size=3))
        b1, b2 = cases._perp_basis(g - x0)
        roll = setup.uniform(0, 2 * math.pi)
        m = 0.5 * (x0 + g)
        tri = [m + P.circumradius * (math.cos(roll + 2 * math.pi * k / 3) * b1
                                     + math.sin(roll + 2 * math.pi * k / 3) * b2) for k in range(3)]
        tries = int(setup.choice([1, 5, 200]))
        a, b = np.random.default_rng(trial), np.random.default_rng(trial)
        want = _fourth_sphere_one_at_a_time(a, P, tries, x0, g, b1, b2, tri)
        if want is None:
            with pytest.raises(_Reject, match="simple_fourth"):
                _draw_fourth_sphere(b, P, tries, x0, g, b1, b2, tri)
        else:
            got = _draw_fourth_sphere(b, P, tries, x0, g, b1, b2, tri)
            assert got.tobytes() == want.tobytes()
        assert a.bit_generator.state == b.bit_generator.state
        assert a.random() == b.random()
        outcomes["rejected" if want is None else "accepted"] += 1
    assert outcomes["accepted"] > 50 and outcomes["rejected"] > 50, outcomes


def test_host_distances_match_jax_sdf():
    rng = np.random.default_rng(0)
    info, scenes = _host_scenes("welding", 9, [3])
    sc = scenes[0]
    sph = [(np.eye(3), rng.normal(size=3) * 0.3, np.array([0.07]))]
    obs = make_obstacles(sph, sc.boxes, sc.cylinders)
    x = rng.normal(size=(200, 3)) * 0.4 + np.asarray(sc.boxes[0][1])
    ref = np.asarray(jax.vmap(obstacle_distances, in_axes=(None, 0))(obs, jnp.asarray(x)))
    np.testing.assert_allclose(host_distances(sph, sc.boxes, sc.cylinders, x), ref, atol=1e-12)


def test_determinism_and_batched_equals_individual(arms, geometric):
    arm = arms[9]
    for case in ("warehouse", "inspection", "welding"):
        batch = geometric[(case, 9)]
        for i in (0, 7):
            a = make_scenario(case, SEEDS[i], arm)
            b = make_scenario(case, SEEDS[i], arm)
            for x, y, z in zip(jax.tree.leaves(a), jax.tree.leaves(b), jax.tree.leaves(_one(batch, i))):
                np.testing.assert_array_equal(np.asarray(x), np.asarray(y))  # bit for bit
                np.testing.assert_array_equal(np.asarray(x), np.asarray(z))
    # one case's scenarios share their shapes; capacities fixed per case
    for case in CASES:
        assert len(obstacle_capacities(case)) == 3
    assert geometric[("warehouse", 9)].obstacles.boxes.mask.shape == (30, obstacle_capacities("warehouse")[1])


def test_errors_name_the_field(arms):
    arm = arms[9]
    with pytest.raises(ValueError, match="case"):
        make_scenario("kitchen", 1, arm)
    with pytest.raises(ValueError, match="seed"):
        make_scenario("warehouse", -1, arm)
    with pytest.raises(ValueError, match="arm"):
        make_scenario("warehouse", 1, "arm")
    with pytest.raises(ValueError, match="params"):
        make_scenario("warehouse", 1, arm, params={"ts": 0.01})
    with pytest.raises(ValueError, match=r"CaseParams\.ts"):
        CaseParams(ts=-0.01)
    with pytest.raises(ValueError, match=r"AgricultureParams\.root_radius"):
        AgricultureParams(root_radius=(0.6, 0.3))
    with pytest.raises(ValueError, match=r"WarehouseParams\.max_boxes"):
        WarehouseParams(max_boxes=9)
    with pytest.raises(ValueError, match=r"SimpleParams\.circumradius"):
        SimpleParams(circumradius=float("nan"))
    with pytest.raises(ValueError, match=r"CaseParams\.simple"):
        CaseParams(simple=AgricultureParams())
    # a float count was accepted and failed deep inside the generator (range(3.0)); a start of
    # two numbers failed in a NumPy broadcast, an empty scan row list with an IndexError
    for make, match in [(lambda: AgricultureParams(n_trees=3.0), r"AgricultureParams\.n_trees: must be an int"),
                        (lambda: CaseParams(max_draws=100.5), r"CaseParams\.max_draws: must be an int"),
                        (lambda: WarehouseParams(capacity=320.0), r"WarehouseParams\.capacity: must be an int"),
                        (lambda: CaseParams(sizing_start=(0.0, 1.2)), r"CaseParams\.sizing_start: must be 3 numbers"),
                        (lambda: InspectionParams(scan_rows=()), r"InspectionParams\.scan_rows: must be one or more"),
                        (lambda: AgricultureParams(root_jitter=(0.1, 0.2)), r"AgricultureParams\.root_jitter: must be a number")]:
        with pytest.raises(ValueError, match=match):
            make()
    with pytest.raises(ValueError, match=r"CaseParams\.rrt: expected an RRTParams"):
        CaseParams(rrt={"step": 0.1})  # was passed on to the planner unchecked
    with pytest.raises(ValueError, match="seeds"):
        make_scenarios("warehouse", [], arm)


def test_tunable_dimensions_take_effect(arms):
    prm = CaseParams(warehouse=WarehouseParams(max_boxes=0, approach_distance=0.30))
    sc = make_scenario("warehouse", 5, arms[9], params=prm)
    dims = np.asarray(sc.obstacles.boxes.dims)[np.asarray(sc.obstacles.boxes.mask)]
    assert not np.any(np.all(np.isclose(dims, 0.12), axis=1))  # no boxes at all
    n = int(sc.reference.n_samples)
    g = np.asarray(sc.goal_p)
    hits = np.linalg.norm(np.asarray(sc.reference.p)[:n] - (g - np.array([0, np.sign(g[1]) * 0.30, 0])), axis=1)
    assert hits.min() < 1e-12


def test_warehouse_keeps_start_protection(arms):
    """Shelves moved to 0.22 m from the base axis break the start protection (0.25 m below
    z = 0.5): every draw is refused (the warehouse generator never checked it)."""
    stats = collections.Counter()
    prm = CaseParams(warehouse=WarehouseParams(front=0.22), max_draws=3)
    sc = make_scenarios("warehouse", [1], arms[9], params=prm, max_retries=0, stats=stats)
    assert not bool(np.asarray(sc.valid)[0]) and stats["redraw:start_protection"] == 3


def test_validate_hook_moves_the_seed(arms):
    arm = arms[9]
    calls = []

    def reject_first(batch):
        calls.append(np.asarray(batch.seed_used).tolist())
        return np.asarray(batch.seed_used) != 3

    sc = make_valid_scenario("inspection", 3, arm, validate=reject_first)
    assert int(sc.seed) == 3 and int(sc.seed_used) == 1003 and bool(sc.valid)
    assert calls == [[3], [1003]]
    bad = make_valid_scenario("inspection", 3, arm, validate=lambda b: np.zeros(1, bool), max_retries=2)
    assert not bool(bad.valid) and int(bad.seed_used) == 2003


def test_retry_rounds_fill_the_batch_speculatively(arms):
    """A round holds the next attempts of the pending seeds up to the batch size; per seed the first
    passing attempt wins and only the attempts up to it are counted: the outcome and the stats
    equal trying one attempt at a time (a batch of one, no room to speculate)."""
    arm = arms[9]
    calls = []

    def reject(bad):
        def validate(batch):
            used = np.asarray(batch.seed_used)
            calls.append(used.tolist())
            return ~np.isin(used, bad)
        return validate

    stats = collections.Counter()
    sc = make_scenarios("inspection", [3, 4, 5], arm, validate=reject([3, 1003, 4]), stats=stats)
    np.testing.assert_array_equal(np.asarray(sc.seed_used), [2003, 1004, 5])
    assert calls == [[3, 4, 5], [1003, 2003, 1004]]  # round 2: seed 3 at +1000 and +2000 at once
    one = collections.Counter()
    for seed in (3, 4, 5):
        single = make_valid_scenario("inspection", seed, arm, validate=reject([3, 1003, 4]), stats=one)
        j = [3, 4, 5].index(seed)
        for x, y in zip(jax.tree.leaves(single), jax.tree.leaves(sc)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y)[j])
    assert stats == one and stats["reject:validate"] == 3 and stats["accepted"] == 3
    calls.clear()
    stats = collections.Counter()
    sc = make_scenarios("inspection", [3, 4, 5], arm, validate=reject([3]), stats=stats)
    assert calls[1] == [1003, 2003, 3003]  # speculative; 2003 and 3003 are dropped
    assert int(sc.seed_used[0]) == 1003
    assert stats["seeds_tried"] == 4 and stats["reject:validate"] == 1 and stats["accepted"] == 3


def test_rrt_cases_plan_in_one_batch(arms):
    """Two simple-obstacle scenes planned by one jit(vmap(rrt_reference)); the order of seeds in
    the batch does not change a scene, and the second batch (same size) compiles nothing."""
    from conftest import backend_compiles

    arm = arms[9]
    a = make_scenarios("simple", [1, 2], arm)
    with backend_compiles() as compiles:
        b = make_scenarios("simple", [2, 1], arm)
    assert compiles == []
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y)[::-1])
    assert bool(np.all(np.asarray(a.valid)))
    n = np.asarray(a.reference.n_samples)
    p, v = np.asarray(a.reference.p), np.asarray(a.reference.v)
    p0 = np.asarray(_q0_geometry(arm)[0])
    for i in range(2):
        np.testing.assert_allclose(p[i, 0], p0, atol=1e-12)
        np.testing.assert_allclose(p[i, n[i] - 1], np.asarray(a.goal_p[i]), atol=1e-9)
        assert np.all(v[i, n[i] - 1] == 0)
    # planner time scaling keeps |v| <= 1 m/s (checked on a dense grid: 1 % slack)
    assert np.linalg.norm(v, axis=-1).max() <= 1.01
    d = _clearances(a, p)
    assert np.where(np.asarray(a.reference.mask), d, np.inf).min() >= PRM.rrt_path_clearance


def test_plots_make_figures(arms, geometric):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from redman_jax._plots import plot_field_slice, plot_scenario

    sc = _one(geometric[("welding", 9)], 0)
    ax = plot_scenario(sc, arms[9])
    assert ax.name == "3d" and len(ax.lines) >= 2
    plt.close(ax.figure)
    ax = plot_field_slice(sc, resolution=16)
    assert len(ax.collections) > 0
    plt.close(ax.figure)
    with pytest.raises(ValueError, match="scenario"):
        plot_scenario(geometric[("welding", 9)])
    with pytest.raises(ValueError, match="q"):
        plot_scenario(sc, arms[9], q=np.zeros(3))
