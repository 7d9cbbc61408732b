"""External wrenches on links (the rigid-MPM coupler's reaction forces), one per substep, added to
the generalised force: a force f (N, world frame) and a torque t (N m, about the world origin) on
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

from .contact.banks import func_acc


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


@ti.func
def func_external_dof(s: ti.template(), i_b, e, src, h):
    x = s.external
    sub = e // x.evals_per_substep
    for i_d in range(s.n_dofs):
        ld = s.dof_link[i_d]
        for l in range(s.n_links):
            # straight into the field: a local sum over a run-time loop crashes Taichi's reverse mode
            c = ti.cast(x.carries[l, ld], s.dtype)
            func_acc(s, s.force, i_b, i_d, c * (s.cdof_w[i_b, i_d].dot(x.ext_t[i_b, sub, l])
                                                + s.cdof_v[i_b, i_d].dot(x.ext_f[i_b, sub, l])))
