"""The pool of rigid cores: free RigidCores by capacity class, and free SceneCores (with a contact
solver, external wrenches or both) by core class, so that a later scene of a class compiles nothing
(see core.py)."""
import gc

from .contact import ContactSolver
from .core import RigidCore, SceneCore
from .external import ExternalWrench


class CorePool:
    """Free cores by capacity class. A scene takes one (or has one made) and a finaliser gives it
    back when the scene's solver dies."""

    def __init__(self):
        self.free = {}
        self.taken = {}  # key -> number of cores held by live scenes
        # SceneCores by core key: each keeps its core, contact solver, external wrenches and compiled kernels
        self.scene_cores_free = {}
        self.scene_cores_taken = 0

    def acquire(self, key):
        free = self.free.setdefault(key, [])
        if not free and self.taken.get(key, 0):
            # scenes that are only garbage still hold their cores: a collection is far cheaper than a compile
            gc.collect()
        self.taken[key] = self.taken.get(key, 0) + 1
        return (free.pop(), True) if free else (RigidCore(key), False)

    def release(self, core):
        self.taken[core.key] -= 1
        self.free.setdefault(core.key, []).append(core)

    def acquire_scene_core(self, key, plan, external_key=None):
        """(scene_core, reused) for a scene of core class `key` with a contact plan (or None) and external
        wrenches of class `external_key` (ExternalWrench.make_key, or None): a free SceneCore with the
        same external wrenches whose contact solver fits the plan (its kernels already compiled), else a
        new one on a core of the class. It keeps that core for good (its kernels are compiled on the
        core's fields)."""

        def fits(o):
            ext = o.external.key if o.external is not None else None
            if ext != external_key or (o.contact is None) != (plan is None):
                return False
            return plan is None or o.contact.fits(plan)

        for attempt in range(2):
            free = self.scene_cores_free.get(key, [])
            fit = [o for o in free if fits(o)]
            if fit:
                # the smallest that fits: a later, larger scene may still find the larger ones
                o = min(fit, key=lambda o: o.contact.caps if o.contact is not None else ())
                free.remove(o)
                self.scene_cores_taken += 1
                return o, True
            if attempt == 0 and self.scene_cores_taken:
                gc.collect()  # dead scenes still holding scene cores give them back
        core, _ = self.acquire(key)
        self.scene_cores_taken += 1
        contact = ContactSolver(core, plan) if plan is not None else None
        external = ExternalWrench(external_key) if external_key is not None else None
        return SceneCore(core, contact, external), False

    def release_scene_core(self, scene_core):
        self.scene_cores_taken -= 1
        self.scene_cores_free.setdefault(scene_core.core.key, []).append(scene_core)

    def clear(self):
        """Forget the free cores and scene cores (their fields stay allocated until Taichi is reset): the next
        scene of every class allocates a new core."""
        self.free.clear()
        self.scene_cores_free.clear()


POOL = CorePool()
