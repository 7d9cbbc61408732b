"""Stage 6, collision: which geoms can touch (built once, numpy), and the narrow phase (Taichi).

Every candidate pair of geoms gets a fixed set of contact *slots* at build time, so a step has a
fixed amount of work and a fixed computation graph (what Taichi's reverse mode needs): a slot is a
sample point of one geom (the "point side", with a radius) tested against the signed distance
function (SDF) of the other (the "SDF side"):

  pair                        point side                                   SDF side
  plane  x any                sphere centre / capsule ends / box corners /  plane
                              cylinder rims / mesh hull vertices
  sphere x any non-plane      the sphere centre (radius r): exact           the other geom
  capsule x capsule           closest points of the two segments, and each  the other capsule
                              capsule's end points
  box x box                   as other primitive pairs below, plus the      the other box
                              closest points of the edge pair whose axis
                              (cross product) separates the boxes best,
                              where it beats every face axis (edge on edge),
                              and else the points where the edges of one    the face of the
                              box's face cross the rim of the other box's   other box (its
                              face lying on it (face on face: crossed       plane)
                              planks touch only there)
  other primitive pairs,      corners + edge midpoints (box), rim and cap   the other geom
  mesh x primitive,           samples (cylinder), axis samples (capsule),
  mesh x mesh                 hull vertices (mesh), in both directions
  mesh x mesh, mesh x box     plus the closest points of the edge pair      the other volume's
                              whose axis separates the two convex volumes   edge
                              best, where it beats every face axis (edge
                              on edge: geoms.polytope_hull's edges,
                              narrow.func_hull_pair_test), else the points  the face of the
                              where the edges of one's face cross the rim   other (its plane)
                              of the other's best face (face on face: up
                              to N_HULLFACE)

SDFs are exact for plane, sphere, capsule, box and cylinder; a mesh is its convex hull, whose SDF is
that of the intersection of 26 of the hull's own face planes (geoms.hull_planes: the bounding box, then
the face that cuts off the corner farthest outside the hull, one at a time; exact for a hull of up to 20
faces, within 0.2-4.6 % of the mesh's size for example-robot-data's Panda, where a k-DOP of 26 fixed
directions, used before 2026-11-29, reached 8-18 % and put a finger's collision volume 7.9 mm past its
hull). Inside a box, cylinder or mesh the nearest face is ambiguous where faces meet (two stacked
identical boxes touch corner on corner), so the face is chosen by penetration plus a bias towards the
face that looks at the other geom's centre. Two meshes (or a mesh and a box) touch where a hull vertex of
one enters the other's planes, where two edges of their volumes cross edge on edge, and where the edges of
one's face cross the rim of the other's face lying on it, with no vertex of either inside the other (the
hull-edge and hull-face slots; before 2026-12-03 crossed mesh planks passed through each other, ridge on
ridge or flat: tests/test_mesh_hull.py). A rounded hull rests on the other's planes, up to their gap to its
hull.

Which pairs are candidates: geoms of different kinematic trees (other entities, and an entity's other
trees: an MJCF's free bodies, its worldbody's floor); geoms of one tree only with `enable_self_collision`,
never on the same link, nor (Genesis's rules, geoms.candidate_pairs) on adjacent links (one the other's
parent, directly or through fixed-joint links) unless `enable_adjacent_collision`, nor pairs that overlap
with every joint at zero unless `enable_neutral_collision`; never two geoms that cannot move. A cheap test
per pair (the broad phase: the geom's support function against a plane, bounding spheres otherwise) skips
the slots of pairs that are not within the contact margin, so a robot standing on the ground computes only
its feet's slots. A mesh is contacted through at most RigidOptions.max_mesh_contact_points of its hull
vertices (farthest-point sampled, extremes kept).

Modules: geoms.py (host side: geoms, candidate pairs, slots), sdf.py (the SDFs), narrow.py (the step's
stages: geom poses, broad phase, slot geometry).
"""
from .geoms import (BOXEDGE_TOL, CYL_RIM_OTHER, CYL_RIM_PLANE, GEOM_BOX, GEOM_CAPSULE, GEOM_CODE, GEOM_CYLINDER,
                    GEOM_MESH, GEOM_PLANE, GEOM_SPHERE, KDOP_DIRS, N_BOXFACE, N_HULL_CORNERS, N_HULL_EDGES, N_HULLFACE, N_KDOP,
                    SLOT_BOXEDGE, SLOT_BOXFACE, SLOT_CYL_RIM, SLOT_HULLEDGE, SLOT_HULLFACE, SLOT_POINT, SLOT_SEGSEG, ContactBuildError,
                    GeomTable, build_geoms, build_slots, candidate_pairs, geom_box_columns, geom_hull, geom_rotations,
                    link_is_dynamic, sample_points, sdf_distance_ratio)
from .narrow import NO_ADJOINT, func_broad_phase, func_geom_pose, func_slot_geometry
from .sdf import TINY, func_sdf_any, func_sdf_of, func_segment_closest

__all__ = ["build_geoms", "candidate_pairs", "build_slots", "func_geom_pose", "func_broad_phase",
           "func_slot_geometry", "ContactBuildError"]
