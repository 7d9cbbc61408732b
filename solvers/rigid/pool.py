"""The pool of rigid cores: free RigidCores by capacity class, and free SceneCores with a contact
solver by core class, so that a later scene of a class compiles nothing (see core.py)."""
import gc

from .contact import ContactSolver
from .core import RigidCore, SceneCore


class CorePool:
    """Free cores by capacity class. A scene takes one (or has one made) and a finaliser gives it
    back when the scene's solver dies."""

    def __init__(self):
        self.free = {}
        self.taken = {}  # key -> number of cores held by live scenes
        # SceneCores with a contact solver, by core key: each keeps its core and its compiled kernels
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

    def acquire_scene_core(self, key, plan):
        """(scene_core, reused) for a scene of core class `key` with a contact plan: a free SceneCore
        whose contact solver fits the plan (its kernels already compiled), else a new one on a core of
        the class. It keeps that core for good (its kernels are compiled on the core's fields)."""
        for attempt in range(2):
            free = self.scene_cores_free.get(key, [])
            fit = [o for o in free if o.contact.fits(plan)]
            if fit:
                # the smallest that fits: a later, larger scene may still find the larger ones
                o = min(fit, key=lambda o: o.contact.caps)
                free.remove(o)
                self.scene_cores_taken += 1
                return o, True
            if attempt == 0 and self.scene_cores_taken:
                gc.collect()  # dead scenes still holding scene cores give them back
        core, _ = self.acquire(key)
        self.scene_cores_taken += 1
        return SceneCore(core, ContactSolver(core, plan), None), False

    def release_scene_core(self, scene_core):
        self.scene_cores_taken -= 1
        self.scene_cores_free.setdefault(scene_core.core.key, []).append(scene_core)

    def clear(self):
        """Forget the free cores and scene cores (their fields stay allocated until Taichi is reset): the next
        scene of every class allocates a new core."""
        self.free.clear()
        self.scene_cores_free.clear()


POOL = CorePool()
