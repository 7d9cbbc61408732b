"""The narrow phase's two forms give one geometry (solvers/rigid/collision/narrow.py). Without gradients
func_slot_geometry takes runtime branches (func_slot_geometry_branched: only the slot's own kind and its SDF
side's own type are evaluated); with them, the single-assignment form the differentiated stages need
(func_slot_geometry_selected: every kind and type the scene has, selected). A box pair's edge and face slots take
the choices of their pair's separating-axis test (func_box_pair_test, which the broad phase runs for the active
pairs; here for every box pair) in both, and so do the hull-edge slots of a mesh against a box
(func_hull_pair_test). A scene with every slot kind and
SDF type (box corners, edges and faces, capsule segment pairs, cylinder rims, points against planes, boxes,
capsules, cylinders and meshes; spheres as points), its bodies and a Panda's joints posed at random in 4 envs: both forms,
slot by slot, give the same point, normal and depth to round-off. Default options, float64."""
import numpy as np
import pytest
import taichi as ti

import genesis_lite as gs
from solvers.rigid.collision.geoms import (GEOM_BOX, GEOM_CAPSULE, GEOM_CYLINDER, GEOM_MESH, GEOM_PLANE,
                                           SLOT_BOXEDGE, SLOT_BOXFACE, SLOT_CYL_RIM, SLOT_HULLEDGE, SLOT_HULLFACE,
                                           SLOT_POINT,
                                           SLOT_SEGSEG)
from solvers.rigid.collision.narrow import (func_box_pair_test, func_hull_pair_test, func_is_hull_pair,
                                            func_slot_geometry_branched, func_slot_geometry_selected)

from conftest import robot_urdf

N_ENVS = 4


def _scene():
    scene = gs.Scene()
    scene.add_entity(gs.morphs.Plane())
    arm = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("panda")), fixed=True))
    bodies = [scene.add_entity(gs.morphs.Box(size=(0.6, 0.1, 0.05), pos=(0.0, 0.0, 0.05))),
              scene.add_entity(gs.morphs.Box(size=(0.1, 0.6, 0.05), pos=(0.02, 0.01, 0.12))),
              scene.add_entity(gs.morphs.Capsule(radius=0.04, height=0.3, pos=(0.3, 0.3, 0.2))),
              scene.add_entity(gs.morphs.Capsule(radius=0.04, height=0.3, pos=(0.3, 0.32, 0.35))),
              scene.add_entity(gs.morphs.Cylinder(radius=0.08, height=0.1, pos=(-0.3, 0.2, 0.3))),
              scene.add_entity(gs.morphs.Sphere(radius=0.05, pos=(-0.3, 0.22, 0.6)))]
    scene.build(n_envs=N_ENVS)
    return scene, arm, bodies


@pytest.mark.slow  # ~58 s of a fresh-cache default suite (2026-12-04), its every-slot-kind scene compiled for it
# alone; by default each form is checked on its own: the branched one by the contact tests' rests and landings,
# the selected one by the gradient matrix's contact cases against finite differences
def test_the_branched_narrow_phase_gives_the_selected_form_s_geometry():
    scene, arm, bodies = _scene()
    solver = scene.sim.rigid_solver
    s, c = solver.step_core, solver.contact
    assert not s.requires_grad  # the default: the fused step's branched form
    n_slots = int(c.plan.n_slots)
    kinds = c.slot_kind.to_numpy()[:n_slots]
    sdf_types = c.plan.geoms.type[c.plan.np_slot_gb]
    for kind in (SLOT_POINT, SLOT_CYL_RIM, SLOT_SEGSEG, SLOT_BOXEDGE, SLOT_BOXFACE, SLOT_HULLEDGE, SLOT_HULLFACE):
        assert (kinds == kind).any(), kind
    # (a sphere is a slot's point side against every other type: no slot takes its SDF here)
    for t in (GEOM_PLANE, GEOM_BOX, GEOM_CAPSULE, GEOM_CYLINDER, GEOM_MESH):
        assert (sdf_types == t).any(), t
    out = ti.field(ti.f64, shape=(N_ENVS, n_slots, 2, 7))

    @ti.kernel
    def both(s: ti.template()):
        c = s.contact
        for i_b, i_p in ti.ndrange(N_ENVS, c.n_pairs):
            ga = c.pair_ga[i_p]
            gb = c.pair_gb[i_p]
            if (c.geom_type[ga] == GEOM_BOX) & (c.geom_type[gb] == GEOM_BOX):
                c.pair_box[i_b, i_p] = func_box_pair_test(c, i_b, ga, gb)
            if func_is_hull_pair(c, ga, gb):
                func_hull_pair_test(c, i_b, i_p, ga, gb)
        for i_b, i_s in ti.ndrange(N_ENVS, c.n_slots):
            p1, n1, d1 = func_slot_geometry_branched(s, i_b, i_s)
            p2, n2, d2 = func_slot_geometry_selected(s, i_b, i_s)
            for j in ti.static(range(3)):
                out[i_b, i_s, 0, j] = p1[j]
                out[i_b, i_s, 1, j] = p2[j]
                out[i_b, i_s, 0, 3 + j] = n1[j]
                out[i_b, i_s, 1, 3 + j] = n2[j]
            out[i_b, i_s, 0, 6] = d1
            out[i_b, i_s, 1, 6] = d2

    rng = np.random.default_rng(3)
    worst, depths = 0.0, []
    for _ in range(10):
        for b in bodies:
            b.set_pos(rng.uniform(-0.3, 0.3, (N_ENVS, 3)) + np.array([0.0, 0.0, 0.3]))
            b.set_quat(rng.normal(size=(N_ENVS, 4)))
        arm.set_dofs_position(rng.uniform(-0.5, 0.5, (N_ENVS, arm.n_dofs)))
        scene.step()  # the geoms' poses (the kernel reads the last evaluation's)
        both(s)
        o = out.to_numpy()
        assert np.isfinite(o).all()
        worst = max(worst, float(np.abs(o[:, :, 0] - o[:, :, 1]).max()))
        depths.append(o[:, :, 0, 6])
    # 7e-15 m over these poses (2026-12-02): the compiler arranges the two kernels' arithmetic differently
    assert worst < 1e-12, worst
    # (the poses put slots of every kind near contact, not only far apart)
    depths = np.concatenate(depths, axis=0)
    for kind in (SLOT_POINT, SLOT_SEGSEG, SLOT_BOXEDGE, SLOT_BOXFACE, SLOT_HULLEDGE, SLOT_HULLFACE):
        assert (np.abs(depths[:, kinds == kind]) < 0.05).any(), kind
