"""Genesis's collision/tower scene (50 layers of crossed 0.25 x 2 x 0.1 m boxes, a 7.5 t cylinder dropped on
top (Genesis's default density, 600 kg/m^3, on both sides), dt 4 ms, f32) stepped on genesis_lite or on real Genesis, printing every 25 steps: step, highest box z, last
box z, cylinder z, largest box |vz|, mean layer spacing, wall time (results/genesis_scripts.md, "tower").

    python benchmarks/tower_bounce.py ours 1000                       # this repository's venv
    /path/to/genesis_venv/bin/python benchmarks/tower_bounce.py genesis 1000
"""
import sys, time
import numpy as np
lib = sys.argv[1]; horizon = int(sys.argv[2])
if lib == "genesis":
    import genesis as gs
else:
    import genesis_lite as gs
gs.init(backend=gs.cpu, precision="32", performance_mode=True, logging_level="warning")
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.004), rigid_options=gs.options.RigidOptions(max_collision_pairs=200), show_viewer=False)
scene.add_entity(gs.morphs.Plane())
bw, bl, bh = 0.25, 2.0, 0.1
boxes = []
for i in range(50):
    size = (bw, bl, bh) if i % 2 == 0 else (bl, bw, bh)
    for s in (-1, 1):
        pos = (s * 0.4 * bl, 0, i * (bh - 1e-3) + 0.5 * bh) if i % 2 == 0 else (0, s * 0.4 * bl, i * (bh - 1e-3) + 0.5 * bh)
        boxes.append(scene.add_entity(gs.morphs.Box(size=size, pos=pos)))
cyl = scene.add_entity(gs.morphs.Cylinder(radius=2.0, height=1.0, pos=(0, 0, 50 * bh + 5.0)))
scene.build()
t0 = time.time(); rows = []
for k in range(horizon):
    scene.step()
    if (k + 1) % 25 == 0:
        z = np.array([float(b.get_pos()[2]) for b in boxes]); vz = np.array([float(b.get_vel()[2]) for b in boxes])
        rows.append((k + 1, float(z.max()), float(z[-1]), float(cyl.get_pos()[2]), float(np.abs(vz).max()), float(np.diff(np.sort(z)[::2]).mean())))
        print(lib, *[f"{v:.4f}" if isinstance(v, float) else v for v in rows[-1]], f"{time.time()-t0:.1f}s", flush=True)
