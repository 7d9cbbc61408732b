"""External wrenches on links, two kinds.

AppliedWrench (the user's forces and torques, and gravity compensation): a wrench per env and link for
the whole step, folded into the links' bias forces (func_applied_wrench, run between bias.func_link_forces
and the accumulation up the tree, so it costs O(links) per evaluation and shares the bias stages' tree walk
and projection). The user's part is stored as a force f (N, world) and its moment m about the link's
origin (N m, world, the lever frozen when the force was applied); each evaluation takes the moment about
its tree's origin o (kinematics.func_link_origin) at the link's current origin p, m + (p - o) x f, so the
force follows the link through the
step's substeps. Gravity compensation gc (per env and link, 0..1) adds the force -gc m g at the link's
centre of mass: the entity feels (1 - gc) of gravity, Genesis's meaning.

ExternalWrench (the rigid-MPM coupler's reaction forces), one per substep, added to
the generalised force: a force f (N, world frame) and a torque t (N m, about the link's tree's origin) on
link l act on dof d through its motion subspace as cdof_w . t + cdof_v . f when d moves l, that is
when d's link is l or one of its ancestors.

One stage, each dof summing over the links its link carries (a static ancestor table), rather than
subtree sums accumulated up the tree in a scratch field: Taichi 1.7.4's adjoint of the kernel came
out wrong (the links' mass gradients) once a tree-accumulation stage and the dof stage were both in
it, though each alone was right.

The fields belong to the scene (its envs, substeps and links), not to the pooled core: a scene with
external wrenches runs its dynamics on a per-scene SceneCore (core.py), as one with
contacts does.
"""
import numpy as np
import taichi as ti

from .kinematics import func_link_origin
from .math3d import func_add


@ti.data_oriented
class ExternalWrench:
    """ext_f, ext_t [env, substep, link]: the wrench of each substep (written by the coupler);
    carries [link, link]: 1 where the second link is the first or one of its ancestors."""

    def __init__(self, key):
        B, S, L, evals_per_substep, dtype, g = key
        self.key = key
        self.evals_per_substep = evals_per_substep
        self.ext_f = ti.Vector.field(3, dtype, shape=(B, S, L), needs_grad=g)
        self.ext_t = ti.Vector.field(3, dtype, shape=(B, S, L), needs_grad=g)
        self.carries = ti.field(ti.i32, shape=(L, L))
        self.grad_fields = [self.ext_f, self.ext_t] if g else []
        self.stages = (func_external_dof,)

    @staticmethod
    def make_key(n_envs, substeps, n_links, evals_per_substep, dtype, requires_grad):
        """What the kernels of a scene's external wrenches compile in (the pool's key)."""
        return (int(n_envs), int(substeps), max(int(n_links), 1), int(evals_per_substep), dtype, bool(requires_grad))

    def load(self, link_parent):
        """A scene's tree (link_parent: parent index per link, -1 for a root) and no wrench yet."""
        L = self.key[2]
        carries = np.zeros((L, L), dtype=np.int32)
        for l in range(len(link_parent)):
            j = l
            while j >= 0:
                carries[l, j] = 1
                j = int(link_parent[j])
        self.carries.from_numpy(carries)
        self.ext_f.fill(0)
        self.ext_t.fill(0)


@ti.data_oriented
class AppliedWrench:
    """force, moment [env, link]: the user's wrench of the current step (force N world, moment N m about
    the link's origin, world axes); gcomp [env, link]: the gravity compensation of each link (its
    entity's). Capacity-sized (the core's envs and elements), so it serves every scene that the core
    holds; the scene's block is [:n_envs, :n_links]."""

    def __init__(self, core):
        B, N, f, g = core.cap_envs, core.cap_elems, core.dtype, core.requires_grad
        self.key = (B, N, f, g)
        self.serial = core.serial
        self.force = ti.Vector.field(3, f, shape=(B, N), needs_grad=g)
        self.moment = ti.Vector.field(3, f, shape=(B, N), needs_grad=g)
        self.gcomp = ti.field(f, shape=(B, N), needs_grad=g)
        self.grad_fields = [self.force, self.moment, self.gcomp] if g else []

    @ti.kernel
    def kernel_set_wrench(self, w: ti.types.ndarray()):
        """force, moment of the scene's envs and links from w (n_envs, n_links, 6) = [force | moment]."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b, i_l in ti.ndrange(w.shape[0], w.shape[1]):
            for k in ti.static(range(3)):
                self.force[i_b, i_l][k] = w[i_b, i_l, k]
                self.moment[i_b, i_l][k] = w[i_b, i_l, 3 + k]

    @ti.kernel
    def kernel_get_wrench_grad(self, g: ti.types.ndarray()):
        """The adjoints of force, moment into g (n_envs, n_links, 6)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b, i_l in ti.ndrange(g.shape[0], g.shape[1]):
            for k in ti.static(range(3)):
                g[i_b, i_l, k] = self.force.grad[i_b, i_l][k]
                g[i_b, i_l, 3 + k] = self.moment.grad[i_b, i_l][k]

    @ti.kernel
    def kernel_set_gcomp(self, x: ti.types.ndarray()):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b, i_l in ti.ndrange(x.shape[0], x.shape[1]):
            self.gcomp[i_b, i_l] = x[i_b, i_l]

    def clear(self):
        self.force.fill(0)
        self.moment.fill(0)
        self.gcomp.fill(0)


@ti.func
def func_applied_wrench(s: ti.template(), i_b, e, src, h):
    """The links' bias forces (what their motion needs, bias.func_link_forces) less the applied wrench:
    the user's (its moment moved to the tree's origin from the link's current origin) and gravity
    compensation's -gc m g at the centre of mass (moment -gc (m c) x g, m c being link_h)."""
    a = s.applied
    for i_l in range(s.n_links):
        f = a.force[i_b, i_l]
        g = s.gravity[i_b]
        gc = a.gcomp[i_b, i_l]
        f_ext = f - (gc * s.link_mass[i_b, i_l]) * g
        t_ext = (a.moment[i_b, i_l] + (s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l)).cross(f)
                 - gc * s.link_h[i_b, i_l].cross(g))
        func_add(s, s.cfrc_n, i_b, i_l, -t_ext)
        func_add(s, s.cfrc_f, i_b, i_l, -f_ext)


@ti.func
def func_external_dof(s: ti.template(), i_b, e, src, h):
    x = s.external
    sub = e // x.evals_per_substep
    for i_d in range(s.n_dofs):
        ld = s.dof_link[i_d]
        for l in range(s.n_links):
            # straight into the field: a local sum over a run-time loop crashes Taichi's reverse mode
            c = ti.cast(x.carries[l, ld], s.dtype)
            func_add(s, s.force, i_b, i_d, c * (s.cdof_w[i_b, i_d].dot(x.ext_t[i_b, sub, l])
                                                + s.cdof_v[i_b, i_d].dot(x.ext_f[i_b, sub, l])))
