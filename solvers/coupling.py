"""Two-way rigid-MPM coupling on the MPM grid.

Every collision geom of a coupled rigid entity is a moving boundary for the MPM grid. The coupling is
a stage of the substep (`couple`, called by genesis_lite/simulator.py between the MPM solver's
particle-to-grid and grid-to-particle, and before the rigid solver's substep): the rigid links' poses
and velocities at the substep's start are computed (through the rigid solver's port,
solvers/rigid/port.py: poses and velocities in, a wrench out), every grid node near the particles
picks the geom it is deepest in (or nearest to, within `softness` outside), and the grid update
(gravity, walls, then the boundary) projects the node's velocity relative to that geom's surface
velocity:

    v_rel = v - v_body(x),  v_n = v_rel . n  (n: the geom's outward normal at the node)
    approaching (v_n < 0): the normal part is removed, the tangential part slides with Coulomb
    friction mu (it loses mu |v_n| of speed, never reverses), blended in over a band of width
    `softness` outside the surface (smoothstep of the signed distance: 1 inside, 0 beyond the band)
    deeper inside (phi < -D dx, D = EXPEL_DEPTH_LIGHT, or EXPEL_DEPTH for a heavy link): v_n is raised to
    at least min(EXPEL_RATE (|phi| - D dx), EXPEL_CELLS dx) / h, so material that got into the body
    leaves it along the normal instead of staying in

The momentum the node loses, m (v - v_new), is the impulse the MPM material gives the body: divided by
the substep it becomes a force at the node on the geom's link (and its torque about the link's tree's origin),
summed into the rigid solver's external wrench of that substep (solvers/rigid/external.py), which the
rigid solver applies in the same substep (after this stage). Both directions are differentiable: the projection is part
of the MPM grid update (Taichi's autodiff), the body's pose and velocity come from the rigid
kinematics launched inside the MPM substep (so its adjoint reaches the rigid state), and the wrench
enters the rigid dynamics like any generalised force.

The choice of geom per node is discrete (no gradient); it is recomputed with the grid when the MPM
substep's adjoint replays it.

Attachments (MPMEntity.set_particle_constraints, Genesis's name): a particle attached to a link is pulled
towards the point of the link it was at when attached, by a spring of stiffness k (N/m) with critical
damping c = 2 sqrt(k m) against its velocity relative to that point. It replaces the grid-to-particle
stage (`g2p_attached`): the particle gathers its velocity v from the grid, the spring acts over the
substep h implicitly (backward Euler, stable for any k, h),

    e = x + h v - target,  v_rel = v - v_link(x)
    dv = -h (k e + c v_rel) / (m (1 + h c / m + h^2 k / m)),

and the particle moves with v + dv. One-way, as Genesis's: the link does not feel the pull (it drives
the material; a reaction on the link, explicit in the rigid solver's substep, oscillated with growing
amplitude for a 0.7 kg box holding 450 particles at k = 1e5 N/m, h = 1e-4 s, and was taken out).
Genesis's spring is explicit and damps the absolute velocity; for a link at rest and a substep within
the explicit limit the two agree to first order in h.
"""
import numpy as np
import taichi as ti

from .mpm.g2p import func_g2p_gather, func_g2p_store
from .mpm.grid import func_grid_velocity, func_walls
from .taichi_compat.adstack import require as require_ad_stack
from .rigid.collision import func_sdf_any, geom_rotations
from .rigid.math3d import func_mm, func_mtv, func_mv

TINY = 1e-30
# Material inside a body (grid nodes with phi < 0) is sent out along the normal at this fraction of its
# depth per substep (relative to the body), on top of the no-approach rule: without it, material that
# got in (the body struck it faster than the grid could stop it, or pressed it against the floor) stays
# in for good (4 t box at rest on jelly: 22 inside in tests/test_faults_mpm.py's scene, 0 deeper now).
# EXPEL_CELLS (a fraction of a cell per substep) caps it: the push is a velocity the material keeps, and
# an uncapped one (tried: 0.1 of the depth alone) threw a jelly block that a heavy box had sunk into
# up into the air.
EXPEL_RATE = 0.02
EXPEL_CELLS = 0.002
# A link heavier than HEAVY_MASS pushes five times
# harder: the material it crushes presses back into it harder than the push above moves it out. A 4 t box
# resting on jelly over a plane (tests/test_faults_mpm.py, once the mass-scaled ground contact held the
# box) kept 20 particles within 4 mm of its top edges at 0.002 cells per substep, 4 at 0.005, none (from
# 150 steps on, 4 t and 400 t) at these. Not for every body: on a ball pressed into a block (the gradient
# matrix's ball_in_block) the stronger push crossed the cap's kink within finite differences' steps.
# (HEAVY_MASS was the rigid contact law's threshold for its mass-scaled stiffness until 2026-12-05, when that
# became relative to the contact stiffness: solvers/rigid/contact/law.py, heavy_mass.)
HEAVY_MASS = 100.0
EXPEL_RATE_HEAVY = 0.1
EXPEL_CELLS_HEAVY = 0.01
# Only material deeper than EXPEL_DEPTH cells is pushed: nearer the surface, pushing granular material
# kept it flowing around a sphere resting in sand (the sphere crept at 2 cm/s instead of a few mm/s).
EXPEL_DEPTH = 0.5
# A light link's push starts deeper, EXPEL_DEPTH_LIGHT cells: a node holds mass from particles up to 1.5 cells
# away along each axis (the quadratic B-spline), so a node less than 1.5 cells inside a face may hold only
# material that is wholly outside it, and pushing that material made Genesis's grasp_soft_cube drop the cube:
# the Panda's fingers (a 1 N squeeze) rested on the cube with no particle inside them, yet 3 fringe nodes
# 0.5-1 cell inside a finger (grid nodes off the cube's centre line: MPMOptions(lower_bound=(.., -0.1, ..))
# at 128 cells/m) were pushed into it every substep, the cube slid down the fingers during the lift and fell
# out of them in the hold (particles' mean z 0.056 m; 0.088 m with this depth, as on Genesis, which pushes
# nothing out). A heavy link keeps EXPEL_DEPTH: the jelly a 4 t box crushes stayed in it (76 particles) with
# the push from 1.5 cells.
EXPEL_DEPTH_LIGHT = 1.5


@ti.data_oriented
class RigidMPMCoupler:
    """Made and pooled by class (`POOL`, `make_key`), loaded with a scene by `load`.
    mpm: the scene's MPMSolver; rigid: the RigidPort of its RigidSolver (built with
    external_wrench=True, solvers/rigid/port.py); geoms: the GeomTable of its collision
    geoms (solvers/rigid/collision.py build_geoms), of which those at `idx` are coupled; friction:
    Coulomb coefficient per coupled geom;
    softness (m): width of the band outside a surface over which its boundary fades in; reaction:
    whether the rigid bodies feel the MPM material (two-way) or only move it (one-way)."""

    def __init__(self, key, mpm, rigid):
        _, _, _, n_geoms, sdf_types, softness, reaction, kdop_width, B, _ = key
        self.key = key
        self.mpm = mpm
        self.rigid = rigid
        # the fields the kernels compiled on this coupler read: held while it waits in the pool, so that the
        # ids in its key name them and no other objects
        self._compiled_against = (rigid.link_R, rigid.ext_f)
        self.n_geoms = n_geoms
        self.softness = softness
        self.reaction = reaction
        self.sdf_types = sdf_types
        self.lower = ti.Vector([float(v) for v in mpm.np_lower])
        self.dx = float(mpm.dx)
        dtype = mpm.dtype
        G = max(n_geoms, 1)
        self.geom_type, self.geom_link = ti.field(ti.i32, shape=G), ti.field(ti.i32, shape=G)
        self.geom_pos = ti.Vector.field(3, dtype, shape=G)
        self.geom_R = ti.Matrix.field(3, 3, dtype, shape=G)
        self.geom_size = ti.Vector.field(3, dtype, shape=G)
        self.geom_kdop = ti.field(dtype, shape=(G, kdop_width))
        self.geom_kdop_dir = ti.Vector.field(3, dtype, shape=(G, kdop_width))
        self.geom_friction = ti.field(dtype, shape=G)
        self.geom_react = ti.field(dtype, shape=G)  # 1: the geom's link feels the material (two-way), 0: not (a tool)
        self.node_geom = ti.field(ti.i32, shape=(B,) + tuple(mpm.grid_res))
        # the domain's floor, watched (see kernel_select): 1 where geom g's origin was inside the domain at
        # the last substep; 1 where it has since gone below the floor within the domain's footprint
        self.upper = ti.Vector([float(v) for v in mpm.np_upper])
        self.geom_in = ti.field(ti.i32, shape=(B, G))
        self.geom_through = ti.field(ti.i32, shape=(B, G))
        self.n_through = ti.field(ti.i32, shape=())
        self.att_link = None  # attachments (set_attachments): allocated with the first
        self.attached = False
        self._make_units()

    @staticmethod
    def make_key(mpm, rigid, geoms, idx, softness, reaction):
        """What the kernels of a coupler compile in: the MPM solver's and the rigid solver's fields (by
        identity: both are pooled, solvers/mpm/solver.py and solvers/rigid/pool.py), the coupled geoms'
        count and SDF types, the band, two-way or not, and the sizes of its own fields."""
        idx = np.asarray(idx, dtype=np.int64)
        return (id(mpm), id(rigid.link_R), id(rigid.ext_f), len(idx), tuple(sorted({int(t) for t in geoms.type[idx]})),
                float(softness), bool(reaction), int(geoms.kdop.shape[1]), rigid.n_envs, rigid.n_links)

    def load(self, rigid, geoms, idx, friction, react=None):
        """A scene into the coupler: its rigid solver's port and the coupled geoms (their Coulomb
        coefficients against the material: friction; react: per geom whether its link feels the material,
        default all, when the coupler is two-way)."""
        self.rigid = rigid
        if rigid.requires_grad:
            require_ad_stack(self.n_geoms)  # each grid node loops over the coupled geoms
        idx = np.asarray(idx, dtype=np.int64)
        npf = np.float64 if self.mpm.dtype == ti.f64 else np.float32
        quat = geoms.quat[idx]
        self.geom_type.from_numpy(geoms.type[idx].astype(np.int32))
        self.geom_link.from_numpy(geoms.link[idx].astype(np.int32))
        self.geom_pos.from_numpy(geoms.pos[idx].astype(npf))
        self.geom_R.from_numpy(geom_rotations(quat / np.linalg.norm(quat, axis=1, keepdims=True)).astype(npf))
        self.geom_size.from_numpy(geoms.size[idx].astype(npf))
        self.geom_kdop.from_numpy(np.ascontiguousarray(geoms.kdop[idx]).astype(npf))
        self.geom_kdop_dir.from_numpy(np.ascontiguousarray(geoms.kdop_dirs[idx]).astype(npf))
        self.geom_friction.from_numpy(np.asarray(friction, dtype=npf))
        self.geom_react.from_numpy(np.ones(len(idx), npf) if react is None else np.asarray(react, dtype=npf))
        self.clear_through()
        if self.att_link is not None:
            self.att_link.fill(-1)
        self.attached = False

    def clear_through(self):
        """Forget the floor watch (a new scene, or a reset): no geom counts as inside until a substep sees it."""
        self.geom_in.fill(0)
        self.geom_through.fill(0)
        self.n_through[None] = 0

    def through_floor(self):
        """None, or (env, coupled geom) index arrays of the geoms that went below the domain's floor."""
        if self.n_through[None] == 0:
            return None
        return np.nonzero(self.geom_through.to_numpy())

    def _make_units(self):
        @ti.ad.no_grad
        def select(sub, region):
            self.kernel_select(sub, *region)

        self.select = select

    def couple(self, i, grad, replay=False):
        """The coupling stage of substep i (after the MPM solver's particle-to-grid): the links' poses and
        velocities at the substep's start, the geom each node of the grid's active region answers to,
        a zeroed external wrench, then the grid update with the rigid boundaries (and their reaction).
        `replay`: the launches are being recorded on the nested Tape of the MPM substep's adjoint, so the
        geom selection goes through its no_grad wrapper; a plain launch otherwise (see
        MPMSolver.substep_pre_coupling). `grad` does not change the launches (the grid is per substep)."""
        mpm = self.mpm
        self.rigid.update_poses(i)
        if replay:
            self.select(i, mpm.region)
        else:
            self.kernel_select(i, *mpm.region)
        self.kernel_grid_update(mpm, mpm.h, i, *mpm.region)

    # ------------------------------------------------------------------ attachments (module docstring)
    def set_attachments(self, mask, link, local, stiffness):
        """Attach the particles where mask (n_envs, capacity) is true to `link` (-1: detach them), at the
        link-frame points local (n_envs, capacity, 3), with springs of `stiffness` (N/m)."""
        if self.att_link is None:
            B, P = self.rigid.n_envs, self.mpm.cap_particles
            self.att_link = ti.field(ti.i32, shape=(B, P))
            self.att_local = ti.Vector.field(3, self.mpm.dtype, shape=(B, P))
            self.att_k = ti.field(self.mpm.dtype, shape=(B, P))
            self.att_c = ti.field(self.mpm.dtype, shape=(B, P))  # damping 2 sqrt(k m) (N s/m)
            self.att_link.fill(-1)
        m = np.asarray(mask, dtype=bool)
        lk = self.att_link.to_numpy()
        lk[m] = int(link)
        self.att_link.from_numpy(lk)
        if link >= 0:
            npf = np.float64 if self.mpm.dtype == ti.f64 else np.float32
            loc, k, c = self.att_local.to_numpy(), self.att_k.to_numpy(), self.att_c.to_numpy()
            loc[m] = np.asarray(local, dtype=np.float64)[m]
            k[m] = float(stiffness)
            c[m] = np.broadcast_to(2.0 * np.sqrt(float(stiffness) * self.mpm.p_mass.to_numpy()), c.shape)[m]
            self.att_local.from_numpy(loc.astype(npf))
            self.att_k.from_numpy(k.astype(npf))
            self.att_c.from_numpy(c.astype(npf))
        self.attached = bool((lk >= 0).any())

    def g2p_attached(self, i, grad):
        """The grid-to-particle stage of substep i with the attachments (MPMSolver.substep_post_coupling
        otherwise); the links' poses are the coupling stage's (couple, earlier in the substep)."""
        mpm = self.mpm
        self.kernel_g2p_attached(mpm, *mpm.slots(i, grad), mpm.h)

    @ti.kernel
    def kernel_g2p_attached(self, mpm: ti.template(), src: ti.i32, dst: ti.i32, h: float):
        for i_b, i_p in ti.ndrange(mpm.n_envs, mpm.n_particles):
            x = mpm.x[src, i_b, i_p]
            v, C = func_g2p_gather(mpm, i_b, x)
            l = self.att_link[i_b, i_p]
            has = ti.cast(l >= 0, float)
            ll = ti.max(l, 0)
            Rl = self.rigid.link_R[i_b, ll]
            target = self.rigid.link_pos[i_b, ll] + func_mv(Rl, self.att_local[i_b, i_p])
            v_link = self.rigid.cvel_v[i_b, ll] + self.rigid.cvel_w[i_b, ll].cross(x - self.func_link_origin(i_b, ll))
            m = mpm.p_mass[i_p]
            k = self.att_k[i_b, i_p] * has
            c = self.att_c[i_b, i_p] * has
            dv = -h * (k * (x + h * v - target) + c * (v - v_link)) / (m + h * c + h * h * k + TINY)
            func_g2p_store(mpm, i_b, i_p, dst, x, v + dv, C, h)  # a free particle's dv is 0: func_g2p's numbers

    @ti.func
    def func_link_origin(self, i_b, l):
        """The point link l's spatial velocity and wrenches are about (RigidPort: its tree's root link's origin)."""
        return self.rigid.link_pos[i_b, self.rigid.link_root[l]]

    @ti.func
    def func_geom_frame(self, i_b, g):
        """World rotation and origin of geom g, and its link."""
        l = self.geom_link[g]
        Rl = self.rigid.link_R[i_b, l]
        return func_mm(Rl, self.geom_R[g]), self.rigid.link_pos[i_b, l] + func_mv(Rl, self.geom_pos[g]), l

    @ti.func
    def func_sdf_world(self, i_b, g, x):
        """Signed distance of the world point x to geom g and the outward unit normal there (world)."""
        R, p, l = self.func_geom_frame(i_b, g)
        q = func_mtv(R, x - p)
        phi, n = func_sdf_any(self, 0, self.geom_type[g], g, q, ti.Vector([0.0, 0.0, 1.0]), 0.0)
        return phi, func_mv(R, n), l

    @ti.kernel
    def kernel_select(self, sub: ti.i32, l0: ti.i32, l1: ti.i32, l2: ti.i32, n0: ti.i32, n1: ti.i32, n2: ti.i32):
        for i_b, i, j, k in ti.ndrange(self.rigid.n_envs, n0, n1, n2):
            I = ti.Vector([l0 + i, l1 + j, l2 + k])
            x = self.lower + ti.cast(I, float) * self.dx
            best = -1
            best_phi = self.softness
            for g in range(self.n_geoms):
                phi, n, l = self.func_sdf_world(i_b, g, x)
                if phi < best_phi:
                    best = g
                    best_phi = phi
            self.node_geom[i_b, I] = best
        for i_b, l in ti.ndrange(self.rigid.n_envs, max(self.rigid.n_links, 1)):
            self.rigid.ext_f[i_b, sub, l] = ti.Vector.zero(float, 3)
            self.rigid.ext_t[i_b, sub, l] = ti.Vector.zero(float, 3)
        # The domain's walls stop particles, not rigid bodies: a geom whose origin was inside the domain and is
        # now below its floor, within its footprint, went through it (the scene raises, CouplerBridge.check)
        for i_b, g in ti.ndrange(self.rigid.n_envs, self.n_geoms):
            R, p, l = self.func_geom_frame(i_b, g)
            over = 1
            inside = 1
            for d in ti.static(range(3)):
                if d < 2 and (p[d] < self.lower[d] or p[d] > self.upper[d]):
                    over = 0
                if p[d] < self.lower[d] or p[d] > self.upper[d]:
                    inside = 0
            if self.geom_in[i_b, g] == 1 and over == 1 and p[2] < self.lower[2]:
                self.geom_through[i_b, g] = 1
                ti.atomic_add(self.n_through[None], 1)
            self.geom_in[i_b, g] = inside

    @ti.kernel
    def kernel_grid_update(self, mpm: ti.template(), h: float, sub: ti.i32, l0: ti.i32, l1: ti.i32, l2: ti.i32,
                           n0: ti.i32, n1: ti.i32, n2: ti.i32):
        """The MPM solver's grid update (MPMSolver.kernel_grid_update) with this scene's rigid boundaries
        after the walls. It lives here, not on the pooled MPM solver: it reads the scene's rigid fields,
        which Taichi would bake into a kernel the pooled solver keeps for later scenes."""
        for i_b, i, j, k in ti.ndrange(mpm.n_envs, n0, n1, n2):
            I = ti.Vector([l0 + i, l1 + j, l2 + k])
            v_walls = func_walls(mpm, func_grid_velocity(mpm, i_b, I, h), I)
            mpm.grid_v[i_b, I] = self.func_rigid_boundary(mpm, i_b, I, v_walls, h, sub)

    @ti.func
    def func_rigid_boundary(self, mpm: ti.template(), i_b, I, v, h, sub):
        """Grid velocity of node I after the rigid boundary it answers to (see the module docstring),
        and the reaction wrench onto that boundary's link. Single-assignment form (Taichi's reverse
        mode); a node with no geom passes through unchanged."""
        g = self.node_geom[i_b, I]
        has = ti.cast(g >= 0, float)
        gg = ti.max(g, 0)
        x = self.lower + ti.cast(I, float) * self.dx
        phi, n, l = self.func_sdf_world(i_b, gg, x)
        o = self.func_link_origin(i_b, l)
        v_body = self.rigid.cvel_v[i_b, l] + self.rigid.cvel_w[i_b, l].cross(x - o)
        v_rel = v - v_body
        vn = v_rel.dot(n)
        t = ti.min(ti.max(1.0 - phi / self.softness, 0.0), 1.0)
        alpha = has * t * t * (3.0 - 2.0 * t)
        # a node deeper inside the body than EXPEL_DEPTH_LIGHT cells (EXPEL_DEPTH for a heavy link) must also
        # leave it: at least `push` outward (see EXPEL_RATE, and EXPEL_RATE_HEAVY for a heavy link); 0
        # elsewhere, where the rule is the no-approach one alone
        heavy = self.rigid.link_mass[i_b, l] > HEAVY_MASS
        over = ti.max(-phi - ti.select(heavy, EXPEL_DEPTH, EXPEL_DEPTH_LIGHT) * self.dx, 0.0)
        push = ti.select(heavy, ti.min(over * EXPEL_RATE_HEAVY, EXPEL_CELLS_HEAVY * self.dx),
                         ti.min(over * EXPEL_RATE, EXPEL_CELLS * self.dx)) / h
        approach = ti.cast(vn < push, float)
        vt = v_rel - vn * n
        vt_norm = ti.sqrt(vt.dot(vt) + TINY)
        # friction from the approach speed only: a node already leaving keeps its tangential velocity
        vt_new = vt * ti.max(0.0, 1.0 + self.geom_friction[gg] * ti.min(vn, 0.0) / vt_norm)
        v_new = v + alpha * approach * (vt_new + push * n - v_rel)
        if ti.static(self.reaction):
            f = (self.geom_react[gg] * mpm.grid_m[i_b, I] / h) * (v - v_new)
            self.rigid.ext_f[i_b, sub, l] += f
            self.rigid.ext_t[i_b, sub, l] += (x - o).cross(f)
        return v_new


class _Pool:
    """Free couplers by class (RigidMPMCoupler.make_key). A scene takes one, or has one made, and its
    coupler bridge gives it back when it dies, so that a later scene of the class compiles nothing."""

    def __init__(self):
        self.free = {}

    def acquire(self, mpm, rigid, geoms, idx, friction, softness, reaction, react=None):
        """(coupler, reused) for a scene (see RigidMPMCoupler), loaded with it."""
        key = RigidMPMCoupler.make_key(mpm, rigid, geoms, idx, softness, reaction)
        free = self.free.get(key)
        coupler, reused = (free.pop(), True) if free else (RigidMPMCoupler(key, mpm, rigid), False)
        coupler.load(rigid, geoms, idx, friction, react)
        return coupler, reused

    def release(self, coupler):
        coupler.rigid = None  # the scene's rigid solver goes with the scene (its pooled fields stay held)
        self.free.setdefault(coupler.key, []).append(coupler)

    def clear(self):
        self.free.clear()


POOL = _Pool()
