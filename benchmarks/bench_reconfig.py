"""Reconfiguration planning time vs size: paper 001 Fig. 6 "inversion" tests (spec §12.3).

    python benchmarks/bench_reconfig.py [--sizes 8,16,...,100] [--exhaustive] [--plot PATH] [--quick] [--json]

Shapes (units numbered along the shape's path; the target puts the k-th unit from the end at the
k-th cell from the start; fault-free, as the paper's timing runs presumably were):
  line(N)   one row of N units;
  U(N)      a "∩": a bar along the front row and two legs of round(N/3) units each (corners
            included) hanging rearwards; path up the left leg, along the bar, down the right leg.
            With equal legs the inversion mirrors each leg onto the other;
  spiral(N) a one-unit-wide square spiral with one empty cell between its arms, walked from the
            centre outwards (arm lengths 2, 2, 4, 4, 6, 6, ...).
Columns: R = disassembly layers, asm = assembly layers, states = memoised pieces of Algorithm 2,
alg2 = Algorithm 2 (pruned, the default planner), alg3 = Algorithm 3 on the resulting pieces,
lap = optimal placement (LAP) for the same shape with one rotor of its middle unit failed,
full = Algorithm 2 evaluating every split of every state like the paper's DP (--exhaustive).
Times are the best of --repeats runs, each on a fresh planner (no cache carried over).
The growth order is the log-log slope fitted over N >= 16; "poly5 R^2" is the paper's fit.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from record import Recorder, add_json_option, apply_quick
from mars_link.core.assembly import AssemblyModel
from mars_link.reconfig import solve_placement
from mars_link.reconfig.sequencing import Sequencer

PRESET = "modquad-cf2"
DEFAULT_SIZES = (8, 16, 24, 32, 40, 50, 64, 80, 100)
TARGETS_S = {("spiral", 50): 0.5, ("line", 100): 10.0, ("U", 100): 10.0, ("spiral", 100): 10.0}


def line_path(n: int) -> list[tuple[int, int]]:
    return [(0, c) for c in range(n)]


def u_path(n: int) -> list[tuple[int, int]]:
    leg = round(n / 3)
    width = n - 2 * leg + 2
    if width < 3:
        raise SystemExit(f"U({n}) is too small: needs a bar of at least 3 cells")
    return ([(r, 0) for r in range(leg - 1, -1, -1)] + [(0, c) for c in range(1, width - 1)]
            + [(r, width - 1) for r in range(leg)])


def spiral_path(n: int) -> list[tuple[int, int]]:
    path = [(0, 0)]
    r = c = 0
    arm, turn = 2, 0
    while len(path) < n:
        dr, dc = ((0, 1), (1, 0), (0, -1), (-1, 0))[turn % 4]
        for _ in range(arm):
            r, c = r + dr, c + dc
            path.append((r, c))
            if len(path) == n:
                break
        turn += 1
        arm += 2 * (turn % 2 == 0)
    r0, c0 = min(p[0] for p in path), min(p[1] for p in path)
    return [(r - r0, c - c0) for r, c in path]


SHAPES = {"line": line_path, "U": u_path, "spiral": spiral_path}


def layout_of(path: list[tuple[int, int]]) -> list[str]:
    cells = set(path)
    n_rows = max(r for r, _ in path) + 1
    n_cols = max(c for _, c in path) + 1
    return ["".join("X" if (r, c) in cells else "." for c in range(n_cols)) for r in range(n_rows)]


def inversion(model: AssemblyModel, path: list[tuple[int, int]]) -> dict[int, tuple[int, int]]:
    unit_at = {cell: u for u, cell in model.unit_cells.items()}
    return {unit_at[path[k]]: path[len(path) - 1 - k] for k in range(len(path))}


def target_unit_middle(model: AssemblyModel, path: list[tuple[int, int]]) -> int:
    """The unit half-way along the path (the one whose rotor fails for the LAP timing)."""
    return {cell: u for u, cell in model.unit_cells.items()}[path[len(path) // 2]]


def measure(shape: str, n: int, repeats: int, exhaustive: bool) -> dict:
    path = SHAPES[shape](n)
    model = AssemblyModel.from_layout(layout_of(path), PRESET)
    target = inversion(model, path)
    health = np.ones((n, 4))
    faulty = health.copy()
    faulty[target_unit_middle(model, path) - 1, 0] = 0.0
    row: dict = {"shape": shape, "n": n, "alg2": math.inf, "alg3": math.inf, "lap": math.inf, "full": None}
    for _ in range(repeats):
        dis, asm = Sequencer(model, health).partial_disassembly(target)
        row.update(R=dis.layers, asm=asm.layers, states=dis.states)
        row["alg2"] = min(row["alg2"], dis.time_s)
        row["alg3"] = min(row["alg3"], asm.time_s)
        t0 = time.perf_counter()
        solve_placement(model, faulty)
        row["lap"] = min(row["lap"], time.perf_counter() - t0)
    if exhaustive:
        dis, _ = Sequencer(model, health).partial_disassembly(target, prune=False)
        row["full"] = dis.time_s
        assert dis.layers == row["R"], "pruning changed the answer"
    return row


def growth(rows: list[dict], key: str) -> tuple[float, float]:
    """(log-log slope over n >= 16, R^2 of a degree-5 polynomial fit of time vs n)."""
    pts = [(r["n"], r[key]) for r in rows if r[key] is not None and r[key] > 0]
    big = [(n, t) for n, t in pts if n >= 16]
    slope = float(np.polyfit(np.log([n for n, _ in big]), np.log([t for _, t in big]), 1)[0]) if len(big) >= 2 else math.nan
    if len(pts) >= 7:
        x, y = np.array(pts, dtype=float).T
        fit = np.polyval(np.polyfit(x, y, 5), x)
        r2 = 1.0 - float(np.sum((y - fit) ** 2) / np.sum((y - y.mean()) ** 2))
    else:
        r2 = math.nan
    return slope, r2


def plot(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for shape in SHAPES:
        sel = [r for r in rows if r["shape"] == shape]
        if not sel:
            continue
        line, = ax.loglog([r["n"] for r in sel], [r["alg2"] for r in sel], "o-", label=f"{shape} (pruned)")
        full = [r for r in sel if r["full"]]
        if full:
            ax.loglog([r["n"] for r in full], [r["full"] for r in full], "s--", color=line.get_color(),
                      alpha=0.6, label=f"{shape} (every split)")
    ax.set_xlabel("modules N")
    ax.set_ylabel("Algorithm 2 time [s]")
    ax.set_title("Inversion planning time (paper 001 Fig. 6 shapes)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default=",".join(map(str, DEFAULT_SIZES)))
    ap.add_argument("--shapes", default=",".join(SHAPES))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--exhaustive", action="store_true", help="also time the unpruned DP (N <= --exhaustive-max)")
    ap.add_argument("--exhaustive-max", type=int, default=64)
    ap.add_argument("--plot", metavar="PATH", help="save a log-log PNG of time vs modules")
    ap.add_argument("--quick", action="store_true", help="sizes 8,16,32,50 and one run each")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, sizes="8,16,32,50", repeats=1)
    rec = Recorder.start("bench_reconfig", args)
    sizes = [int(s) for s in args.sizes.split(",")]
    shapes = args.shapes.split(",")
    rows = []
    print(f"{'shape':7s} {'N':>4s} {'R':>3s} {'asm':>3s} {'states':>7s} {'alg2 s':>9s} {'alg3 s':>9s} "
          f"{'lap s':>9s} {'full s':>9s}")
    for shape in shapes:
        for n in sizes:
            row = measure(shape, n, args.repeats, args.exhaustive and n <= args.exhaustive_max)
            rows.append(row)
            full = f"{row['full']:9.4f}" if row["full"] is not None else f"{'-':>9s}"
            print(f"{shape:7s} {n:4d} {row['R']:3d} {row['asm']:3d} {row['states']:7d} {row['alg2']:9.4f} "
                  f"{row['alg3']:9.4f} {row['lap']:9.4f} {full}", flush=True)
    print()
    for shape in shapes:
        sel = [r for r in rows if r["shape"] == shape]
        for key, name in (("alg2", "pruned Alg. 2"), ("full", "every-split Alg. 2"), ("alg3", "Alg. 3")):
            if all(r[key] is None for r in sel):
                continue
            slope, r2 = growth([r for r in sel if r[key] is not None], key)
            print(f"{shape:7s} {name:19s} growth order {slope:5.2f} (log-log slope, N >= 16); poly5 R^2 {r2:.4f}")
            rec.figure(f"growth_{shape}_{key}", slope, "log-log slope", f"{shape}, {name}, N >= 16")
    print()
    for (shape, n), limit in TARGETS_S.items():
        hit = [r for r in rows if r["shape"] == shape and r["n"] == n]
        if hit:
            t = hit[0]["alg2"] + hit[0]["alg3"]
            print(f"target {shape}-{n}: {t:.3f} s planning (Alg. 2 + Alg. 3) < {limit} s: "
                  f"{'PASS' if t < limit else 'FAIL'}")
            (rec.headline if (shape, n) == ("spiral", 50) else rec.figure)(
                f"plan_{shape}_{n}_s", t, "s", f"{shape}-{n} inversion: Alg. 2 + Alg. 3 (target < {limit} s)")
    if args.plot:
        plot(rows, args.plot)
        print(f"plot written to {args.plot}")
    rec.finish()


if __name__ == "__main__":
    main()
