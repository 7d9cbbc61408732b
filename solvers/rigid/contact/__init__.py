"""Stage 7, contact: smooth penalty forces with Coulomb friction, treated implicitly.

The model, per contact slot (see collision.py for where slots come from), with depth d > 0 meaning
penetration, n the normal from the SDF side towards the point side, u the velocity of the point side
relative to the other at the contact point, h the step and d' = d - h (u' . n) the depth at the end
of the step (u' the velocity after it):

    normal     f_n = k delta softplus(d' / delta) + (c / h) delta (softplus(d' / delta) - softplus(d / delta))
    friction   f_t = -mu f_n u_t' / sqrt(|v|^2 + eps^2)        mu = max(mu_a, mu_b)

The stiffness k is RigidOptions.contact_stiffness (1e5 N/m per point; scaled with the mass for a pair heavier
than k (10 ms)^2, law.heavy_mass). The damper c is, by default, the pair's critical damping times
RigidOptions.contact_damping_ratio (1 unless given), 2 zeta sqrt(k m_eff) (at least 4 k h), m_eff the mass the
contact moves along its normal: each side's link weighed through its articulation at the initial configuration,
armature included (law.func_link_invmass; ANYmal's foot moves 4-5 kg, its own mass is 0.35 kg), a static side
infinitely heavy; or the fixed RigidOptions.contact_damping (N s/m per point) when that is given. Until
2026-12-05 the default was the fixed 4e4 N s/m with k = 1e6 N/m: it gave a 0.3 kg foot a damping time m / c ~
1e-5 s (1e-4 s with rotor inertia) that no practical step resolves, and the quadruped drops converged slowly as dt
shrank (issue #24, benchmarks/results/workprecision_quadruped_starts.md). With the critical damper at 1e6 N/m a
sliding box's friction was biased at fine steps (+3.9e-3 m from Coulomb's slide at 0.3125 ms); at 1e5 N/m it is
not (-2.8e-4 m, tests/test_contact.py). Traced 2026-12-06: the bias follows the depth a contact rests at, mg / k per
point, against contact_smoothing (5e-6 m), not the stiffness itself. Within a few smoothing widths of zero depth the
front and back points of a sliding box have different slopes, the frictionless solve's loads f2 sum to less than the
weight (0.936 of it for a 100 g box at 1e5 N/m, RK4 at dt = 0.25 ms), and friction's load, predicted with Coulomb's
forces of those f2 (step 3), misses part of the load that friction's torque moves onto the leading edge (1.2 %
there): the box brakes 0.57 % short of mu g at dt = 1 ms (0.66 % with RK4 at 0.25 ms), a 100 g box at the default
stiffness as a 1 kg box at 1e6 N/m (their depths are equal; with contact_smoothing=5e-7 the 100 g box brakes 0.0045
% short, RK4 at 0.25 ms). Open. A probe of 2026-12-06 (not kept): a second prediction in the fused step, Coulomb's
forces of the first prediction's loads applied to A2 again (one more back-substitution), brought the 100 g box to
-0.021 %, a 300 g box to -0.0055 % and the 1 kg box to -4e-5 %, and cost the 1,024-env quadruped 7-18 % a step (RK4,
implicitfast), where its feet rest many smoothing widths deep and need no second one: a cure should run it only
where contacts are that shallow (and on the gradient path too). Strict xfails in tests/test_contact.py
(LIGHT_LOAD_GAP).
The normal force is a spring on the end-of-step depth plus a damper on the overlap gained over the
step, (c / h)(d'+ - d+), which for a contact that stays in overlap is -c (u' . n) (the familiar
spring-damper) and for one that starts apart acts only on the part of the step spent in overlap.
Because the force is a function of the end-of-step depth, a pair whose gap closes within the step is in
contact in that step (a speculative contact): a body arriving at 20 m/s stops at the surface instead
of being caught one step deep (the broad phase widens its margin by the distance the pair can close in
h, and a slot counts while its current or its predicted depth is within the margin). The predicted
depth moves the two sides as the integrator does, each link turned by exactly h w about its origin
(func_rot_excess: the tangent h (w x r) plus Rodrigues' remainder), not along the tangent: with the
tangent alone, a box spinning at 1e3 rad/s 6 cm above the ground "reached" 1.7 m below it and the
ground threw it at 28.8 m/s; two boxes 1 m apart pushed each other (issue #21). Friction follows
Coulomb's law with the normal force the step actually applies, and is viscous below the slip speed eps:
RigidOptions.friction_smoothing (1e-3 m/s), at most friction_smoothing_accel times h (0.25 m/s^2 by default:
below h = 4 ms; passes.func_slip_eps), so that the law converges to Coulomb's as dt shrinks.

Limits (issue #21). A penalty contact stops a body within a step only when (k + c / h) times the
depth it allows outweighs the body's momentum per step and its load: a box at 1e6 m/s (1e4 m per step)
or a 400 t box on four corners of 1e5 N/m, were its stiffness not scaled with its mass, goes through. The report
pass records, per env, the first
contact that ends a step deeper than DEEP_FRACTION of the thinner geom's half thickness, and the scene
warns (ContactPenetrationWarning, ContactSolver.watch: a read after each of the first 16 steps, then
every 16th), naming the geoms, the step and the remedy (smaller dt or more substeps for a fast body, a
larger contact_stiffness for a heavy one; with 1e10 N/m the 400 t box rests within 0.1 mm); once per
pair of geoms, for at most MAX_DEEP_WARNINGS (3) pairs a scene, so that a body placed inside another at
the start does not silence a tangle later in the run.
Known gap: a point of one box beside an edge of another box, level with its face (a box sliding over
the edge of the one below it), is tested against the side face (the nearest feature), and the step's
linear prediction along that face's normal closes a gap that never closes: a horizontal kick (whose
aftermath broke Coulomb's bound until the bound rounds, step 5 below: tests/test_faults_contact.py).

Time stepping. The forces are linearly implicit (backward Euler on the linearised force, as the
joint-limit springs): f_n is linearised about the predicted depth d - h (u . n), which makes it
linear in u' with slope B = (c + h k) sigmoid; each contact contributes J^T W J to the generalised mass
matrix (W the 3x3 block on the contact's relative velocity) and J^T f to the force. One evaluation's
solve runs in steps (func_contact_solve), because Coulomb's law ties the friction to a normal force that
only the solve determines (a stiff implicit contact is a velocity constraint: its force is whatever
stops the approach, far from the explicit penalty force of the state), and because a speculative
contact's linear force pulls where another contact stops the body first:

 1. every candidate normal contact: A1 = M + sum J^T (h B n n^T) J, qacc_candidates = A1^-1 force; each
    contact's normal force in it, f1 = f_n(u1), from the implicit law at the resulting velocity.
 2. without the contacts whose linear force at u1 pulls (a speculative contact that another contact
    stopped first, or one that separates), and with the candidates (below) linearised again about u1:
    A2, qacc_normal (the normal solve), and its normal forces f2. (Dropping a contact whose force is 0 at the
    solution leaves the solution unchanged, so the removal is continuous.)
 2b. normal rounds: the contacts of step 2 are those whose law pushed at u1, which need not be those that
    push at the solution (a contact dropped there can be driven in by the others: in a pile of thrown
    bodies, a box point 1.25 cm from a cylinder closing at 2.8 m/s ended the step 3.9 cm deep, and the
    tangle that followed threw bodies at 300 m/s). The frictionless step with every linear law clipped
    at 0 minimises a convex energy, 1/2 x^T M x - f^T x + sum (law(x))+^2 / (2 W) (W the law's slope), and
    its minimiser is the solution of the system whose contacts are exactly the laws that push there.
    Each round (rounds.func_normal_round) checks that at the last solution; where a law pushes outside
    the system or pulls inside it, it moves from the round's start towards that solution (the whole way
    if the energy falls, else to the energy's minimum along the way: an exact line search of a piecewise
    linear derivative), takes the laws that push there as the system's contacts and solves again, at
    most NORMAL_ROUNDS (8) times. The energy falls at every round, so no set comes back and the rounds
    end at the exact set (2 to 5 rounds in a tumbling pile's steps; none where step 2's set is right,
    as for robots standing or walking). The solve's value depends on the set only through the last
    system, so the gradient path records each round's change of the system (a pass with its adjoint)
    and the last solve, not the search.
 3. Coulomb's forces -mu f2 g2 (g2 the smoothed slip direction of u2) applied to A2 (a back-substitution
    with its factor) predict each contact's slip speed at the end of the step, v = (u2 + h J A2^-1 J^T
    f_c)_t . g2, smoothly clipped at 0 (a slip that would reverse sticks).
 4. the final system adds friction as a viscosity eta = mu f2 / sqrt(v^2 + eps^2) (f2 here friction's load:
    the law's force with Coulomb's forces applied, see after step 5, or with RigidOptions(friction_load=
    "frictionless") the frictionless solve's normal force) (the secant of the
    law at the predicted slip, so the implicit step can stop a contact but never reverse it: while a
    contact slides, eta |u_t'| = mu f2 to the accuracy of the prediction, exact for a body whose contact
    points slip alike; a sticking contact gets eta = mu f2 / eps, the static friction of a stiff
    damper), and drops the speculative contacts whose f2 pulled: A3 = A2 + sum J^T dW J, qacc = A3^-1
    (force + sum J^T dF).
 5. bound rounds: the prediction of step 3 can be far off where a stiff contact's Coulomb force
    overshoots its own small slip (two boxes pressed together at 100 N whose faces slip sideways at
    0.1 m/s: the predicted reversal turns the boxes and makes the ground corners of one of them
    "stick"; their viscosity mu f2 / eps then had no bound in the final solve, and a box pushed into
    a resting one lost 97 % of its momentum in one step, 34 N of friction on 2.4 N of normal force).
    After the final solve, each contact whose friction at the slip it gives, eta |u_t|, exceeds
    Coulomb's bound mu f2 by more than BOUND_TOL (1 %) takes the law's secant at that slip, eta =
    mu f2 / sqrt(|u_t|^2 + eps^2) (continuously: passes.func_bound_eta), and the system is solved
    again, at most BOUND_ROUNDS (8) times, stopping at the first round that changes nothing (the
    pushed box keeps 1.860 of its 2 N s; the Coulomb floor is 1.804). The viscosities only decrease,
    so A stays positive definite and friction dissipative. A contact within the bound keeps its
    viscosity, however far from the smoothed law (the viscous creep of a sticking foot below eps):
    ANYmal standing runs a round in 1 of 1,385 evaluations, a box sliding in none.
    The same rounds keep the final system's normal laws to those that push: a law that pulls at the last
    solution, beyond its round-off, is released (its law and its friction leave the system), and a law
    out of the system that pushes there (released in an earlier round, or left out of the frictionless solve:
    friction moves load onto it) comes back, once a step, with the friction pass's viscosity (none for a law
    the frictionless solve left out) or, where lower, the law's secant at its slip (passes.func_release_slot).
    The laws of step 4 are those that pushed in the frictionless solve,
    and friction can pull a body off them: before (2026-11-28) a cube that a Panda's pads lifted by
    friction stayed glued to the ground, the ground's laws pulling it down with up to 3.6 N against its
    0.38 N weight; a 38 g cube did not leave the ground at all, and in float32 the grasps threw the cube
    (tests/test_grasp.py; Genesis's franka_cube scene, benchmarks/franka_cube_precision.py, now ends at
    z = 0.1847 m in float32 and float64 on 2026-12-05's evening, 0.1850 with the fixed damper of before; Genesis
    0.1832). Released for good (no return within the step),
    the points of a pad's face that pulled while the face pushed left its load on two or three points,
    and the cube spun in the pads; released by pairs of geoms, a pad's face kept a +-23 N couple of
    points and threw the cube in float32. The set changes are not a line search (step 2b's): a law whose
    solution lies between its two sets (it pulls when in, pushes when out) ends out, a push of up to ~1 N
    missing for that step (a box sliding over an edge), rather than in and pulling. A line search would not
    cure the known failure these rounds leave (a 192 g cube lifted at once turns in a Panda's pads,
    tests/test_grasp.py): with the set exact for its viscosities the cube still tilts; the viscosities are
    the cause (friction's bound from the frictionless loads, lowered at intermediate rounds' slips).
Steps 1, 2 and 4 factorise, 2b once per round, 3 reuses the last normal factor, 5 factorises once per round. Candidates: the linearisation at the
start-of-step velocity misses a gap that closes only because the motion changes within the step (two
boxes falling together, the lower one stopped: their relative velocity is ~0 at the start). A slot whose
gap the two bodies' speeds could close within the step is in the system from step 1 with the ~0 force
and slope of that linearisation; between steps 1 and 2 its law is linearised again at the velocity of
the first solve (a Newton step), and it acts if the law pushes there. Contacts acting at the start keep
their first linearisation (linearising them again too left a 30-link chain on the ground swinging) where the
start-of-step velocity predicts them in contact; predicted further out than a few contact widths, their first
linearisation has almost no slope, and they take the tangent at the first solve's velocity too, wholly from ten
widths out (passes.func_relinearise_share: continuous, and a box falling onto one just stopped is caught).
The passes between the solves (link velocities
of a dof vector, per-slot forces, accumulation onto the dofs) are Taichi-differentiated kernels; the
solves have hand-written adjoints (ContactSolver.solve_grad runs them in reverse; the gradient path
keeps each bound round's starting solution and factor for its adjoint; the normal and the bound rounds each run
one kernel whatever the round, the round read at run time, and their backward rebuilds a round's shared
forward values before its adjoint).

Friction's load (RigidOptions.friction_load). The frictionless solve's normal forces f2 miss the load that
friction itself moves between a body's contacts (a box sliding on a face presses its leading edge; a
standing robot's splayed legs load their feet through friction): the final normal forces differ from f2,
and so should the friction bound. By default ("coulomb", since 2026-12-02) the load is taken at the velocity
of step 3 (passes.func_coulomb_load: the law's force with Coulomb's forces applied, f2 + r (f_law(u_c) - f2), r
the share of Coulomb's force that acts, at least 0, at most LOAD_SHIFT = 2 times f2), and the bound rounds
bound friction by mu times that load or, where less, the law's force at the round's solution
(passes.func_coulomb_bound: the load was a prediction). Measured 2026-12-02: a sliding box's error against
Coulomb's slide falls at first order, -9.9e-3, -2.5e-3, -6.1e-4, -2.4e-4 m at 10, 2.5, 0.625, 0.3125 ms
("frictionless": -9.9e-3, -2.0e-3, +1.2e-3, +3.2e-3 m, its f2 summing to 9.70 N for a 9.81 N box while it
pitched); ANYmal's standing posture converges (its base, every 50 ms of t = 0.5 .. 1 s, moves by 8.9e-5,
6.0e-5, 4.8e-5 m per halving of dt from 5 to 0.6 ms; "frictionless": 2.0e-4, 1.2e-4, 2.5e-4 m;
tests/test_contact.py); a box sliding over an edge stays in Coulomb's cone in all of its ~1,500 face steps
("frictionless": one step 0.6 N over; tests/test_faults_contact.py). Without the rounds' second bound the
predicted load left that cone in 6 steps by up to 3.4 N. The thrown piles of tests/workers/broad_phase_pile.py
stay bounded (seeds 1-30: at most 7.6 m/s and 61 rad/s); one of them went to 350 rad/s until a free body's gyroscopic moment became
implicit the same day (solvers/rigid/bias.py).

Every term is differentiable in the state and in mu, k and c; the kinks are the contact's on/off (at
the margin, where the force is below 1e-8 k delta, and where the force of the current and of the
predicted state both stop pushing: fast separation; a slot predicted out by more than a few widths is linearised
again at u1 whether it counts as acting or as a candidate, passes.func_relinearise_share), the removals of steps
2 and 4 and the rounds' choices (continuous in the frictionless solve: a contact enters or leaves where its
force is 0, see above) and the bound rounds' tolerance band (continuous, piecewise linear). Not continuous
(measured 2026-12-05): where a law enters the normal system at zero force, the system A2 that step 3 uses for
Coulomb's response gains that law's whole stiffness, so the slips it predicts, and the viscosities of step 4, jump
(a 2 kg box set exactly on its face, with the heavy-pair threshold tried at 1 kg: 1.5e-5 m in one step between
starting heights 1.5e-9 m apart; a 6 kg box landing on a corner with the fixed damper is kinked every ~1e-6 m of
its drop height, tests/test_contact.py). Gradients are the exact derivatives of this smoothed, time-discretised
model where it is smooth (what tests/test_contact.py checks against finite differences); they approach those of
hard contact and exact Coulomb friction only as delta, eps and dt go to 0.

The part of J^T W J that lives on one kinematic tree (a contact against a static geom, and the two
diagonal blocks J_a^T W J_a, J_b^T W J_b of a contact between moving links a and b) is accumulated like
composite inertia (a 6x6 block per link, summed up the tree: AccBank), so it fits the tree sparsity of
M. The coupling -(J_a^T W J_b + J_b^T W J_a) between two moving links does not: scenes with such contact
pairs (objects stacked or touching each other, self-collision) accumulate it per link pair into
`mass_cross` and factor M over its envelope (func_factor_solve_dense: a skyline L D L^T, the bodies
ordered by starting height, whose cost follows the band the contacts make, ~24 of the 100-box tower's
606 dofs, not n^3); scenes whose contacts all involve a static geom (robots on the ground) keep the
tree factorisation, and so, without gradients, does each evaluation of a dense scene in which no listed
slot couples two moving links (linalg.func_tree_env: mass_cross is then zero; a Panda beside a box it does
not touch steps as the Panda alone, to the bit, its step's kernel 15.8 -> 9.1 us with the narrow phase's
branches, tests/test_contact.py; a robot with self-collision whose links do not touch solves as without it). (Dropping the coupling is not an option: stacked bodies then close the gap between them twice per step, or half of it when the blocks are
doubled, and with the force's clip at 0 a stack of boxes ends in a limit cycle.)

Dynamics stages (each one loop over elements, see ../core.py): geom poses, broad phase, clear the
per-link (and per-link-pair) accumulators, slots (geometry + normal force, accumulated onto the two
links, and the slot's data for the passes), sum up the tree, project onto the dofs (force += J^T f,
M += J^T W J), and with moving pairs the cross terms. The passes of the solve repeat the accumulation
for their own forces.

(The stages live one concern a file: law.py the force law, slots.py the dynamics stages, banks.py the
per-link sums, passes.py the passes between the solves, rounds.py the normal rounds (step 2b), linalg.py the factorisations and solves with their
adjoints, solve.py their order, plan.py the host-side model, solver.py the fields and launches,
report.py what the user is told.)
"""
from .linalg import func_factor_solve_dense, func_solve_grad_dense, func_tree_env
from .plan import ContactPlan
from .report import ContactPenetrationWarning
from .slots import CONTACT_STAGES
from .solve import func_contact_solve
from .solver import ContactSolver
from ..collision import ContactBuildError

__all__ = ["ContactPlan", "ContactSolver", "ContactBuildError", "ContactPenetrationWarning", "CONTACT_STAGES",
           "func_contact_solve", "func_factor_solve_dense", "func_solve_grad_dense", "func_tree_env"]
