"""Backward of a rollout fed `controls[t]`: the setters' routing of a view's gradient to its base
(genesis_lite/grad/views.py) against torch's own backward of the views (GS_ROUTE_VIEWS=0), by horizon.

    python benchmarks/bench_view_grads.py [--envs 256] [--horizons 100,1000,3000] [--repeats 3]

The scene: assets/urdf/arm.urdf, fixed base, float64, dt = 0.01 s, default options, requires_grad=True. Each
rollout: scene.reset(); for t in range(T): robot.control_dofs_force(controls[t]); scene.step(); loss = squared
position of the last link summed over envs; forward = reset .. loss, backward = loss.backward(). The two ways
alternate in one process (the same compiled kernels), medians of the repeats; the gradients of the two ways are
compared bit for bit.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))  # genesis_lite without an install

import genesis_lite as gs  # noqa: E402  (before torch: gs.init sets torch's OpenMP wait policy)
import torch  # noqa: E402

from common import progress  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=256)
    ap.add_argument("--horizons", default="100,1000,3000")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="write the table here (Markdown)")
    a = ap.parse_args()
    gs.init(backend=gs.cpu, precision="64", logging_level="warning")
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
    robot = scene.add_entity(gs.morphs.URDF(file=str(HERE.parent / "assets" / "urdf" / "arm.urdf"), fixed=True))
    scene.build(n_envs=a.envs)
    gen = torch.Generator().manual_seed(0)
    rows = ["| envs | steps | backward of the views | forward s | backward s | backward / forward | same gradients |",
            "| --- | --- | --- | --- | --- | --- | --- |"]
    horizons = [int(h) for h in a.horizons.split(",")]
    runs = [(T, r, way) for T in horizons for r in range(a.repeats + 1) for way in ("torch", "routed")]
    times, grads = {}, {}
    controls = {T: (0.1 * torch.randn(T, a.envs, robot.n_dofs, generator=gen, dtype=torch.float64)).requires_grad_()
                for T in horizons}
    for T, r, way in progress(runs, desc="rollouts"):
        os.environ["GS_ROUTE_VIEWS"] = "0" if way == "torch" else "1"
        c = controls[T]
        c.grad = None
        t0 = time.perf_counter()
        scene.reset()
        for t in range(T):
            robot.control_dofs_force(c[t])
            scene.step()
        loss = (robot.get_links_pos()[..., -1, :] ** 2).sum()
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        if r > 0:  # the first round warms up
            times.setdefault((T, way), []).append((t1 - t0, t2 - t1))
        grads[(T, way)] = c.grad.clone()
    os.environ.pop("GS_ROUTE_VIEWS")
    for T in horizons:
        same = torch.equal(grads[(T, "torch")], grads[(T, "routed")])
        for way in ("torch", "routed"):
            f = statistics.median(x[0] for x in times[(T, way)])
            b = statistics.median(x[1] for x in times[(T, way)])
            label = "torch's (GS_ROUTE_VIEWS=0)" if way == "torch" else "routed to the base"
            rows.append(f"| {a.envs} | {T} | {label} | {f:.3f} | {b:.3f} | {b / f:.2f} | {'yes' if same else 'NO'} |")
    text = "\n".join(rows)
    print(text)
    if a.out:
        a.out.write_text(text + "\n")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
