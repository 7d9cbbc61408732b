"""What a coupler sees of the rigid solver: the links' poses and velocities at the start of a substep
and their masses (in), and a wrench per link and substep that the rigid dynamics of that substep adds to its
generalised force (out, solvers/rigid/external.py). A coupler (solvers/coupling.py) reads and writes
these fields inside its own kernels and calls nothing else of the solver.
"""


class RigidPort:
    """link_pos [env, link] (m, world), link_R [env, link] (rotation, world), link_root [link] (the root link
    of the link's kinematic tree, whose origin o = link_pos[env, link_root[link]] the tree's spatial algebra is
    about: solvers/rigid/kinematics.func_link_origin), cvel_v / cvel_w [env, link] (the link's spatial
    velocity at o: linear m/s, angular rad/s; a point x moves at cvel_v + cvel_w x (x - o)), link_mass [env,
    link] (kg), ext_f / ext_t [env, substep, link] (force N, torque N m about o);
    n_envs, n_links: the scene's counts. `update_poses(i)` fills the poses and velocities for substep i."""

    def __init__(self, solver):
        if solver.external is None:
            raise ValueError("RigidPort: the rigid solver was built without external wrenches (external_wrench=True)")
        self._solver = solver
        self.requires_grad = solver.requires_grad
        self.n_envs, self.n_links = solver.n_envs, solver.n_links
        self.link_pos, self.link_R = solver.link_pos, solver.link_R
        self.cvel_v, self.cvel_w = solver.cvel_v, solver.cvel_w
        self.link_root = solver.core.link_root
        self.link_mass = solver.core.link_mass
        self.ext_f, self.ext_t = solver.external.ext_f, solver.external.ext_t

    def update_poses(self, i):
        """Poses and velocities of the links at the start of substep i (the rigid kinematics, a launch
        recorded on an active Tape so that its adjoint reaches the rigid state)."""
        s = self._solver
        s.scratch_overwritten()
        s.core.kernel_kinematics(s.substep_slot[i])
