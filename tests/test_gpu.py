"""gs.gpu selects Taichi's CUDA backend. Runs only where torch sees a CUDA device (skipped here
otherwise); it needs its own process because gs.init runs once per process."""
import subprocess
import sys

import pytest
import torch

SCRIPT = """
import torch, genesis_lite as gs
gs.init(backend=gs.gpu, precision="32")
assert gs.device.type == "cuda"
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 1)))
scene.build(n_envs=4)
v0 = torch.zeros(4, 6, device=gs.device, requires_grad=True)
box.set_dofs_velocity(v0)
for _ in range(10):
    scene.step()
z = box.get_pos()[:, 2]
assert torch.allclose(z, torch.full_like(z, 1 - 9.81 * 0.01 * 0.01 * 55), atol=1e-4), z
z.sum().backward()
assert torch.allclose(v0.grad[:, 2], torch.full((4,), 0.1, device=gs.device), atol=1e-5), v0.grad
print("ok")
"""


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: gs.gpu cannot be exercised here")
def test_gpu_backend_steps_and_differentiates():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and "ok" in out.stdout, out.stdout + out.stderr
