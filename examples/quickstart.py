"""Main example: a Panda arm (example-robot-data) under PD control swings from a start pose towards
PD targets, and autograd gives the gradient of a tracking loss with respect to the start angles and
the targets, checked entry by entry against central finite differences.

The loss is the mean squared distance (m^2) between the gripper and a goal point over the whole
motion, not only at its end: under PD control the end pose forgets where the arm started (its
gradient with respect to the start would be ~0), while the path on the way there does not.

    python examples/quickstart.py [--quick] [--steps 100] [--out out/quickstart]

Writes trajectory.csv (joint angles and gripper position per step), gradients.csv (autograd and,
for the checked entries, finite differences) and quickstart.png (joint angles, distance to the goal,
the two gradients as bars).
"""
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch

from example_utils import panda_urdf, parse_args, progress, pyplot, save_figure, summary, write_csv

F64 = dict(dtype=torch.float64)


def main():
    t_start = time.time()
    args = parse_args("quickstart", __doc__, lambda ap: ap.add_argument(
        "--steps", type=int, default=100, help="steps of 10 ms (--quick: 40)"))
    steps = 40 if args.quick else args.steps

    gs.init(backend=gs.cpu, precision="64")
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
    scene.add_entity(gs.morphs.Plane())
    arm = scene.add_entity(gs.morphs.URDF(file=panda_urdf(), fixed=True))
    scene.build()
    print(f"built {arm} in {time.time() - t_start:.1f} s")
    fingers = [arm.get_link(n).idx_local for n in ("panda_leftfinger", "panda_rightfinger")]
    # moderate gains: the arm takes most of a second to settle, as a real arm under impedance control
    arm.set_dofs_kp(torch.tensor([300.0] * 7 + [100.0] * 2, **F64))
    arm.set_dofs_kv(torch.tensor([30.0] * 7 + [5.0] * 2, **F64))
    q0 = torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02], **F64)
    target = torch.tensor([0.5, 0.4, 0.3, -1.8, 0.2, 1.6, 0.6, 0.03, 0.03], **F64)
    goal = torch.tensor([0.45, 0.25, 0.35], **F64)  # m, world frame

    def rollout(q_start, q_target, record=None, bar=False):
        """Loss (m^2): mean over the steps of |gripper - goal|^2."""
        scene.reset()
        arm.set_dofs_position(q_start)
        arm.control_dofs_position(q_target)
        loss = 0.0
        it = progress(range(steps), desc="forward", total=steps) if bar else range(steps)
        for _ in it:
            scene.step()
            grip = arm.get_links_pos()[fingers].mean(0)
            loss = loss + ((grip - goal) ** 2).sum() / steps
            if record is not None:
                record.append(np.concatenate([arm.get_dofs_position().detach().numpy(), grip.detach().numpy()]))
        return loss

    q0_leaf, target_leaf = q0.clone().requires_grad_(True), target.clone().requires_grad_(True)
    rows = []
    t1 = time.time()
    loss = rollout(q0_leaf, target_leaf, record=rows, bar=True)
    t_fwd = time.time() - t1
    t2 = time.time()
    loss.backward()
    t_bwd = time.time() - t2
    g_q0, g_target = q0_leaf.grad.clone(), target_leaf.grad.clone()
    rows = np.array(rows)
    print(f"forward {steps} steps in {t_fwd:.2f} s, backward in {t_bwd:.2f} s; loss {loss.item():.6f} m^2")
    print(f"joint error at the end: {np.abs(rows[-1, :9] - target.numpy()).max():.4f} rad")
    np.set_printoptions(precision=5, suppress=False, linewidth=120)
    print("dloss/dq0     =", g_q0.numpy())
    print("dloss/dtarget =", g_target.numpy())

    # Spot check one start angle (the base joint's: the start matters through the path, not the end
    # pose) and one target (the elbow's), each moved alone by +-h in float64.
    checks = [("q0", 0), ("target", 3)]
    h = 1e-6
    fd = {}
    with torch.no_grad():
        for name, i in checks:
            base = {"q0": q0, "target": target}
            vals = []
            for s in (1.0, -1.0):
                x = {k: v.clone() for k, v in base.items()}
                x[name][i] += s * h
                vals.append(rollout(x["q0"], x["target"]).item())
            fd[(name, i)] = (vals[0] - vals[1]) / (2 * h)
    check_lines = []
    for name, i in checks:
        ad = (g_q0 if name == "q0" else g_target)[i].item()
        rel = abs(ad - fd[(name, i)]) / abs(fd[(name, i)])
        check_lines.append(f"  d loss / d {name}[{i}]: autograd {ad: .9e}  central FD (h={h:g}) {fd[(name, i)]: .9e}"
                           f"  rel. diff {rel:.1e}")
    print("finite-difference spot check (float64):")
    print("\n".join(check_lines))
    worst = max(abs((g_q0 if n == "q0" else g_target)[i].item() - fd[(n, i)]) / abs(fd[(n, i)]) for n, i in checks)
    if worst > 1e-5:  # a wrong gradient must not pass as a demonstration
        raise SystemExit(f"autograd and finite differences disagree (rel. diff {worst:.1e})")

    written = []
    t = np.arange(1, steps + 1) * scene.dt
    write_csv(args.out, "trajectory.csv", ["t"] + [f"q{i}" for i in range(9)] + ["grip_x", "grip_y", "grip_z"],
              [t] + [rows[:, k] for k in range(12)], written)
    fd_q0 = [fd.get(("q0", i), np.nan) for i in range(9)]
    fd_tg = [fd.get(("target", i), np.nan) for i in range(9)]
    write_csv(args.out, "gradients.csv", ["dof", "dloss_dq0", "dloss_dtarget", "fd_dq0", "fd_dtarget"],
              [np.arange(9), g_q0.numpy(), g_target.numpy(), fd_q0, fd_tg], written)

    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    for k in range(7):
        ax[0].plot(t, rows[:, k], label=f"joint {k + 1}")
    ax[0].set_xlabel("t (s)")
    ax[0].set_ylabel("angle (rad)")
    ax[0].legend(fontsize=7, ncol=2)
    ax[0].set_title("joint angles (PD towards the targets)")
    ax[1].plot(t, np.linalg.norm(rows[:, 9:12] - goal.numpy(), axis=1))
    ax[1].set_xlabel("t (s)")
    ax[1].set_ylabel("|gripper - goal| (m)")
    ax[1].set_title(f"loss = mean of its square = {loss.item():.4g} m^2")
    x = np.arange(9)
    ax[2].bar(x - 0.2, g_q0.numpy(), 0.4, label="d loss / d q0")
    ax[2].bar(x + 0.2, g_target.numpy(), 0.4, label="d loss / d target")
    for name, i in checks:
        ax[2].plot(i + (-0.2 if name == "q0" else 0.2), fd[(name, i)], "k*", ms=12)
    ax[2].plot([], [], "k*", label="central finite difference")
    ax[2].set_xticks(x, [f"j{k + 1}" for k in range(7)] + ["f1", "f2"])
    ax[2].set_ylabel("m^2 / rad")
    ax[2].legend(fontsize=8)
    ax[2].set_title("gradients")
    save_figure(fig, args.out, "quickstart.png", written)

    summary("quickstart", [f"Panda, {steps} steps of {scene.dt} s; forward {t_fwd:.2f} s, backward {t_bwd:.2f} s",
                           f"loss {loss.item():.6f} m^2; |dloss/dq0| = {g_q0.norm().item():.4g}, "
                           f"|dloss/dtarget| = {g_target.norm().item():.4g}"] + check_lines, written, t_start)


if __name__ == "__main__":
    main()
