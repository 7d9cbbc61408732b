"""Emitter: Genesis's MPM particle source (`scene.add_emitter`, `emitter.emit`, `emitter.emit_omni`).

An emitter owns an MPM entity of `max_particles` particles that exist from build() on but take no part
in the simulation until emitted. They are placed after every other entity's particles, beyond the MPM
solver's run-time particle count, and carry no mass or volume there (bridges/mpm.py): a particle not yet
emitted is in no kernel loop, so a scene with an emitter that has not emitted steps its other entities
exactly as the same scene without it. `emit` fills a droplet (a cylinder, sphere or box around the
nozzle, its axis along `direction`) with a regular lattice of spacing `p_size`, sets those particles'
positions and velocity `speed * direction`, gives them their mass, and the solver counts them from then
on. As in Genesis, particles are taken in order and recycled from the first once the next batch would
not fit, an emitted particle stays in the simulation, and particles not yet emitted read as lying at
`gu.nowhere()` (2333333, 6666666, 5201314) m.

Not differentiable, as in Genesis: `add_emitter` refuses a scene built with requires_grad=True (emission
changes which particles exist between steps, outside the step's autograd node).
"""
from __future__ import annotations

import logging

import numpy as np

from ..errors import GenesisException

logger = logging.getLogger("genesis_lite")

NOWHERE = (2333333.0, 6666666.0, 5201314.0)  # Genesis's gu.nowhere(): where unemitted particles are reported
SHAPES = ("circle", "sphere", "square", "rectangle")
EPS = 1e-15  # Genesis's gs.EPS: the shortest direction accepted


def _number(x):
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and np.isfinite(x)


def _vec3(x, what, call):
    a = np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise GenesisException(f"emitter.{call}: {what} must be 3 finite numbers, got {x!r}")
    return a


def lattice(size, p_size):
    """Cell centres of a regular lattice filling the box `size` (3,) m centred at the origin: round(a /
    p_size) cells (at least 1) along each side a, the spacing adjusted so they tile the box, as the
    entities' sampler (loaders/particles.py) and Genesis's 'regular' sampler count them."""
    size = np.asarray(size, dtype=np.float64)
    counts = np.maximum(np.round(size / p_size).astype(int), 1)
    step = size / counts
    axes = [-s / 2 + (np.arange(n) + 0.5) * d for s, n, d in zip(size, counts, step)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def droplet(shape, size, length, p_size):
    """Particles (n, 3) of a droplet in the nozzle frame (its axis z, centred at the nozzle): a cylinder
    of diameter `size` and height `length` ("circle"), a ball of diameter `size` ("sphere", length
    ignored), a box size x size x length ("square") or size[0] x size[1] x length ("rectangle")."""
    if shape == "circle":
        r = size / 2.0
        pts = lattice((size, size, length), p_size)
        return pts[np.linalg.norm(pts[:, :2], axis=1) <= r]
    if shape == "sphere":
        pts = lattice((size, size, size), p_size)
        return pts[np.linalg.norm(pts, axis=1) <= size / 2.0]
    if shape == "square":
        return lattice((size, size, length), p_size)
    return lattice((size[0], size[1], length), p_size)


def z_to(direction, theta):
    """Rotation taking the nozzle frame's z to the unit vector `direction`, turned by theta (rad) about
    it; its x axis is horizontal (z x up) as Genesis's z_up_to_R makes it (up = world z, or world y
    when direction is vertical)."""
    z = direction
    x = np.array([z[1], -z[0], 0.0]) if abs(z[2]) < 1.0 - 1e-12 else np.array([z[2], 0.0, -z[0]])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], 1)
    c, s = np.cos(theta), np.sin(theta)
    return R @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class Emitter:
    """A source of MPM particles made by `scene.add_emitter(material, max_particles, surface)` (Genesis's
    API): call `emit(...)` or `emit_omni(...)` between steps of the built scene."""

    def __init__(self, scene, entity, max_particles):
        self._scene = scene
        self._entity = entity
        self._max_particles = int(max_particles)
        self._next_particle = 0
        self._acc_droplet_len = 0.0  # stream length (m) carried to the next emit while shorter than a particle
        self.high_water = 0  # particles 0 .. high_water-1 have been emitted (bridges/mpm.py MPMSim.activate)
        entity._emitter = self

    # ---------------------------------------------------------------- Genesis's properties
    @property
    def uid(self):
        return self._entity.uid

    @property
    def entity(self):
        """The MPM entity holding the emitter's particles (get_particles_pos etc.)."""
        return self._entity

    @property
    def max_particles(self):
        return self._max_particles

    @property
    def next_particle(self):
        """Index (in the entity) of the next particle to emit."""
        return self._next_particle

    @property
    def solver(self):
        return self._scene.mpm_solver

    def reset(self):
        """Emit from the first particle again (Genesis's; scene.reset() calls it)."""
        self._next_particle = 0
        self._acc_droplet_len = 0.0

    # ---------------------------------------------------------------- emission
    def _sim(self, call):
        if not self._scene.is_built:
            raise GenesisException(f"emitter.{call}() before scene.build(): add the emitter, build the scene, then "
                                   f"call emitter.{call}() between scene.step() calls")
        return self._scene._mpm

    def emit(self, droplet_shape, droplet_size, droplet_length=None, pos=(0.5, 0.5, 1.0), direction=(0, 0, -1),
             theta=0.0, speed=1.0, p_size=None):
        """Emit one droplet from a nozzle at `pos` (m) pointing along `direction`: droplet_shape "circle"
        (a cylinder of diameter droplet_size, m), "sphere" (a ball of diameter droplet_size), "square"
        (droplet_size x droplet_size) or "rectangle" (droplet_size = (width, height), m), of length
        droplet_length (m) along the direction, centred at the nozzle and turned by theta (rad) about
        its axis. Its particles, on a lattice of spacing p_size (m; default MPMOptions.particle_size),
        move at speed (m/s) along direction. With droplet_length None the length is what the stream
        covers in one step, speed * dt, carried over steps until it reaches one particle (a step that
        emits nothing). Particles are recycled from the first once a batch would pass max_particles."""
        if droplet_shape not in SHAPES:
            raise GenesisException(f"emitter.emit: unsupported droplet_shape {droplet_shape!r}; use one of {SHAPES}")
        if droplet_shape == "rectangle":
            ok = isinstance(droplet_size, (tuple, list, np.ndarray)) and len(droplet_size) == 2 and \
                all(_number(s) and s > 0 for s in droplet_size)
            if not ok:
                raise GenesisException(f"emitter.emit(droplet_shape='rectangle'): droplet_size must be (width, height) "
                                       f"in m, two positive numbers; got {droplet_size!r}")
            droplet_size = (float(droplet_size[0]), float(droplet_size[1]))
        elif not (_number(droplet_size) and droplet_size > 0):
            raise GenesisException(f"emitter.emit(droplet_shape={droplet_shape!r}): droplet_size must be one positive "
                                   f"number (the diameter or side, m); got {droplet_size!r}")
        direction = _vec3(direction, "direction", "emit")
        norm = float(np.linalg.norm(direction))
        if norm < EPS:
            raise GenesisException(f"emitter.emit: zero-length direction {direction.tolist()}; give the nozzle's "
                                   "direction as a non-zero vector, e.g. (0, 0, -1) for straight down")
        direction = direction / norm
        pos = _vec3(pos, "pos", "emit")
        if not _number(theta):
            raise GenesisException(f"emitter.emit: theta must be a finite number (rad), got {theta!r}")
        if not _number(speed):
            raise GenesisException(f"emitter.emit: speed must be a finite number (m/s), got {speed!r}")
        sim = self._sim("emit")
        p_size = self._p_size(p_size, "emit")
        if droplet_length is None:
            if speed < 0:
                raise GenesisException(f"emitter.emit: speed={speed} < 0 with droplet_length=None: the stream's length "
                                       "per step is speed * dt; give speed >= 0 (reverse direction instead)")
            droplet_length = speed * self._scene.sim_options.dt + self._acc_droplet_len
            if droplet_length < p_size:
                self._acc_droplet_len = droplet_length
                logger.debug("emitter: the stream is %.3g m long, under a particle: nothing emitted this step",
                             droplet_length)
                return
            self._acc_droplet_len = 0.0
        elif not (_number(droplet_length) and droplet_length > 0):
            raise GenesisException(f"emitter.emit: droplet_length must be a positive number (m) or None, got "
                                   f"{droplet_length!r}")
        local = droplet(droplet_shape, droplet_size, float(droplet_length), p_size)
        positions = local @ z_to(direction, float(theta)).T + pos
        self._place(sim, positions, np.broadcast_to(speed * direction, positions.shape), "emit")

    def emit_omni(self, source_radius=0.1, pos=(0.5, 0.5, 1.0), speed=1.0, particle_size=None):
        """Emit a spherical shell around `pos` (m), outer radius source_radius (m), inner 0.4 of it (as
        Genesis's code has it), each particle moving radially outwards at speed (m/s); particles on a
        lattice of spacing particle_size (m; default MPMOptions.particle_size)."""
        if not (_number(source_radius) and source_radius > 0):
            raise GenesisException(f"emitter.emit_omni: source_radius must be a positive number (m), got "
                                   f"{source_radius!r}")
        if not _number(speed):
            raise GenesisException(f"emitter.emit_omni: speed must be a finite number (m/s), got {speed!r}")
        pos = _vec3(pos, "pos", "emit_omni")
        sim = self._sim("emit_omni")
        p_size = self._p_size(particle_size, "emit_omni")
        d = 2.0 * source_radius
        local = lattice((d, d, d), p_size)
        r = np.linalg.norm(local, axis=1)
        keep = (r <= source_radius) & (r >= 0.4 * source_radius)
        local, r = local[keep], r[keep]
        self._place(sim, local + pos, speed * local / np.maximum(r, EPS)[:, None], "emit_omni")

    def _p_size(self, p_size, call):
        if p_size is None:
            return float(self._scene.mpm_options.particle_size)
        if not (_number(p_size) and p_size > 0):
            raise GenesisException(f"emitter.{call}: the particle size must be a positive number (m) or None, got "
                                   f"{p_size!r}")
        return float(p_size)

    def _place(self, sim, positions, vels, call):
        n = len(positions)
        lo, hi = sim.inside
        bad = (positions < lo) | (positions > hi)
        if bad.any():
            a = int(np.argmax(bad.any(0)))
            raise GenesisException(
                f"emitter.{call}: the droplet's particles span {positions.min(0).round(4).tolist()} .. "
                f"{positions.max(0).round(4).tolist()} m, outside the MPM domain along {'xyz'[a]} (particles must lie "
                f"within {np.round(lo, 4).tolist()} .. {np.round(hi, 4).tolist()} m: MPMOptions lower_bound/upper_bound "
                "less 3 cells of wall). Move the nozzle, shrink the droplet, or enlarge the domain.")
        if n > self._max_particles:
            raise GenesisException(
                f"emitter.{call}: this droplet has {n} particles, more than the emitter's max_particles "
                f"({self._max_particles}); give scene.add_emitter a larger max_particles, or emit a smaller droplet "
                "(droplet_size, droplet_length, or a larger p_size)")
        if self._next_particle + n > self._max_particles:
            self._next_particle = 0  # recycle (Genesis does this after the previous batch; see below)
        start = self._next_particle
        sim.emit(self._entity, start, positions, np.asarray(vels, dtype=np.float64).copy())
        self._next_particle = start + n
        if self._next_particle + n > self._max_particles:  # Genesis's rule: the next batch of this size would not fit
            self._next_particle = 0
        logger.debug("emitter: emitted %d particles (%d .. %d)", n, start, start + n - 1)

    def __repr__(self):
        return (f"<Emitter of {type(self._entity.material).__name__}: {self._max_particles} particles, "
                f"{self.high_water} emitted so far, next {self._next_particle}>")
