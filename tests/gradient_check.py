"""Running one case of the gradient matrix (tests/gradient_cases.py): autograd against central finite
differences in float64, whatever the case's variation.

`run_case` rolls the case's scene out once with autograd and compares every input's gradient with
central finite differences: every component for inputs of at most 6 scalars, else 2 fixed random
directions (with n_envs > 0: one random direction inside each env, so that each env's gradient is
checked on its own). Every input is float64, and so is every finite-difference rollout, which records
the same forward as autograd's (its inputs require grad; nothing calls backward).

Loss: a sum of outputs read after two steps (mid-horizon and last), each weighted by fixed random normal
weights of its shape, so that no gradient is zero by symmetry. Control modes given for one entity take
turns over the horizon.

Finite differences: central differences D(h), D(h/2), D(h/4) with h the input kind's step (INPUTS[..].h
or the scene's Built.fd_h, times max(1, |x|) and Built.fd_scale), extrapolated (Richardson) to
R1 = (4 D(h/2) - D(h)) / 3 and R2 = (4 D(h/4) - D(h/2)) / 3. The two must agree,
|R1 - R2| <= TOL * max(|R2|, scale), and the round-off of a difference quotient, taken as the
loss's round-off over h, must stay below that bound too; the loss's round-off is 2e-15 max(1, |loss|) or,
where larger, 4x what a case measures: the scatter of the loss about a straight line through 5 points
1e-3 h apart (R2's own scatter is ~3.8x the loss's). A direction where they do not is tried again
at h/3, h/10, h/30 (a kink or jump of the model within h: contact on/off, B-spline weights, plastic
yield, the rigid boundary's face choice on the MPM grid), then 3 h, 10 h (round-off); if no level
converges the direction is FD-unreliable (a failure of the case, never a pass).
Pass: |g_ad - R2| <= TOL * max(|R2|, scale), TOL = 1e-6, scale = the norm of the input's
finite-difference gradient (every component), or its root mean square over the random directions
(Gaussian directions: E[(g.d)^2] = |g|^2), so that a true zero is checked as zero. An input whose
gradient is no larger than round-off makes the case "degenerate" (it could not fail): also a failure.

`execute` runs a case with its variation: in this process (after whatever ran here, or after a prelude
scene it builds and differentiates itself), first in a fresh process, or in float32 (a fresh process)
against this process's float64. The fresh processes run this file as a script:
    python tests/gradient_check.py CASE_ID [--precision 32] [--no-fd]
which prints the case's result as JSON on its last line.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # run as a script: the table beside it
from gradient_cases import (CASE_BY_ID, CASES, F32_TOL, F64, INPUTS, OUTPUTS, REPO, SCENES,  # noqa: E402
                            Built, Case, CONTROL_MODES, Variation, _rng_for)

import torch  # noqa: E402

import genesis_lite as gs  # noqa: E402

TOL = 1e-6  # |g_ad - g_fd| <= TOL * max(|g_fd|, scale)
# the steps (times the input kind's h) a direction is tried at when the differences at h do not converge
FD_LADDER = (1 / 3, 1 / 10, 1 / 30, 3.0, 10.0)


@dataclass
class DirResult:
    input: str
    direction: str      # "k=3" (component), "rand0" (random direction), "env1" (random, inside env 1)
    ad: float
    h: float = float("nan")        # the largest finite-difference step
    d_h: float = float("nan")      # central differences D(h), D(h/2), D(h/4)
    d_h2: float = float("nan")
    d_h4: float = float("nan")
    fd_coarse: float = float("nan")  # Richardson (4 D(h/2) - D(h)) / 3
    fd: float = float("nan")         # Richardson (4 D(h/4) - D(h/2)) / 3: the reference
    fwd: float = float("nan")      # one-sided differences at h/4: (f(x + h/4 d) - f(x)) / (h/4)
    bwd: float = float("nan")      # (f(x) - f(x - h/4 d)) / (h/4)
    scale: float = float("nan")
    rel_err: float = float("nan")  # |ad - fd| / max(|fd|, scale)
    status: str = ""               # ok | mismatch | fd_unreliable | degenerate


@dataclass
class CaseResult:
    case_id: str
    loss: float
    dirs: List[DirResult]
    seconds: float
    build_seconds: float
    f32_tol: float = F32_TOL

    @property
    def status(self) -> str:
        s = {d.status for d in self.dirs}
        for k in ("mismatch", "fd_unreliable", "degenerate"):
            if k in s:
                return k
        return "ok"

    @property
    def worst(self) -> float:
        return max((d.rel_err for d in self.dirs if not math.isnan(d.rel_err)), default=0.0)

    def report(self) -> str:
        lines = [f"{self.case_id}: {self.status}, worst rel. error {self.worst:.2e}, loss {self.loss:.6g}"]
        for d in self.dirs:
            lines.append(f"  {d.input:24s} {d.direction:6s} ad {d.ad: .10e} fd {d.fd: .10e} (coarser {d.fd_coarse: .10e}; "
                         f"D(h/4) {d.d_h4: .6e}, one-sided {d.fwd: .6e} {d.bwd: .6e}; h {d.h:.1e}) scale {d.scale:.3e} "
                         f"rel {d.rel_err:.2e} {d.status}")
        return "\n".join(lines)

    def to_json(self):
        return dict(case_id=self.case_id, loss=self.loss, dirs=[asdict(d) for d in self.dirs], seconds=self.seconds,
                    build_seconds=self.build_seconds, f32_tol=self.f32_tol)

    @classmethod
    def from_json(cls, d):
        return cls(d["case_id"], d["loss"], [DirResult(**x) for x in d["dirs"]], d["seconds"], d["build_seconds"],
                   d["f32_tol"])


class Rollout:
    """The scalar loss of a case as a function of its inputs (name -> float64 tensor)."""

    def __init__(self, case: Case, b: Built):
        self.case, self.b = case, b
        self.names = list(case.inputs)
        applied = {**{k: None for k in b.defaults}, **{k: None for k in self.names}}
        self.order = sorted(applied, key=lambda k: INPUTS[k.split(".")[1]].phase)
        rng = _rng_for(case.scene, "weights")
        self.steps = b.out_steps or (b.T // 2 - 1, b.T - 1)
        self.outs = []
        with torch.no_grad():
            for o in case.outputs:
                ent, kind = o.split(".")
                shape = tuple(OUTPUTS[kind](b.ents[ent]).shape)
                self.outs.append((ent, kind, [torch.tensor(rng.normal(size=shape), dtype=F64) for _ in self.steps]))

    def base_values(self) -> Dict[str, torch.Tensor]:
        """Each input's value: the scene's default, else the kind's base; batched: env k's own value."""
        b, vals = self.b, {}
        for name in self.names:
            ent, kind = name.split(".")
            spec = INPUTS[kind]
            rng = _rng_for(self.case.scene, name, "base")
            x = b.defaults.get(name)
            x = np.asarray(spec.base(b, b.ents[ent], ent, rng) if x is None else x, dtype=np.float64)
            if b.n_envs:
                xs = [x] + [x + b.jitter * spec.jitter * k * rng.normal(size=x.shape) for k in range(1, b.n_envs)]
                if spec.symmetric:
                    xs = [0.5 * (a + np.swapaxes(a, -1, -2)) for a in xs]
                x = np.stack(xs)
            vals[name] = torch.tensor(x, dtype=F64)
        return vals

    def defaults(self) -> Dict[str, torch.Tensor]:
        b, out = self.b, {}
        for k, x in b.defaults.items():
            t = torch.tensor(np.asarray(x, dtype=np.float64), dtype=F64)
            out[k] = t.expand((b.n_envs,) + t.shape) if b.n_envs else t
        return out

    def __call__(self, inputs: Dict[str, torch.Tensor]) -> torch.Tensor:
        b = self.b
        values = {**self.defaults(), **inputs}
        b.scene.reset(b.reset_state)
        ctrl = []
        for name in self.order:
            ent, kind = name.split(".")
            spec = INPUTS[kind]
            if spec.phase == 3:
                ctrl.append((spec, b.ents[ent], ent, values[name]))
            else:
                spec.apply(b, b.ents[ent], ent, values[name], None)
        # control modes of one entity take turns: with m of them, the k-th drives steps [k T / m, (k+1) T / m)
        modes = {}
        for spec, e, ent, x in ctrl:
            if spec in CONTROL_MODES:
                modes.setdefault(ent, []).append(spec)
        loss = torch.zeros((), dtype=F64)
        for t in range(b.T):
            for spec, e, ent, x in ctrl:
                turn = modes.get(ent, [spec])
                if len(turn) > 1 and turn.index(spec) != t * len(turn) // b.T:
                    continue
                spec.apply(b, e, ent, x, t)
            b.scene.step()
            if t in self.steps:
                i = self.steps.index(t)
                for ent, kind, ws in self.outs:
                    loss = loss + (ws[i] * OUTPUTS[kind](b.ents[ent]).to(F64)).sum()
        return loss


def directions(case: Case, name: str, x: torch.Tensor, n_envs: int):
    """(label, direction) pairs: every component of an input of at most 6 scalars (unbatched), else 2
    Gaussian directions; batched, one Gaussian direction inside each env."""
    spec = INPUTS[name.split(".")[1]]
    rng = _rng_for(case.scene, name, "directions")
    out = []
    if n_envs:
        for k in range(n_envs):
            d = torch.zeros_like(x)
            d[k] = torch.tensor(rng.normal(size=x.shape[1:]), dtype=F64)
            out.append((f"env{k}", d))
    elif x.numel() <= 6:
        for k in range(x.numel()):
            d = torch.zeros(x.numel(), dtype=F64)
            d[k] = 1.0
            out.append((f"k={k}", d.reshape(x.shape)))
    else:
        for k in range(2):
            out.append((f"rand{k}", torch.tensor(rng.normal(size=x.shape), dtype=F64)))
    if spec.symmetric:
        out = [(lab, 0.5 * (d + d.transpose(-1, -2))) for lab, d in out]
    return out


def prepare(case: Case):
    """Build the case's scene; returns (Built, Rollout, base values)."""
    b = SCENES[case.scene](case.var)
    roll = Rollout(case, b)
    return b, roll, roll.base_values()


def run_case(case: Case, fd: bool = True, tol: float = TOL) -> CaseResult:
    """Autograd gradient of every input, projected on each direction, and (fd=True) its central
    finite differences in float64 at h and h/2 with the verdicts described at the top of the file."""
    t0 = time.time()
    b, roll, base = prepare(case)
    t_build = time.time() - t0
    leaves = {k: v.clone().requires_grad_(True) for k, v in base.items()}
    loss = roll(leaves)
    grads = torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
    grads = {k: (torch.zeros_like(v) if g is None else g) for (k, v), g in zip(leaves.items(), grads)}
    f0 = float(loss.detach())
    results = []

    def f(name, x):
        # the same (gradient-recording) forward as autograd's rollout: inputs that require grad
        vals = {k: v.clone().requires_grad_(True) for k, v in base.items()}
        vals[name] = x.clone().requires_grad_(True)
        with torch.enable_grad():
            return float(roll(vals).detach())

    def estimate(r, name, x, d, h):
        """Central differences at h, h/2, h/4 along d, their Richardson extrapolations, one-sided at h/4."""
        D = []
        for k in (1, 2, 4):
            fp, fm = f(name, x + (h / k) * d), f(name, x - (h / k) * d)
            D.append((fp - fm) / (2 * h / k))
        r.h, (r.d_h, r.d_h2, r.d_h4) = h, D
        r.fd_coarse, r.fd = (4 * D[1] - D[0]) / 3, (4 * D[2] - D[1]) / 3
        r.fwd, r.bwd = (fp - f0) / (h / 4), (f0 - fm) / (h / 4)

    def h_of(name, x):
        spec = INPUTS[name.split(".")[1]]
        return b.fd_h.get(name.split(".")[1], spec.h) * max(1.0, float(x.abs().max())) * b.fd_scale

    def measured_noise():
        # the rollout's own round-off, measured: the loss at 5 points 1e-3 h apart along the first input's
        # first direction, less the straight line through them (least squares; its curvature over 4e-3 h
        # is far below round-off). Iterative solves, ill-conditioned contact systems and rounds that stop
        # where nothing changes leave ~1e-13 of the loss in places (gripper_plane: +-7e-13 of 1.48), many
        # ulps above 2e-15 of it; taken without gradients of its own, so it cannot favour the autograd side
        if not fd:
            return 0.0
        name, x = next(iter(base.items()))
        d = directions(case, name, x, b.n_envs)[0][1]
        dx = 1e-3 * h_of(name, x)
        ks = np.arange(-2.0, 3.0)
        ys = np.array([f0 if k == 0 else f(name, x + (k * dx) * d) for k in ks])
        fit = np.polyval(np.polyfit(ks, ys, 1), ks)
        return float(np.abs(ys - fit).max())

    # R2 = (4 D(h/4) - D(h/2)) / 3 carries ~3.8 sigma / h of a loss scattered by sigma (the measured
    # scatter's largest residual of 5 is ~1-2 sigma): 4x what was measured
    floor = max(2e-15 * max(1.0, abs(f0)), 4.0 * measured_noise())

    def noise(h):
        # round-off of a difference quotient: a rollout's loss carries at least ~10 ulps of its size, or
        # what was measured above, whatever h, and a step too small for the gradient asked for cannot
        # resolve it
        return floor / h

    def converged(r, scale):
        ref = max(abs(r.fd), scale)
        return abs(r.fd_coarse - r.fd) <= tol * ref and noise(r.h) <= tol * ref

    for name, x in base.items():
        dirs = directions(case, name, x, b.n_envs)
        h = h_of(name, x)
        rows = [DirResult(name, lab, float((grads[name] * d).sum())) for lab, d in dirs]
        if fd:
            def scale_of():
                fds = np.array([r.fd for r in rows])
                basis = all(r.direction.startswith("k=") for r in rows)
                return float(np.linalg.norm(fds)) if basis else float(np.sqrt(np.mean(fds ** 2)))

            for r, (lab, d) in zip(rows, dirs):
                estimate(r, name, x, d, h)
            # a direction whose differences do not converge at h is tried again at smaller steps (a kink
            # or a jump within h), then larger ones (round-off); the first level that converges is kept
            scale = scale_of()
            for r, (lab, d) in zip(rows, dirs):
                tried = []
                for level in FD_LADDER:
                    if converged(r, scale):
                        break
                    tried.append((abs(r.fd_coarse - r.fd) / max(abs(r.fd), scale, 1e-300), dict(asdict(r))))
                    estimate(r, name, x, d, h * level)
                if not converged(r, scale) and tried:
                    best = min(tried + [(abs(r.fd_coarse - r.fd) / max(abs(r.fd), scale, 1e-300), dict(asdict(r)))],
                               key=lambda t: t[0])[1]
                    for k, val in best.items():
                        setattr(r, k, val)
            scale = scale_of()
            for r in rows:
                r.scale = scale
                ref = max(abs(r.fd), scale)
                r.rel_err = abs(r.ad - r.fd) / ref if ref > 0 else (0.0 if r.ad == 0 else math.inf)
                if scale <= 100 * noise(r.h):
                    r.status = "degenerate"  # no gradient above round-off: the case cannot fail, fix the case
                elif not converged(r, scale):
                    r.status = "fd_unreliable"
                else:
                    r.status = "ok" if abs(r.ad - r.fd) <= tol * ref else "mismatch"
        results.extend(rows)
    return CaseResult(case.id, f0, results, time.time() - t0, t_build, b.f32_tol or F32_TOL)


def run_in_subprocess(case: Case, precision: str = "64", fd: bool = True, timeout: float = 900) -> CaseResult:
    """The case as the first scene of a fresh process (gs.init(precision=...)), via this file's main."""
    import subprocess

    cmd = [sys.executable, str(Path(__file__).resolve()), case.id, "--precision", precision] + ([] if fd else ["--no-fd"])
    # the child imports this checkout's genesis_lite and solvers, as this process does (not whatever an
    # editable install points at)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=str(REPO), env=env)
    marker = "GRADIENT_CASE_JSON "
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith(marker)]
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"subprocess for {case.id} failed (rc {out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-5000:]}")
    return CaseResult.from_json(json.loads(lines[-1][len(marker):]))


def compare_precision(r32: CaseResult, r64: CaseResult) -> List[Tuple[str, str, float, float, float, bool]]:
    """float32 autograd against float64's (whose own check is r64): per direction (input, direction,
    ad32, ad64, rel, ok) with rel = |ad32 - ad64| / max(|ad64|, scale64), ok: rel <= the scene's tolerance."""
    tol = r64.f32_tol
    rows = []
    for a, b in zip(r32.dirs, r64.dirs):
        assert (a.input, a.direction) == (b.input, b.direction)
        ref = max(abs(b.ad), b.scale if not math.isnan(b.scale) else 0.0)
        rel = abs(a.ad - b.ad) / ref if ref > 0 else math.inf
        rows.append((a.input, a.direction, a.ad, b.ad, rel, rel <= tol))
    return rows


# ================================================================================= a case, whatever its variation
# the scene built and differentiated before a case of process="after" (another size class and solver mix)
PRELUDE = {"arm": "free_box", "free_box": "arm"}
PRELUDE_DEFAULT = "arm"


@dataclass
class Outcome:
    case_id: str
    status: str                    # ok | mismatch | fd_unreliable | degenerate | f32_mismatch | error
    worst: float                   # worst relative error against finite differences (float64)
    seconds: float
    report: str
    result: Optional[CaseResult] = None
    f32_worst: float = float("nan")  # worst |g32 - g64| / max(|g64|, scale)

    @property
    def passed(self):
        return self.status == "ok"


def run_prelude(name: str):
    """Build another scene and differentiate a short rollout of it (for process="after")."""
    first = next(c for c in CASES if c.scene == name and not c.slow and c.var == Variation())
    b, roll, base = prepare(first)
    leaves = {k: v.clone().requires_grad_(True) for k, v in base.items()}
    roll(leaves).backward()


def execute(case: Case) -> Outcome:
    """Run a case with its variation: in this process (after the scenes it ran before, or after a
    prelude scene), as the first scene of a fresh process, or in float32 against this process's float64.
    Never raises for a gradient failure: the outcome says what happened."""
    t0 = time.time()
    v = case.var
    f32_rows, f32_worst = None, float("nan")
    if v.process == "first":
        res = run_in_subprocess(case, precision="64", fd=True)
    else:
        if v.process == "after":
            run_prelude(PRELUDE.get(case.scene, PRELUDE_DEFAULT))
        res = run_case(case)
        if v.precision == "32":
            r32 = run_in_subprocess(case, precision="32", fd=False)
            f32_rows = compare_precision(r32, res)
            f32_worst = max(r[4] for r in f32_rows)
    status = res.status
    if status == "ok" and f32_rows is not None and not all(r[5] for r in f32_rows):
        status = "f32_mismatch"
    rep = res.report()
    if f32_rows is not None:
        rep += f"\n  float32 against float64 (tolerance {res.f32_tol:.1e}):"
        for name, lab, a32, a64, rel, ok in f32_rows:
            rep += f"\n  {name:24s} {lab:6s} ad32 {a32: .8e} ad64 {a64: .8e} rel {rel:.2e} {'ok' if ok else 'MISMATCH'}"
    return Outcome(case.id, status, res.worst, time.time() - t0, rep, res, f32_worst)


def main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case_id")
    ap.add_argument("--precision", default="64")
    ap.add_argument("--no-fd", action="store_true")
    a = ap.parse_args(argv)
    gs.init(backend=gs.cpu, precision=a.precision)
    res = run_case(CASE_BY_ID[a.case_id], fd=not a.no_fd)
    print(res.report(), file=sys.stderr)
    print("GRADIENT_CASE_JSON " + json.dumps(res.to_json()))


if __name__ == "__main__":
    main()
