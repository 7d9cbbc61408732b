"""The whole gradient matrix (tests/gradient_cases.py, slow cases included) and its summary.

    python benchmarks/bench_gradient_matrix.py [--only SUBSTRING] [--default-only]
                                               [--out benchmarks/results/gradient_matrix.md] [--json FILE]

Runs every case of the table as tests/test_gradient_matrix.py does (gradient_check.execute: autograd
against central finite differences in float64, Richardson-checked; variations in this process, after a
prelude scene, first in a fresh process, float32 against float64) and writes a Markdown report: the
number of cases, passed / failed / known bugs (the table's xfail rows) / FD-unreliable / degenerate /
errors, and the worst relative error |g_ad - g_fd| / max(|g_fd|, scale) per scene, per input kind and
per variation, then every case with its time. Cases run one after another in this process (each builds
its own scene); a case that raises is recorded as an error and the run goes on.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
import traceback
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests")]  # this checkout's genesis_lite and test table

import gradient_cases as gc  # noqa: E402  (sets GS_CHECK_AD_STACK=1 before genesis_lite is imported)
import gradient_check as gk  # noqa: E402
import genesis_lite as gs  # noqa: E402


def _fmt(x):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.1e}"


def _worst(values):
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return max(vals) if vals else float("nan")


def run(cases):
    rows = []
    for i, case in enumerate(cases):
        t0 = time.time()
        try:
            out = gk.execute(case)
        except Exception as exc:  # recorded, and the run goes on
            out = gk.Outcome(case.id, "error", float("nan"), time.time() - t0,
                             f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=4)}")
        verdict = out.status
        if case.xfail:
            verdict = "xfail" if out.status != "ok" else "XPASS"
        rows.append((case, out, verdict))
        print(f"[{i + 1}/{len(cases)}] {out.seconds:6.1f} s  {verdict:13s} worst {_fmt(out.worst)}  {case.id}", flush=True)
        if verdict not in ("ok", "xfail"):
            print(out.report, flush=True)
    return rows


def directions_of(rows, known_bugs=False):
    """(case, DirResult) for every checked direction; known-bug cases only when asked."""
    for case, out, verdict in rows:
        if out.result is None or (bool(case.xfail) != known_bugs):
            continue
        for d in out.result.dirs:
            yield case, d


def report(rows, seconds, argv):
    counts = defaultdict(int)
    for _, _, verdict in rows:
        counts[verdict] += 1
    n = len(rows)
    lines = [
        "# Gradient matrix",
        "",
        f"`python benchmarks/bench_gradient_matrix.py{(' ' + ' '.join(argv)) if argv else ''}`, "
        f"{time.strftime('%Y-%m-%d %H:%M')}, {os.cpu_count()} CPU cores ({platform.machine()}), Taichi CPU backend, "
        f"float64 (float32 rows: a child process), total {seconds / 60:.1f} min, load average at the end "
        f"{os.getloadavg()[0]:.1f}.",
        "",
        "Every case of `tests/gradient_cases.py` (the table `tests/test_gradient_matrix.py` runs; `-m slow` "
        "rows included). Each compares autograd with central finite differences in float64 along every "
        "component (inputs of <= 6 scalars) or 2 random directions (1 per env when batched), with "
        "Richardson-extrapolated differences at h, h/2, h/4 that must agree (else FD-unreliable). "
        "relative error = |g_ad - g_fd| / max(|g_fd|, scale), scale = the norm (rms over random directions) of "
        "the input's finite-difference gradient; a case passes at <= 1e-6. float32 rows also compare "
        f"float32 autograd with float64's (tolerance {gc.F32_TOL:.1e} of the same scale, {gc.F32_TOL_CONTACT:.1e} "
        "in scenes with rigid contact).",
        "",
        "## Summary",
        "",
        "| cases | passed | failed | known bugs (xfail) | fixed known bugs (XPASS) | FD-unreliable | degenerate | "
        "float32 mismatch | errors |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        f"| {n} | {counts['ok']} | {counts['mismatch']} | {counts['xfail']} | {counts['XPASS']} | "
        f"{counts['fd_unreliable']} | {counts['degenerate']} | {counts['f32_mismatch']} | {counts['error']} |",
        "",
    ]

    def group_table(title, key_of, what):
        groups = defaultdict(list)
        for case, out, verdict in rows:
            for k in key_of(case):
                groups[k].append((case, out, verdict))
        lines.extend([f"## {title}", "",
                      f"| {what} | cases | passed | not passed (known bugs) | worst rel. error (cases without a known "
                      "bug) | worst rel. error, known-bug cases | worst float32 vs float64 |",
                      "| --- | --- | --- | --- | --- | --- | --- |"])
        for k in sorted(groups):
            g = groups[k]
            ok = sum(v == "ok" for _, _, v in g)
            bad = [v for _, _, v in g if v != "ok"]
            known = sum(v == "xfail" for v in bad)
            w = _worst([o.worst for c, o, v in g if not c.xfail])
            wk = _worst([o.worst for c, o, v in g if c.xfail])
            w32 = _worst([o.f32_worst for c, o, v in g])
            lines.append(f"| {k} | {len(g)} | {ok} | {len(bad)} ({known}) | {_fmt(w)} | {_fmt(wk)} | {_fmt(w32)} |")
        lines.append("")

    group_table("Per scene", lambda c: [c.scene], "scene")
    group_table("Per variation", lambda c: c.var.tags(), "variation")

    per_input = defaultdict(list)
    per_input_known = defaultdict(list)
    for case, d in directions_of(rows):
        per_input[d.input.split(".")[1]].append(d)
    for case, d in directions_of(rows, known_bugs=True):
        per_input_known[d.input.split(".")[1]].append(d)
    lines.extend(["## Per input kind", "",
                  "| input kind | directions checked | ok | not ok | worst rel. error (cases without a known bug) | "
                  "worst rel. error, known-bug cases |", "| --- | --- | --- | --- | --- | --- |"])
    for k in sorted(set(per_input) | set(per_input_known)):
        ds = per_input[k]
        ok = sum(d.status == "ok" for d in ds)
        lines.append(f"| {k} | {len(ds)} | {ok} | {len(ds) - ok} | {_fmt(_worst([d.rel_err for d in ds]))} | "
                     f"{_fmt(_worst([d.rel_err for d in per_input_known[k]]))} |")
    lines.append("")

    known = [(c, o, v) for c, o, v in rows if c.xfail]
    if known:
        lines.extend(["## Known bugs (xfail rows of the table)", ""])
        for c, o, v in known:
            lines.append(f"- `{c.id}`: {v}, worst rel. error {_fmt(o.worst)}. {c.xfail}")
        lines.append("")
    bad = [(c, o, v) for c, o, v in rows if v not in ("ok", "xfail")]
    if bad:
        lines.extend(["## Not passed (beyond the known bugs)", ""])
        for c, o, v in bad:
            lines.extend([f"### `{c.id}`: {v}", "", "```", o.report.strip(), "```", ""])

    lines.extend(["## Every case", "", "| case | default run | status | worst rel. error | float32 vs float64 | s |",
                  "| --- | --- | --- | --- | --- | --- |"])
    for c, o, v in rows:
        lines.append(f"| `{c.id}` | {'slow' if c.slow else 'yes'} | {v} | {_fmt(o.worst)} | {_fmt(o.f32_worst)} | "
                     f"{o.seconds:.1f} |")
    lines.append("")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", default=None, help="run the cases whose id contains this")
    ap.add_argument("--default-only", action="store_true", help="only the cases of the default (not slow) run")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "gradient_matrix.md"))
    ap.add_argument("--json", default=None, help="also write every direction's numbers here")
    args = ap.parse_args()
    gs.init(backend=gs.cpu, precision="64")
    cases = [c for c in gc.CASES if (args.only is None or args.only in c.id) and not (args.default_only and c.slow)]
    t0 = time.time()
    rows = run(cases)
    text = report(rows, time.time() - t0, sys.argv[1:])
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)
    if args.json:
        Path(args.json).write_text(json.dumps([dict(case=c.id, status=v, seconds=o.seconds, f32_worst=o.f32_worst,
                                                    result=o.result.to_json() if o.result else None)
                                               for c, o, v in rows], indent=1))


if __name__ == "__main__":
    main()
