"""MPMSolver: the particles of every MPM entity of a scene on one background grid (MLS-MPM, APIC).

Fields (axes as in DESIGN.md): particle state x, v, C, F has a slot axis [t, i_b, i_p] holding the
substeps of one step (one slot without gradients: substeps update it in place; substeps + 1 with
gradients, each substep writing the next slot once); per-particle data without an env axis (mass,
volume, material); parameters and external forces [i_b, i_p]; the grid [i_b, node] is scratch,
rewritten every substep; the Kirchhoff stress tau [t, i_b, i_p] has one slot per substep of the
current step with gradients (one without), so a substep's adjoint finds its stress without redoing
the SVD.

A substep is three stages, called in order by the scene's simulator (genesis_lite/simulator.py), which
owns the order: `substep_pre_coupling` (clear the grid, constitutive update of F and tau,
particle-to-grid), the grid update (`grid_update`: gravity and walls; in a coupled scene the coupler's
own, solvers/coupling.py, which adds the rigid boundaries), and `substep_post_coupling`
(grid-to-particle). With gradients the simulator records the three as one `ti.ad.grad_replaced` call
on the scene's Tape (`record_substep`), whose adjoint recomputes the substep's grid (another substep
has overwritten it) by replaying the stages (`replay=True`) under a nested Tape, which then runs their
adjoints in reverse, followed by the adjoint of the constitutive update (the SVD-based one
hand-written, constitutive.py; the others Taichi's). The constitutive update itself is not replayed:
its outputs (F of the next slot, tau of this one) are kept. The two transfers have written-out
adjoints (p2g.func_p2g_adjoint, g2p.func_g2p_adjoint; Taichi's own are the same sums, its g2p one
with an atomic add per node and component), and so has the grid update (grid.func_grid_velocity_adjoint);
a coupler's stages keep Taichi's. The written-out adjoints add into a particle's or a node's own
adjoints with plain adds (one thread owns each; Taichi's `+=` on a field is an atomic add, a
compare-and-swap loop on the CPU). When the step's backward has loaded the substeps its forward left
(kernel_set_substeps, genesis_lite/bridges/mpm.py substep_states), record_substep records the substep
without computing it (`substeps_loaded`).
Particle to grid adds the same way with and without gradients (func_p2g_all), so a rollout's numbers
do not depend on requires_grad.

One compile serves every scene of a class, as in the rigid solver (solvers/rigid/solver.py): Taichi
bakes the fields a kernel touches, and every Python value it reads while compiling, into the compiled
kernel, keyed by the object that owns the kernel. So a solver is pooled by its class (`_key`: dtype,
gradients, envs, the particle capacity, state slots, the grid (lower corner, cell size, resolution), the
walls' friction and the set of materials), and a scene takes a solver of its class from `POOL` and
gives it back when its bridge dies (weakref.finalize in genesis_lite/bridges/mpm.py). The class has a
particle capacity, not a count (RUNTIME_PARTICLE_COUNT): the fields are sized by it and the scene's
count is read at run time from the small `cfg_i` field. A coupled
scene's grid update, which reads that scene's rigid fields, is compiled on its coupler
(solvers/coupling.py), never on the pooled solver, which holds no reference to any scene.
"""

import gc

import numpy as np
import taichi as ti

from .. import taichi_compat

from .constitutive import (AD_MATERIALS, MAT_ELASTIC, MAT_LIQUID, MAT_NEOHOOKEAN, SVD_MATERIALS, func_ad_material,
                           func_corotated_polar_adjoint,
                           func_principal, func_svd_adjoint)
from .g2p import func_g2p, func_g2p_adjoint
from .grid import func_grid_velocity, func_grid_velocity_adjoint, func_walls
from .p2g import func_p2g, func_p2g_adjoint
from .svd import POLAR_TOL, func_polar, func_svd3

# the walls: the grid nodes from each face up to BOUND cells in (BOUND + 1 of them) take no velocity into
# the wall (grid.func_wall), so material rests BOUND cells in from the face, where Genesis's boundary
# holds it (lower_bound + 3 dx); particles are clamped one cell further out (x_min, x_max), a safety net
# that material held by the walls does not reach (a clamp where it rests would cut its gradients)
BOUND = 3
NAN_BIG = 1 << 30  # nan_env holds NAN_BIG - (first non-finite step) (kernel_count_nonfinite)
# Whether the particle count is read at run time, so that scenes of nearby counts share a solver of
# one capacity (cap_particles), as rigid scenes share by size class: a sweep over a body's size compiles
# once (tests/test_faults_mpm.py). Off: the count is a compile-time constant, and only scenes of the same
# count share. The run-time count compiles the loops differently: trajectories and gradients move in their
# last bit against a compile-time count (measured 2.8e-17 m, relative 1e-16, on an elastic + plasticine
# scene and a coupled one), the physics and the gradients are otherwise the same.
RUNTIME_PARTICLE_COUNT = True
MIN_PARTICLES = 512  # the smallest particle capacity with a run-time count


def cap_particles(n: int) -> int:
    """Particle capacity of a scene of n particles: n itself (RUNTIME_PARTICLE_COUNT off), else 512,
    768, 1024, 1536, 2048, ... (powers of two and 1.5 times them), so that nearby particle counts share
    a solver and at most a third of it idles."""
    if not RUNTIME_PARTICLE_COUNT:
        return int(n)
    c = MIN_PARTICLES
    while c < n:
        c = c * 3 // 2 if c & (c - 1) == 0 else c // 3 * 4
    return c


@ti.data_oriented
class MPMSolver:
    """n_envs environments of up to `cap` particles on the grid of [lower, upper] with cells of dx m,
    pooled by its class (see the module docstring): made by `acquire`, which loads a scene into it
    (`_load`). Per scene: particle positions x0 (P, 3) m, volumes vol (P,) m^3, masses mass (P,) kg,
    material codes mat (P,); dt is one scene step (s), split into `substeps`; wall_friction is the
    walls' Coulomb coefficient (a number, or one per axis of the faces' normals). Its substep is three
    stages (see the module docstring)."""

    def __init__(self, key):
        dtype, requires_grad, n_envs, cap, n_slots, lower, dx, grid_res, wall_friction, mats = key
        self.key = key
        self.n_envs = n_envs
        self.cap_particles = cap
        self.runtime_count = RUNTIME_PARTICLE_COUNT
        self._n_particles = cap  # the scene's count: the capacity itself unless it is read at run time
        self.dtype = dtype
        self.np_dtype = np.float64 if dtype == ti.f64 else np.float32
        self.bits = 64 if dtype == ti.f64 else 32
        self.dx = float(dx)
        self.inv_dx = 1.0 / self.dx
        self.lower = ti.Vector([float(v) for v in lower])
        self.grid_res = grid_res
        self.bound = BOUND
        res = np.asarray(grid_res)
        upper_eff = np.asarray(lower, float) + (res - 1) * self.dx
        self.np_lower, self.np_upper = np.asarray(lower, float), upper_eff
        # plain floats: compile-time constants (a ti.Vector attribute in the clamp crashed g2p's adjoint)
        self.x_min = tuple(float(v) for v in self.np_lower + (BOUND - 1) * self.dx)
        self.x_max = tuple(float(v) for v in upper_eff - (BOUND - 1) * self.dx)
        self.requires_grad = requires_grad
        self.wall_friction = tuple(float(m) for m in wall_friction)  # per axis of the faces' normals
        self.mats = mats
        self.has_svd = any(m in SVD_MATERIALS for m in self.mats)
        self.has_ad = any(m in AD_MATERIALS for m in self.mats)
        self.n_slots = n_slots
        self._region = None  # see `region`
        # the slots of the step being recorded on a Tape already hold its substeps, as its forward left them
        # (kernel_set_substeps): record_substep records without computing them again
        self.substeps_loaded = False
        # particle to grid of the no-gradient substep without atomics, one thread per env's grid
        # (kernel_substep_nograd), where that beats atomic adds from every thread: on the CPU with fewer
        # than 5 threads per env (one thread adds without atomics in a fifth of the time it takes with them,
        # measured on this project's CPUs); never on a GPU, whose float atomics are native
        cfg = taichi_compat.config()
        self.plain_p2g = cfg.arch in (ti.x64, ti.arm64) and cfg.cpu_max_num_threads < 5 * n_envs
        self._allocate()
        self._make_units()

    @property
    def n_particles(self):
        """The scene's particle count: in Python its number, inside a kernel being compiled a read of
        cfg_i (so the compiled kernel serves every scene of the class)."""
        if self.runtime_count and taichi_compat.inside_kernel():
            return taichi_compat.subscript(self.cfg_i, 0)
        return self._n_particles

    def _load(self, x0, vol, mass, mat, dt, substeps, gravity):
        """A scene into the solver: its particles (the first len(x0) of the capacity), step and gravity."""
        self._n_particles = len(x0)
        self.dt = dt
        self.substeps = substeps
        self.h = dt / substeps
        self.cfg_i.from_numpy(np.array([len(x0)], np.int32))
        self.substeps_loaded = False
        if hasattr(self, "nan_env"):
            self.nan_env.fill(0)  # no record of an earlier scene's divergence
        self._fill(x0, vol, mass, mat, gravity)

    # ------------------------------------------------------------------ build
    def _allocate(self):
        B, P, S = self.n_envs, self.cap_particles, self.n_slots
        f, g = self.dtype, self.requires_grad
        V3 = lambda shape, grad=g: ti.Vector.field(3, f, shape=shape, needs_grad=grad)  # noqa: E731
        M3 = lambda shape, grad=g: ti.Matrix.field(3, 3, f, shape=shape, needs_grad=grad)  # noqa: E731
        F = lambda shape, grad=g: ti.field(f, shape=shape, needs_grad=grad)  # noqa: E731
        self.x, self.v, self.C, self.F = V3((S, B, P)), V3((S, B, P)), M3((S, B, P)), M3((S, B, P))
        self.tau = M3((max(S - 1, 1), B, P))  # slot = the substep's source slot
        self.p_mass, self.p_vol = F(P, False), F(P, False)
        self.p_mat = ti.field(ti.i32, shape=P)
        self.mu, self.lam, self.yield_stress, self.alpha, self.viscosity = (F((B, P)) for _ in range(5))
        self.f_ext = V3((B, P))
        self.gravity = V3(B)
        G = (B,) + self.grid_res
        self.grid_m, self.grid_mv, self.grid_v = F(G), V3(G), V3(G)
        self.nan_count = ti.field(ti.i32, shape=())
        self.cfg_i = ti.field(ti.i32, shape=1)  # the scene's particle count
        self.nan_env = ti.field(ti.i32, shape=B)  # per env, NAN_BIG - the first step it was not finite (0: never)
        # the block of grid nodes the particles of a substep can touch: the grid loops skip the rest
        self.active_lo = ti.Vector.field(3, ti.i32, shape=())
        self.active_n = ti.Vector.field(3, ti.i32, shape=())
        # per-chunk bounds of the particles' stencils: atomics on six global integers from every particle
        # cost more than the rest of the substep's grid work
        self.n_chunks = min(64, max(1, (B * P) // 256))
        self.chunk_lo = ti.Vector.field(3, ti.i32, shape=self.n_chunks)
        self.chunk_hi = ti.Vector.field(3, ti.i32, shape=self.n_chunks)
        # the loss of the nested Tape that replays a substep in its adjoint: nothing reads it (the
        # adjoints start from the grid's and particles' own), but a Tape needs a scalar to seed; the scene's
        # bridge gives the process's token (genesis_lite/simulator.py tape_loss)
        self.replay_loss = None
        self.vjp_loss = ti.field(f, shape=(), needs_grad=True) if g else None  # see kernel_vjp
        # the adjoints zeroed before a step's backward; not the grid's, which every substep's adjoint
        # zeroes in its own region (kernel_clear_grid_grads) and no kernel reads outside it
        self.grad_fields = [self.x, self.v, self.C, self.F, self.tau, self.mu, self.lam, self.yield_stress,
                            self.alpha, self.viscosity, self.f_ext, self.gravity] if g else []

    def _fill(self, x0, vol, mass, mat, gravity):
        nd = self.np_dtype
        pad = lambda a, t: np.concatenate([np.asarray(a, t), np.zeros(self.cap_particles - len(a), t)])  # noqa: E731
        self.p_mass.from_numpy(pad(mass, nd))
        self.p_vol.from_numpy(pad(vol, nd))
        self.p_mat.from_numpy(pad(mat, np.int32))
        self.gravity.from_numpy(np.tile(np.asarray(gravity, nd), (self.n_envs, 1)))
        self.x0 = np.asarray(x0, nd)

    def _make_units(self):
        """The Tape-recorded calls with their own adjoints (see the module docstring)."""

        @ti.ad.no_grad
        def clear_grid():
            self.kernel_clear_grid()  # the region record_substep_grad has just found (active_lo, active_n)

        @ti.ad.grad_replaced
        def record_substep(i, stages):
            if not self.substeps_loaded:
                stages(i, True, False)

        @ti.ad.grad_for(record_substep)
        def record_substep_grad(i, stages):
            # another substep has overwritten the grid: recompute this one's, and let a nested Tape run
            # the adjoints of its transfers in reverse, from zeroed grid adjoints; then the adjoint of
            # the constitutive update, whose outputs (F[i + 1], tau[i]) are still there
            self.region = tuple(int(r) for r in self.kernel_active_region(i))
            self.kernel_clear_grid_grads(i)
            with ti.ad.Tape(loss=self.replay_loss, clear_gradients=False):
                stages(i, True, True)
            if self.has_ad:
                self.kernel_constitutive_ad.grad(i, i + 1, self.h)
            if self.has_svd:
                self.kernel_constitutive_svd_grad(i, i + 1, self.h)

        # the transfers as the substep's adjoint records them: p2g forward as the no-gradient substep adds
        # (kernel_p2g_fwd), both with written-out adjoints (kernel_p2g_grad, kernel_g2p_grad) instead of
        # Taichi's (whose g2p adjoint scatters with atomic adds: ~5x slower on the CPU)
        @ti.ad.grad_replaced
        def p2g(src):
            self.kernel_p2g_fwd(src, self.h)

        @ti.ad.grad_for(p2g)
        def p2g_grad(src):
            self.kernel_p2g_grad(src, self.h)

        @ti.ad.grad_replaced
        def g2p(src, dst):
            pass  # nothing to recompute: slot dst holds what kernel_g2p wrote there in the step's forward
            # (the backward's replay of the step, whose slots no later launch overwrites), which is all
            # the adjoint reads; only the grid, which the next substep overwrote, is recomputed

        @ti.ad.grad_for(g2p)
        def g2p_grad(src, dst):
            self.kernel_g2p_grad(src, dst, self.h)

        @ti.ad.grad_replaced
        def grid_update(i):
            self.kernel_grid_update(self.h, i, *self.region)

        @ti.ad.grad_for(grid_update)
        def grid_update_grad(i):
            self.kernel_grid_update_grad(self.h, i, *self.region)

        self.clear_grid = clear_grid
        self.grid_update_replay = grid_update
        self.p2g_replay = p2g
        self.g2p_replay = g2p
        # record_substep(i, stages): substep i as one call on the scene's Tape, where stages(i, grad, replay)
        # runs the substep's stages in the simulator's order (replay=True: the adjoint's recompute)
        self.record_substep = record_substep

    # ------------------------------------------------------------------ stepping: the substep's stages
    def _clear_grid(self, src):
        self.region = tuple(int(r) for r in self.kernel_active_region(src))
        self.kernel_clear_grid()

    @property
    def region(self):
        """(lower corner, extent) of the substep's active block of grid nodes, as Python ints: read from
        the device only when asked (a kernel's return value waits for the device and costs several
        launches), which a substep without gradients and without a coupler never does."""
        if self._region is None:
            self._region = tuple(int(r) for r in self.kernel_read_region())
        return self._region

    @region.setter
    def region(self, value):
        self._region = value

    @staticmethod
    def slots(i, grad):
        """(source, destination) particle slots of substep i: i -> i + 1 with gradients, 0 in place without."""
        return (i, i + 1) if grad else (0, 0)

    def substep_pre_coupling(self, i, grad, replay=False):
        """Substep i up to the grid's momenta: clear the grid, constitutive update, particle-to-grid.
        `replay`: the launches are being recorded on the nested Tape of the substep's adjoint, so the
        pieces with adjoints of their own go through their grad_replaced / no_grad wrappers and the
        constitutive update, whose outputs are kept, is left out. Otherwise they are plain launches:
        Taichi clears its 'inside a grad_replaced call' flag when such a wrapper returns, so one called
        inside the substep's own grad_replaced forward would let the launches after it onto the scene's
        Tape. Without gradients: one launch (kernel_substep_nograd)."""
        src, dst = self.slots(i, grad)
        if not grad:
            self.kernel_substep_nograd(self.h, True, False, False)
            self._region = None
            return
        if replay:
            self.clear_grid()
            self.p2g_replay(src)
        else:
            self._clear_grid(src)
            if self.has_svd:
                self.kernel_constitutive_svd(src, dst, self.h)
            if self.has_ad:
                self.kernel_constitutive_ad(src, dst, self.h)
            self.kernel_p2g_fwd(src, self.h)

    def grid_update(self, i, replay=False):
        """Grid velocities of substep i with gravity and the domain walls (a scene without a coupler);
        replay: see substep_pre_coupling."""
        if replay:
            self.grid_update_replay(i)
        else:
            self.kernel_grid_update(self.h, i, *self.region)

    def substep_post_coupling(self, i, grad, replay=False):
        """Substep i from the grid's velocities on: grid-to-particle (replay: see substep_pre_coupling)."""
        if replay:
            self.g2p_replay(*self.slots(i, grad))
        else:
            self.kernel_g2p(*self.slots(i, grad), self.h)

    def substep_uncoupled(self, i):
        """Substep i without gradients in a scene without a coupler: substep_pre_coupling, grid_update and
        substep_post_coupling in that order, in one launch (kernel_substep_nograd)."""
        self.kernel_substep_nograd(self.h, True, True, True)
        self._region = None

    @property
    def last_slot(self):
        return self.n_slots - 1

    # ------------------------------------------------------------------ kernels: the substep
    @ti.func
    def func_chunk_bounds(self, c, src):
        """Bounds of the stencils of the particles (all envs) in chunk c of slot src, into chunk_lo, chunk_hi."""
        big = 1 << 30
        total = self.n_envs * self.n_particles
        lo = ti.Vector([big, big, big])
        hi = ti.Vector([-big, -big, -big])
        for k in range(c * total // self.n_chunks, (c + 1) * total // self.n_chunks):
            x = self.x[src, k // self.n_particles, k % self.n_particles]
            base = ti.cast(ti.floor((x - self.lower) * self.inv_dx - 0.5), ti.i32)
            lo = ti.min(lo, base)
            hi = ti.max(hi, base + 3)
        self.chunk_lo[c] = lo
        self.chunk_hi[c] = hi

    @ti.func
    def func_merge_chunks(self):
        """active_lo, active_n from the chunks' bounds, clamped to the grid (one thread)."""
        big = 1 << 30
        lo = ti.Vector([big, big, big])
        hi = ti.Vector([-big, -big, -big])
        for c in range(self.n_chunks):
            lo = ti.min(lo, self.chunk_lo[c])
            hi = ti.max(hi, self.chunk_hi[c])
        lo = ti.max(lo, 0)
        hi = ti.min(hi, ti.Vector([self.grid_res[0], self.grid_res[1], self.grid_res[2]]))
        self.active_lo[None] = lo
        self.active_n[None] = ti.max(hi - lo, 0)

    @ti.kernel
    def kernel_active_region(self, src: ti.i32) -> ti.types.vector(6, ti.i32):
        """(lower corner, extent) of the block of nodes the stencils of all particles in slot src touch
        (all envs), also left in active_lo, active_n for the clearing kernels."""
        for c in range(self.n_chunks):
            self.func_chunk_bounds(c, src)
        for _ in range(1):
            self.func_merge_chunks()
        lo, n = self.active_lo[None], self.active_n[None]
        return ti.Vector([lo[0], lo[1], lo[2], n[0], n[1], n[2]])

    @ti.kernel
    def kernel_read_region(self) -> ti.types.vector(6, ti.i32):
        """The region the last kernel_active_region or kernel_substep_nograd left in active_lo, active_n."""
        lo, n = self.active_lo[None], self.active_n[None]
        return ti.Vector([lo[0], lo[1], lo[2], n[0], n[1], n[2]])

    @ti.func
    def func_clear_node(self, i_b, I):
        self.grid_m[i_b, I] = 0.0
        self.grid_mv[i_b, I] = ti.Vector.zero(float, 3)

    @ti.kernel
    def kernel_clear_grid(self):
        lo, n = self.active_lo[None], self.active_n[None]
        for i_b, i, j, k in ti.ndrange(self.n_envs, n[0], n[1], n[2]):
            self.func_clear_node(i_b, lo + ti.Vector([i, j, k]))

    @ti.kernel
    def kernel_clear_grid_grads(self, src: ti.i32):
        lo, n = self.active_lo[None], self.active_n[None]
        for i_b, i, j, k in ti.ndrange(self.n_envs, n[0], n[1], n[2]):
            I = lo + ti.Vector([i, j, k])
            self.grid_m.grad[i_b, I] = 0.0
            self.grid_mv.grad[i_b, I] = ti.Vector.zero(float, 3)
            self.grid_v.grad[i_b, I] = ti.Vector.zero(float, 3)
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            self.tau.grad[src, i_b, i_p] = ti.Matrix.zero(float, 3, 3)

    @ti.func
    def func_trial(self, i_b, i_p, src, h):
        """(I + h C) and the trial deformation gradient (I + h C) F of a particle."""
        A = ti.Matrix.identity(float, 3) + h * self.C[src, i_b, i_p]
        return A, A @ self.F[src, i_b, i_p]

    @ti.func
    def func_constitutive_svd(self, i_b, i_p, src, dst, h):
        mat = self.p_mat[i_p]
        polar = False
        if ti.static(MAT_ELASTIC in self.mats) and mat == MAT_ELASTIC:
            # corotated: tau = 2 mu (F - R) F^T + lam (J - 1) J I needs only F's rotation R (func_polar),
            # the SVD's U V^T; symmetrised (it is symmetric up to round-off, as U diag(t) U^T is exactly)
            _, Ft = self.func_trial(i_b, i_p, src, h)
            R, polar = func_polar(Ft, ti.static(POLAR_TOL[self.bits]))
            if polar:
                J = Ft.determinant()
                P = self.mu[i_b, i_p] * (Ft - R) @ Ft.transpose()
                self.F[dst, i_b, i_p] = Ft
                self.tau[src, i_b, i_p] = P + P.transpose() + self.lam[i_b, i_p] * (J - 1.0) * J * ti.Matrix.identity(float, 3)
        if mat != MAT_NEOHOOKEAN and mat != MAT_LIQUID and not polar:  # an SVD material
            _, Ft = self.func_trial(i_b, i_p, src, h)
            U, s, V = func_svd3(Ft)
            hs, _Jh, _dh, t, _Jt, _dt = func_principal(mat, s, self.mu[i_b, i_p], self.lam[i_b, i_p],
                                               self.yield_stress[i_b, i_p], self.alpha[i_b, i_p], False, self.mats)
            Fn = U @ ti.Matrix([[hs[0], 0.0, 0.0], [0.0, hs[1], 0.0], [0.0, 0.0, hs[2]]]) @ V.transpose()
            # elastic: F_new is F_trial itself, not its SVD reassembled (which would drift by round-off)
            if mat == MAT_ELASTIC:
                self.F[dst, i_b, i_p] = Ft
            else:
                self.F[dst, i_b, i_p] = Fn
            self.tau[src, i_b, i_p] = U @ ti.Matrix([[t[0], 0.0, 0.0], [0.0, t[1], 0.0], [0.0, 0.0, t[2]]]) @ U.transpose()

    @ti.kernel
    def kernel_constitutive_svd(self, src: ti.i32, dst: ti.i32, h: float):
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            self.func_constitutive_svd(i_b, i_p, src, dst, h)

    @ti.kernel
    def kernel_constitutive_svd_grad(self, src: ti.i32, dst: ti.i32, h: float):
        """Adjoint of kernel_constitutive_svd (constitutive.func_svd_adjoint; for elastic particles whose
        forward took the polar rotation, constitutive.func_corotated_polar_adjoint), into C, F and the
        material parameters of slot src."""
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            mat = self.p_mat[i_p]
            polar = False
            if ti.static(MAT_ELASTIC in self.mats) and mat == MAT_ELASTIC:
                # where the forward took the polar rotation, its adjoint (no SVD)
                A, Ft = self.func_trial(i_b, i_p, src, h)
                R, polar = func_polar(Ft, ti.static(POLAR_TOL[self.bits]))
                if polar:
                    gFt, gmu, glam = func_corotated_polar_adjoint(Ft, R, self.mu[i_b, i_p], self.lam[i_b, i_p],
                                                                  self.tau.grad[src, i_b, i_p])
                    gFt += self.F.grad[dst, i_b, i_p]  # F_new = F_trial
                    self.C.grad[src, i_b, i_p] = self.C.grad[src, i_b, i_p] + h * gFt @ self.F[src, i_b, i_p].transpose()
                    self.F.grad[src, i_b, i_p] = self.F.grad[src, i_b, i_p] + A.transpose() @ gFt
                    self.mu.grad[i_b, i_p] = self.mu.grad[i_b, i_p] + gmu
                    self.lam.grad[i_b, i_p] = self.lam.grad[i_b, i_p] + glam
            if mat != MAT_NEOHOOKEAN and mat != MAT_LIQUID and not polar:
                A, Ft = self.func_trial(i_b, i_p, src, h)
                U, s, V = func_svd3(Ft)
                hs, Jh, dh, t, Jt, dt = func_principal(mat, s, self.mu[i_b, i_p], self.lam[i_b, i_p],
                                                       self.yield_stress[i_b, i_p], self.alpha[i_b, i_p], True, self.mats)
                gFt, dG, dT = func_svd_adjoint(U, s, V, hs, Jh, t, Jt, self.F.grad[dst, i_b, i_p],
                                               self.tau.grad[src, i_b, i_p])
                self.C.grad[src, i_b, i_p] = self.C.grad[src, i_b, i_p] + h * gFt @ self.F[src, i_b, i_p].transpose()
                self.F.grad[src, i_b, i_p] = self.F.grad[src, i_b, i_p] + A.transpose() @ gFt
                gp = dh.transpose() @ dG + dt.transpose() @ dT
                self.mu.grad[i_b, i_p] = self.mu.grad[i_b, i_p] + gp[0]
                self.lam.grad[i_b, i_p] = self.lam.grad[i_b, i_p] + gp[1]
                self.yield_stress.grad[i_b, i_p] = self.yield_stress.grad[i_b, i_p] + gp[2]
                self.alpha.grad[i_b, i_p] = self.alpha.grad[i_b, i_p] + gp[3]

    @ti.func
    def func_constitutive_ad(self, i_b, i_p, src, dst, h):
        mat = self.p_mat[i_p]
        if mat == MAT_NEOHOOKEAN or mat == MAT_LIQUID:
            _, Ft = self.func_trial(i_b, i_p, src, h)
            Fn, tau = func_ad_material(mat, Ft, self.C[src, i_b, i_p], h, self.mu[i_b, i_p],
                                       self.lam[i_b, i_p], self.viscosity[i_b, i_p], self.mats)
            self.F[dst, i_b, i_p] = Fn
            self.tau[src, i_b, i_p] = tau

    @ti.kernel
    def kernel_constitutive_ad(self, src: ti.i32, dst: ti.i32, h: float):
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            self.func_constitutive_ad(i_b, i_p, src, dst, h)

    @ti.kernel
    def kernel_p2g_grad(self, src: ti.i32, h: float):
        """Adjoint of kernel_p2g_fwd (p2g.func_p2g_adjoint: a gather, one thread per particle)."""
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            func_p2g_adjoint(self, i_b, i_p, src, h)

    @ti.func
    def func_p2g_all(self, src, h):
        """Particle to grid for every particle of slot src: without atomics, each env's particles added
        in order by one thread, where threads are few (`plain_p2g`, see p2g.py), else with atomics."""
        if ti.static(self.plain_p2g):
            for i_b in range(self.n_envs):
                for i_p in range(self.n_particles):
                    func_p2g(self, i_b, i_p, src, h, False)
        else:
            for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
                func_p2g(self, i_b, i_p, src, h, True)

    @ti.kernel
    def kernel_p2g_fwd(self, src: ti.i32, h: float):
        """Particle to grid as the no-gradient substep adds (func_p2g_all): the gradient path's forward and
        its adjoint's recompute (the same numbers both times)."""
        self.func_p2g_all(src, h)

    @ti.kernel
    def kernel_grid_update(self, h: float, sub: ti.i32, l0: ti.i32, l1: ti.i32, l2: ti.i32, n0: ti.i32, n1: ti.i32,
                           n2: ti.i32):
        """Grid velocities of the nodes in the block (l0, l1, l2) + [0, n0) x [0, n1) x [0, n2) in
        substep `sub`."""
        for i_b, i, j, k in ti.ndrange(self.n_envs, n0, n1, n2):
            I = ti.Vector([l0 + i, l1 + j, l2 + k])
            self.grid_v[i_b, I] = func_walls(self, func_grid_velocity(self, i_b, I, h), I)

    @ti.kernel
    def kernel_grid_update_grad(self, h: float, sub: ti.i32, l0: ti.i32, l1: ti.i32, l2: ti.i32, n0: ti.i32,
                                n1: ti.i32, n2: ti.i32):
        """Adjoint of kernel_grid_update (grid.func_grid_velocity_adjoint), gravity's adjoint summed per chunk
        of nodes (one atomic add per chunk instead of one per node)."""
        n = n0 * n1 * n2
        for i_b, c in ti.ndrange(self.n_envs, self.n_chunks):
            acc = ti.Vector.zero(float, 3)
            for k in range(c * n // self.n_chunks, (c + 1) * n // self.n_chunks):
                I = ti.Vector([l0 + k // (n1 * n2), l1 + (k // n2) % n1, l2 + k % n2])
                acc += func_grid_velocity_adjoint(self, i_b, I, h)
            self.gravity.grad[i_b] += acc

    @ti.kernel
    def kernel_substep_nograd(self, h: float, pre: ti.template(), grid: ti.template(), post: ti.template()):
        """Stages of a substep without gradients, in place in slot 0, in one launch: `pre` (what
        substep_pre_coupling does: the active region, clearing it, the constitutive update, particle to
        grid), `grid` (grid_update), `post` (grid to particle). The same arithmetic as the separate kernels
        of the gradient path; the region stays on the device (the grid loops read it from active_lo,
        active_n; the host reads it only when a coupler asks, `region`)."""
        if ti.static(pre):
            for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
                if ti.static(self.has_svd):
                    self.func_constitutive_svd(i_b, i_p, 0, 0, h)
                if ti.static(self.has_ad):
                    self.func_constitutive_ad(i_b, i_p, 0, 0, h)
            for c in range(self.n_chunks):
                self.func_chunk_bounds(c, 0)
            for _ in range(1):
                self.func_merge_chunks()
            lo, n = self.active_lo[None], self.active_n[None]
            for i_b, i, j, k in ti.ndrange(self.n_envs, n[0], n[1], n[2]):
                self.func_clear_node(i_b, lo + ti.Vector([i, j, k]))
            self.func_p2g_all(0, h)
        if ti.static(grid):
            glo, gn = self.active_lo[None], self.active_n[None]
            for i_b, i, j, k in ti.ndrange(self.n_envs, gn[0], gn[1], gn[2]):
                I = glo + ti.Vector([i, j, k])
                self.grid_v[i_b, I] = func_walls(self, func_grid_velocity(self, i_b, I, h), I)
        if ti.static(post):
            for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
                func_g2p(self, i_b, i_p, 0, 0, h)

    @ti.kernel
    def kernel_g2p(self, src: ti.i32, dst: ti.i32, h: float):
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            func_g2p(self, i_b, i_p, src, dst, h)

    @ti.kernel
    def kernel_g2p_grad(self, src: ti.i32, dst: ti.i32, h: float):
        """Adjoint of kernel_g2p (g2p.func_g2p_adjoint), its scatter into the grid adjoints added as
        func_p2g_all adds: without atomics by one thread per env where threads are few."""
        if ti.static(self.plain_p2g):
            for i_b in range(self.n_envs):
                for i_p in range(self.n_particles):
                    func_g2p_adjoint(self, i_b, i_p, src, dst, h, False)
        else:
            for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
                func_g2p_adjoint(self, i_b, i_p, src, dst, h, True)

    # ------------------------------------------------------------------ kernels: I/O and gradients
    @ti.kernel
    def kernel_set_state(self, slot: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                         F: ti.types.ndarray()):
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            for a in ti.static(range(3)):
                self.x[slot, i_b, i_p][a] = x[i_b, i_p, a]
                self.v[slot, i_b, i_p][a] = v[i_b, i_p, a]
                for b in ti.static(range(3)):
                    self.C[slot, i_b, i_p][a, b] = C[i_b, i_p, a, b]
                    self.F[slot, i_b, i_p][a, b] = F[i_b, i_p, a, b]

    @ti.kernel
    def kernel_get_state(self, slot: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                         F: ti.types.ndarray()):
        """Read the state in `slot` and make it the current state (slot 0)."""
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            for a in ti.static(range(3)):
                x[i_b, i_p, a] = self.x[slot, i_b, i_p][a]
                v[i_b, i_p, a] = self.v[slot, i_b, i_p][a]
                for b in ti.static(range(3)):
                    C[i_b, i_p, a, b] = self.C[slot, i_b, i_p][a, b]
                    F[i_b, i_p, a, b] = self.F[slot, i_b, i_p][a, b]
            self.x[0, i_b, i_p] = self.x[slot, i_b, i_p]
            self.v[0, i_b, i_p] = self.v[slot, i_b, i_p]
            self.C[0, i_b, i_p] = self.C[slot, i_b, i_p]
            self.F[0, i_b, i_p] = self.F[slot, i_b, i_p]

    @ti.kernel
    def kernel_get_substeps(self, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                            F: ti.types.ndarray(), tau: ti.types.ndarray()):
        """The step's substeps as its forward left them: slots 1.. of x, v, C, F into [slot - 1] and the stress
        of every substep (tau's slots) into [substep] (the copy a step node keeps, MPMSim.substep_states)."""
        for t, i_b, i_p in ti.ndrange(self.n_slots - 1, self.n_envs, self.n_particles):
            for a in ti.static(range(3)):
                x[t, i_b, i_p, a] = self.x[t + 1, i_b, i_p][a]
                v[t, i_b, i_p, a] = self.v[t + 1, i_b, i_p][a]
                for b in ti.static(range(3)):
                    C[t, i_b, i_p, a, b] = self.C[t + 1, i_b, i_p][a, b]
                    F[t, i_b, i_p, a, b] = self.F[t + 1, i_b, i_p][a, b]
                    tau[t, i_b, i_p, a, b] = self.tau[t, i_b, i_p][a, b]

    @ti.kernel
    def kernel_set_substeps(self, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                            F: ti.types.ndarray(), tau: ti.types.ndarray()):
        """kernel_get_substeps' copy back into the slots (a step's backward, before its Tape)."""
        for t, i_b, i_p in ti.ndrange(self.n_slots - 1, self.n_envs, self.n_particles):
            for a in ti.static(range(3)):
                self.x[t + 1, i_b, i_p][a] = x[t, i_b, i_p, a]
                self.v[t + 1, i_b, i_p][a] = v[t, i_b, i_p, a]
                for b in ti.static(range(3)):
                    self.C[t + 1, i_b, i_p][a, b] = C[t, i_b, i_p, a, b]
                    self.F[t + 1, i_b, i_p][a, b] = F[t, i_b, i_p, a, b]
                    self.tau[t, i_b, i_p][a, b] = tau[t, i_b, i_p, a, b]

    @ti.kernel
    def kernel_vjp(self, slot: ti.i32, gx: ti.types.ndarray(), gv: ti.types.ndarray(), gC: ti.types.ndarray(),
                   gF: ti.types.ndarray()):
        """vjp_loss += <gradients torch hands the step's output state, that state in `slot`>: the scalar whose
        adjoint the step's Tape propagates. It is the solver's own, its adjoint seeded to 1 by
        kernel_clear_grads: the Tape's loss is a torch token no kernel reads (genesis_lite/simulator.py
        tape_loss), and a kernel taking a field of a scene would compile again for each scene of the class."""
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            acc = 0.0
            for a in ti.static(range(3)):
                acc += gx[i_b, i_p, a] * self.x[slot, i_b, i_p][a] + gv[i_b, i_p, a] * self.v[slot, i_b, i_p][a]
                for b in ti.static(range(3)):
                    acc += gC[i_b, i_p, a, b] * self.C[slot, i_b, i_p][a, b] + gF[i_b, i_p, a, b] * self.F[slot, i_b, i_p][a, b]
            self.vjp_loss[None] += acc

    @ti.kernel
    def kernel_get_state_grads(self, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                               F: ti.types.ndarray(), f: ti.types.ndarray()):
        """Adjoints of the state in slot 0 and of the external forces."""
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            for a in ti.static(range(3)):
                x[i_b, i_p, a] = self.x.grad[0, i_b, i_p][a]
                v[i_b, i_p, a] = self.v.grad[0, i_b, i_p][a]
                f[i_b, i_p, a] = self.f_ext.grad[i_b, i_p][a]
                for b in ti.static(range(3)):
                    C[i_b, i_p, a, b] = self.C.grad[0, i_b, i_p][a, b]
                    F[i_b, i_p, a, b] = self.F.grad[0, i_b, i_p][a, b]

    @ti.kernel
    def kernel_set_params(self, p: ti.types.ndarray(), f: ti.types.ndarray(), g: ti.types.ndarray()):
        """p (B, 5, P): mu, lam, yield stress, alpha, viscosity; f (B, P, 3) external forces; g (B, 3)."""
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            self.mu[i_b, i_p] = p[i_b, 0, i_p]
            self.lam[i_b, i_p] = p[i_b, 1, i_p]
            self.yield_stress[i_b, i_p] = p[i_b, 2, i_p]
            self.alpha[i_b, i_p] = p[i_b, 3, i_p]
            self.viscosity[i_b, i_p] = p[i_b, 4, i_p]
            for a in ti.static(range(3)):
                self.f_ext[i_b, i_p][a] = f[i_b, i_p, a]
        for i_b in range(self.n_envs):
            for a in ti.static(range(3)):
                self.gravity[i_b][a] = g[i_b, a]

    @ti.kernel
    def kernel_get_param_grads(self, p: ti.types.ndarray(), g: ti.types.ndarray()):
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            p[i_b, 0, i_p] = self.mu.grad[i_b, i_p]
            p[i_b, 1, i_p] = self.lam.grad[i_b, i_p]
            p[i_b, 2, i_p] = self.yield_stress.grad[i_b, i_p]
            p[i_b, 3, i_p] = self.alpha.grad[i_b, i_p]
            p[i_b, 4, i_p] = self.viscosity.grad[i_b, i_p]
        for i_b in range(self.n_envs):
            for a in ti.static(range(3)):
                g[i_b, a] = self.gravity.grad[i_b][a]

    @ti.kernel
    def kernel_clear_grads(self):
        """Zero every adjoint field (before a step's backward replay). Constants, not x * 0: a NaN left
        by an earlier failed backward must not survive."""
        for x in ti.static(self.grad_fields):
            for I in ti.grouped(x):
                if ti.static(not hasattr(x, "n")):
                    x.grad[I] = 0.0
                elif ti.static(x.m == 1):
                    x.grad[I] = ti.Vector.zero(float, x.n)
                else:
                    x.grad[I] = ti.Matrix.zero(float, x.n, x.m)
        self.vjp_loss.grad[None] = 1.0  # see kernel_vjp

    # ------------------------------------------------------------------ emitters (genesis_lite/entities/emitter.py)
    def set_count(self, n):
        """Make the scene's particle count n (<= the capacity): the kernels then loop over the first n
        particles only. An emitter's particles lie after every other entity's, and the count grows over
        them as they are emitted, so a particle not yet emitted is in no loop and touches nothing."""
        if not self.runtime_count or not 0 <= n <= self.cap_particles:
            raise ValueError(f"MPMSolver.set_count({n}): needs a run-time count and 0 <= n <= {self.cap_particles}")
        self._n_particles = int(n)
        self.cfg_i.from_numpy(np.array([n], np.int32))

    @ti.kernel
    def kernel_set_particle_mass(self, lo: ti.i32, hi: ti.i32, mass: float, vol: float):
        """Mass (kg) and volume (m^3) of particles lo..hi-1 (an emitter's particles carry none until emitted)."""
        for i_p in range(lo, hi):
            self.p_mass[i_p] = mass
            self.p_vol[i_p] = vol

    @ti.kernel
    def kernel_park(self, lo: ti.i32, hi: ti.i32, p: ti.types.vector(3, float)):
        """Put particles lo..hi-1 of slot 0 at rest at p with C = 0 and F = I: particles not yet emitted
        that lie inside the count (behind another emitter's that has emitted). They carry no mass and no
        volume, so they add exact zeros to the grid; parking them after every step keeps their F from
        drifting into a degenerate (non-finite) stress."""
        for i_b, i_p in ti.ndrange(self.n_envs, (lo, hi)):
            self.x[0, i_b, i_p] = p
            self.v[0, i_b, i_p] = ti.Vector.zero(float, 3)
            self.C[0, i_b, i_p] = ti.Matrix.zero(float, 3, 3)
            self.F[0, i_b, i_p] = ti.Matrix.identity(float, 3)

    @ti.kernel
    def kernel_count_nonfinite(self, slot: ti.i32, step: ti.i32) -> ti.i32:
        """Record the `step` (>= 1) at which env i_b first had a particle whose x or v in `slot` is not
        finite, as nan_env[i_b] = NAN_BIG - step (0: no record; an atomic max keeps the first step);
        returns how many envs have a record.
        One pass over the particles and an integer the scene reads after every step."""
        for i_b, i_p in ti.ndrange(self.n_envs, self.n_particles):
            bad = 0
            for a in ti.static(range(3)):
                x = self.x[slot, i_b, i_p][a]
                v = self.v[slot, i_b, i_p][a]
                if ti.math.isnan(x) or ti.math.isinf(x) or ti.math.isnan(v) or ti.math.isinf(v):
                    bad = 1
            if bad:
                ti.atomic_max(self.nan_env[i_b], NAN_BIG - step)
        self.nan_count[None] = 0
        for i_b in range(self.n_envs):
            if self.nan_env[i_b] != 0:
                ti.atomic_add(self.nan_count[None], 1)
        return self.nan_count[None]

    @ti.kernel
    def kernel_reset_nan(self, envs: ti.types.ndarray()) -> ti.i32:
        """Forget the NaN record (kernel_count_nonfinite) of the envs with envs[i_b] != 0; returns how
        many envs keep one."""
        self.nan_count[None] = 0
        for i_b in range(self.n_envs):
            if envs[i_b] != 0:
                self.nan_env[i_b] = 0
            if self.nan_env[i_b] != 0:
                ti.atomic_add(self.nan_count[None], 1)
        return self.nan_count[None]


def solver_key(n_envs, n_particles, mat, lower, upper, dx, substeps, dtype, requires_grad, wall_friction):
    """The class of solver a scene needs (see the module docstring): what its kernels compile in."""
    res = np.round((np.asarray(upper, float) - np.asarray(lower, float)) / float(dx)).astype(int) + 1
    return (dtype, bool(requires_grad), int(n_envs), cap_particles(n_particles), substeps + 1 if requires_grad else 1,
            tuple(float(v) for v in lower), float(dx), tuple(int(r) for r in res),
            tuple(float(m) for m in np.broadcast_to(np.asarray(wall_friction, float), (3,))),
            tuple(sorted(set(int(m) for m in mat))))


class _Pool:
    """Free solvers by class. A scene takes one (or has one made) and a finaliser on its bridge gives
    it back when the scene dies (as the rigid solver's pool, solvers/rigid/solver.py)."""

    def __init__(self):
        self.free = {}
        self.taken = {}  # key -> number of solvers held by live scenes

    def acquire(self, key):
        """(solver, reused) of class `key`."""
        free = self.free.setdefault(key, [])
        if not free and self.taken.get(key, 0):
            gc.collect()  # scenes that are only garbage still hold their solvers: a collection is far cheaper than a compile
        self.taken[key] = self.taken.get(key, 0) + 1
        return (free.pop(), True) if free else (MPMSolver(key), False)

    def release(self, solver):
        self.taken[solver.key] -= 1
        self.free.setdefault(solver.key, []).append(solver)

    def clear(self):
        """Forget the free solvers (their fields stay allocated until Taichi is reset)."""
        self.free.clear()


POOL = _Pool()


def acquire(n_envs, x0, vol, mass, mat, lower, upper, dx, dt, substeps, gravity, dtype, requires_grad, wall_friction):
    """A solver of the scene's class from POOL, loaded with the scene (see MPMSolver); the caller
    gives it back with POOL.release when the scene dies. Returns (solver, reused)."""
    key = solver_key(n_envs, len(x0), mat, lower, upper, dx, substeps, dtype, requires_grad, wall_friction)
    solver, reused = POOL.acquire(key)
    solver._load(x0, vol, mass, mat, dt, substeps, gravity)
    return solver, reused
