"""Small helpers shared by the examples: the command line every example accepts (--quick, --out),
progress bars, headless figures, result tables and the robots of example-robot-data.

The examples import it as a sibling module (`python examples/<name>.py` puts examples/ on sys.path).
"""
from __future__ import annotations

import argparse
import os
import site
import sys
import sysconfig
import time
from pathlib import Path

import numpy as np


def parse_args(name: str, doc: str, add_arguments=None):
    """The examples' common command line: --quick (a short run of seconds to a minute, what the tests
    run) and --out (the folder everything is written to, default out/<name>, created here).
    `add_arguments(parser)` adds an example's own options. Returns the parsed namespace."""
    ap = argparse.ArgumentParser(description=(doc or "").strip().splitlines()[0] if doc else None,
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a short run (what the tests run)")
    ap.add_argument("--out", default=os.path.join("out", name), help="folder for figures and files")
    if add_arguments is not None:
        add_arguments(ap)
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    return args


def progress(iterable=None, **kw):
    """A tqdm progress bar on stderr (a plain iterator when tqdm is missing); `total`, `desc` as tqdm.
    The bar updates at most twice a second, so logs of non-interactive runs stay short."""
    try:
        from tqdm import tqdm
    except ImportError:  # progress bars are a nicety, never a reason to fail
        return iterable if iterable is not None else range(kw.get("total", 0))
    kw.setdefault("mininterval", 0.5)
    kw.setdefault("dynamic_ncols", True)
    kw.setdefault("file", sys.stderr)
    return tqdm(iterable, **kw)


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, out, filename, written):
    """Save `fig` as out/filename (PNG, 110 dpi), close it and note the path in `written`."""
    path = os.path.join(out, filename)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    written.append(path)
    return path


def format_table(headers, rows, floatfmt="{:.6g}"):
    """A plain-text table (Markdown pipe syntax, so it pastes into a report): headers and rows of
    strings or numbers."""
    cells = [[c if isinstance(c, str) else floatfmt.format(c) for c in r] for r in rows]
    widths = [max(len(str(h)), *(len(r[i]) for r in cells)) for i, h in enumerate(headers)]
    line = lambda r: "| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    return "\n".join([line(headers), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(r) for r in cells])


def identification_table(names, true, initial, fitted, units=None):
    """Rows name / true / initial / fitted / error % (|fitted - true| / |true|) of an identification,
    as a Markdown table, and the largest error in %."""
    true, initial, fitted = (np.asarray(v, dtype=float).reshape(-1) for v in (true, initial, fitted))
    err = 100.0 * np.abs(fitted - true) / np.abs(true)
    units = units or [""] * len(names)
    rows = [[f"{n} ({u})" if u else n, t, i, f, f"{e:.3f}"] for n, u, t, i, f, e in zip(names, units, true, initial, fitted, err)]
    return format_table(["parameter", "true", "initial", "fitted", "error %"], rows), float(err.max())


def write_text(out, filename, text, written):
    path = os.path.join(out, filename)
    with open(path, "w") as f:
        f.write(text if text.endswith("\n") else text + "\n")
    written.append(path)
    return path


def write_csv(out, filename, header, columns, written):
    """Columns (equal-length sequences) as a CSV file with a one-line header."""
    path = os.path.join(out, filename)
    np.savetxt(path, np.column_stack([np.asarray(c, dtype=float) for c in columns]), delimiter=",",
               header=",".join(header), comments="", fmt="%.9g")
    written.append(path)
    return path


def summary(title, lines, written, t_start):
    """The closing block every example prints: its findings, the files it wrote, its wall time."""
    print(f"\n===== {title}: summary =====")
    for line in lines:
        print(line)
    print("files:")
    for p in written:
        print(f"  {p} ({os.path.getsize(p)} bytes)")
    print(f"wall time {time.time() - t_start:.1f} s")


def robots_dir() -> Path:
    """example-robot-data's robots folder (its pip wheel installs it under cmeel.prefix)."""
    env = os.environ.get("EXAMPLE_ROBOT_DATA_DIR")
    if env:
        return Path(env)
    bases = []
    for getter in (site.getsitepackages, lambda: [site.getusersitepackages()]):
        try:
            bases += list(getter())
        except Exception:
            pass
    bases += [sysconfig.get_paths()["purelib"], sys.prefix]
    for base in bases:
        d = Path(base) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if d.is_dir():
            return d
    sys.exit("example-robot-data is not installed: pip install example-robot-data")


def panda_urdf() -> str:
    return str(robots_dir() / "panda_description" / "urdf" / "panda.urdf")


def repo_path(*parts) -> str:
    """A path inside the repository (assets/...), wherever the example is started from."""
    return str(Path(__file__).resolve().parents[1].joinpath(*parts))



def fit_log_lbfgsb(loss_fn, init, lo, hi, iters, desc="L-BFGS-B", postfix=None):
    """Fit positive parameters by L-BFGS-B (scipy's: a Moré-Thuente line search and bounds) on their
    logarithms, with the gradient from autograd. loss_fn(values) takes a float64 tensor of parameter
    values and returns a scalar tensor; init, lo, hi are the start and the physical bounds (the bounds
    keep the line search from trying a mass or stiffness that makes the simulation diverge). One
    progress-bar tick per iteration; `postfix(values)` gives the bar's extra fields. Returns (losses,
    iterates): the loss and the parameter values at the start and after every iteration."""
    import torch
    from scipy.optimize import minimize

    init = np.asarray(init, dtype=float).reshape(-1)
    cache = {}

    def fun(x):
        leaf = torch.tensor(x, dtype=torch.float64, requires_grad=True)
        loss = loss_fn(leaf.exp())
        (g,) = torch.autograd.grad(loss, leaf)
        cache[x.tobytes()] = float(loss)
        return float(loss), g.numpy().copy()

    x0 = np.log(init)
    losses, iterates = [fun(x0)[0]], [init.copy()]
    bar = progress(total=iters, desc=desc)

    def callback(x):
        losses.append(cache[x.tobytes()] if x.tobytes() in cache else fun(x)[0])
        iterates.append(np.exp(x))
        bar.update(1)
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{losses[-1]:.4g}", **(postfix(iterates[-1]) if postfix else {}))

    res = minimize(fun, x0, jac=True, method="L-BFGS-B", callback=callback,
                   bounds=list(zip(np.log(np.broadcast_to(lo, init.shape)), np.log(np.broadcast_to(hi, init.shape)))),
                   options=dict(maxiter=iters))
    if hasattr(bar, "close"):
        bar.close()
    print(f"L-BFGS-B: {res.nit} iterations, {res.nfev} evaluations: {res.message}")
    return losses, iterates
