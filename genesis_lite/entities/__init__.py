from .rigid_entity import RigidEntity, RigidJoint, RigidLink  # noqa: F401
