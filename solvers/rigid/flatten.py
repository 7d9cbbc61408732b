"""Model flattening: the entities of a scene (model.EntityModel, numpy) as one kinematic tree in numpy.

Links, joints and dofs of every entity are numbered one after another (an entity's links, qs and dofs
start at entity_link_start / entity_q_start / entity_dof_start); each joint gets its type code, its
q and dof offsets; each dof its link, its parent in the dof tree (the previous dof of its link, else
the last dof of the nearest ancestor link that has dofs), its ancestors (np_dof_anc and the pairs
np_anc_pairs that the mass matrix's sparsity follows) and its mimic leader. The core's fields are
filled from these arrays at build (RigidSolver), and the contact plan reads the tree from them.
Arrays are named np_<field> after the core's field they fill.
"""
from typing import List

import numpy as np

from .kinematics import JOINT_FIXED, JOINT_FREE, JOINT_PRISMATIC, JOINT_REVOLUTE
from .model import JOINT_NQ, JOINT_NV, EntityModel

# a joint's limit constraint without parameters of its own: (timeconst: the scene's, dampratio, MuJoCo's solimp)
DEFAULT_LIMIT_SOL = (np.nan, 1.0, 0.9, 0.95, 1e-3, 0.5, 2.0)
JTYPE = {"fixed": JOINT_FIXED, "free": JOINT_FREE, "revolute": JOINT_REVOLUTE, "prismatic": JOINT_PRISMATIC}


class FlatModel:
    """The entities' links, joints and dofs as one tree of numpy arrays (see the module docstring).
    n_links, n_qs, n_dofs: the scene's sizes; use_mimic: honour URDF <mimic> joints."""

    def __init__(self, models: List[EntityModel], use_mimic: bool):
        parent, jtype, qstart, dstart, ndof, jpos, jquat, jaxis, ent = [], [], [], [], [], [], [], [], []
        self.entity_link_start, self.entity_q_start, self.entity_dof_start = [], [], []
        q0, lo, hi, eff, damp, fl, arm, stiff, sref, limsol = [], [], [], [], [], [], [], [], [], []
        mass, com, inertia = [], [], []
        dof_link, dof_q = [], []
        nl = nq = nd = 0
        for i_e, m in enumerate(models):
            self.entity_link_start.append(nl)
            self.entity_q_start.append(nq)
            self.entity_dof_start.append(nd)
            for l in m.links:
                parent.append(l.parent + nl if l.parent >= 0 else -1)
                jtype.append(JTYPE[l.joint_type])
                qstart.append(nq)
                dstart.append(nd)
                ndof.append(JOINT_NV[l.joint_type])
                jpos.append(l.joint_pos if l.joint_type != "free" else np.zeros(3))
                jquat.append(l.joint_quat if l.joint_type != "free" else np.array([1.0, 0, 0, 0]))
                jaxis.append(l.joint_axis)
                ent.append(i_e)
                mass.append(l.mass)
                com.append(l.com)
                inertia.append(l.inertia)
                if l.joint_type == "free":
                    q0.extend(list(l.joint_pos) + list(l.joint_quat))
                    for k in range(6):
                        dof_link.append(len(parent) - 1)
                        dof_q.append(-1)
                        lo.append(-np.inf); hi.append(np.inf); eff.append(np.inf)
                        damp.append(0.0); fl.append(0.0); arm.append(0.0); stiff.append(0.0); sref.append(0.0)
                        limsol.append(DEFAULT_LIMIT_SOL)
                elif l.joint_type in ("revolute", "prismatic"):
                    q0.append(0.0)
                    dof_link.append(len(parent) - 1)
                    dof_q.append(nq)
                    lo.append(l.limit[0]); hi.append(l.limit[1])
                    # URDFs write effort="0" for 'unspecified': no limit
                    eff.append(l.effort if l.effort > 0 else np.inf)
                    damp.append(l.damping); fl.append(l.frictionloss); arm.append(l.armature)
                    stiff.append(l.stiffness); sref.append(l.springref)
                    limsol.append((DEFAULT_LIMIT_SOL[:2] if l.limit_solref is None else tuple(l.limit_solref))
                                  + (DEFAULT_LIMIT_SOL[2:] if l.limit_solimp is None else
                                     tuple(float(x) for x in l.limit_solimp)))
                nq += JOINT_NQ[l.joint_type]
                nd += JOINT_NV[l.joint_type]
            nl += m.n_links
        self.n_links, self.n_qs, self.n_dofs = nl, nq, nd
        self.qpos_len, self.qvel_len = max(nq, 1), max(nd, 1)  # clamp bounds of masked-out reads
        self.np_link_parent = np.array(parent, dtype=np.int32)
        self.np_link_jtype = np.array(jtype, dtype=np.int32)
        self.np_link_q_start = np.array(qstart, dtype=np.int32)
        self.np_link_dof_start = np.array(dstart, dtype=np.int32)
        self.np_link_ndof = np.array(ndof, dtype=np.int32)
        self.np_link_jpos = np.array(jpos, dtype=float).reshape(nl, 3)
        self.np_link_jquat = np.array(jquat, dtype=float).reshape(nl, 4)
        self.np_link_jaxis = np.array(jaxis, dtype=float).reshape(nl, 3)
        self.np_link_entity = np.array(ent, dtype=np.int32)
        self.np_link_mass = np.array(mass, dtype=float).reshape(nl)
        self.np_link_com = np.array(com, dtype=float).reshape(nl, 3)
        self.np_link_inertia = np.array(inertia, dtype=float).reshape(nl, 3, 3)
        self.np_qpos0 = np.array(q0, dtype=float).reshape(nq)
        self.np_dof_link = np.array(dof_link, dtype=np.int32)
        self.np_dof_q = np.array(dof_q, dtype=np.int32)
        self.np_dof_limit = np.stack([np.array(lo, float), np.array(hi, float)], -1).reshape(nd, 2)
        # the limit constraint's (timeconst, dampratio, dmin, dmax, width, mid, power) per dof; timeconst nan: the
        # scene's (RigidSolver)
        self.np_dof_limit_sol = np.array(limsol, dtype=float).reshape(nd, 7)
        self.np_dof_effort = np.array(eff, dtype=float).reshape(nd)
        self.np_dof_damping = np.array(damp, dtype=float).reshape(nd)
        self.np_dof_frictionloss = np.array(fl, dtype=float).reshape(nd)
        self.np_dof_armature = np.array(arm, dtype=float).reshape(nd)
        self.np_dof_stiffness = np.array(stiff, dtype=float).reshape(nd)
        self.np_dof_springref = np.array(sref, dtype=float).reshape(nd)
        # dof tree: a dof's parent is the previous dof of its link, else the last dof of the
        # nearest ancestor link that has dofs
        dof_parent = np.full(nd, -1, dtype=np.int32)
        for i_d in range(nd):
            i_l = dof_link[i_d]
            if i_d > dstart[i_l]:
                dof_parent[i_d] = i_d - 1
            else:
                p = parent[i_l]
                while p >= 0 and ndof[p] == 0:
                    p = parent[p]
                dof_parent[i_d] = dstart[p] + ndof[p] - 1 if p >= 0 else -1
        self.np_dof_parent = dof_parent
        # URDF <mimic>: follower dof -> leader dof of the same entity
        self.np_mimic = np.zeros((max(nd, 1), 3))
        self.np_mimic[:, 0] = -1
        if use_mimic:
            for i_e, m in enumerate(models):
                dof_of = {}
                d = self.entity_dof_start[i_e]
                for l in m.links:
                    if l.joint_type in ("revolute", "prismatic"):
                        dof_of[l.joint_name] = d
                    d += JOINT_NV[l.joint_type]
                for l in m.links:
                    if l.mimic is not None and l.joint_name in dof_of and l.mimic.joint in dof_of:
                        self.np_mimic[dof_of[l.joint_name]] = (dof_of[l.mimic.joint], l.mimic.multiplier, l.mimic.offset)
        self.has_mimic = bool((self.np_mimic[:, 0] >= 0).any())
        # the mimics folded into the dynamics (inertia.func_fold_matrix): a follower with no dof below it,
        # beside its leader (the same parent dof), the leader's only such follower and itself no follower.
        # Its motion is then m times the leader's in every solve, and its inertia, forces and contacts act
        # on the leader (a rigid coupling, as an equality constraint in MuJoCo or Genesis); other mimics
        # keep the copy at integration only (integrate.func_integrate_qvel)
        self.np_fold_leader = np.full(max(nd, 1), -1, dtype=np.int32)  # a folded follower's leader, else -1
        parents = {int(p) for p in dof_parent[:nd] if p >= 0}
        for f in range(nd):
            lead = int(self.np_mimic[f, 0])
            if (lead >= 0 and lead != f and dof_parent[f] == dof_parent[lead] and f not in parents
                    and self.np_mimic[lead, 0] < 0 and lead not in self.np_fold_leader):
                self.np_fold_leader[f] = lead
        self.has_fold = bool((self.np_fold_leader >= 0).any())
        anc = np.zeros((max(nd, 1), max(nd, 1)), dtype=np.int32)
        for i in range(nd):
            j = i
            while j >= 0:
                anc[i, j] = 1
                j = dof_parent[j]
        self.np_dof_anc = anc
        pairs = [(i, j) for i in range(nd) for j in range(i + 1) if anc[i, j]]
        self.np_anc_pairs = np.array(pairs, dtype=np.int32).reshape(-1, 2)
