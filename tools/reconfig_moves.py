"""Paper 001's reconfiguration cases: can single-piece moves reach a better arrangement?

    python tools/reconfig_moves.py [--depth 2] [--max-piece UNITS]

For each case of `reconfig_eval.CASES` (ModQuad modules, thrust limits on, paper 001's fault pattern)
prints the hover Σ T² (the qp allocator's, N²) of the structure as it is, the best arrangement that at
most `--depth` moves reach (`mars_link.reconfig.moves`: one piece splits off along a straight line and
docks back elsewhere, the piece, the rest and the result each able to hover) and those moves, then the
best rebuild on the ground (`best_ground_moves`: the body lands, up to two pieces that fly alone lift
off and come down into other slots; what rests need not hover). Paper 001's plans (disassemble, then
assemble into the same layout) are the other family; the README compares.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from mars_link.core.assembly import layout_of_cells  # noqa: E402
from mars_link.reconfig.moves import HoverCosts, best_ground_moves, best_moves  # noqa: E402
from mars_link.reconfig.placement import nominal_cells  # noqa: E402
from mars_link.config.scenario import eta_after  # noqa: E402
from reconfig_eval import CASES, paper_faults, scenario  # noqa: E402


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--depth", type=positive_int, default=2, help="moves at most (default 2)")
    ap.add_argument("--max-piece", type=positive_int, default=None, help="units a moving piece may have")
    args = ap.parse_args()
    for shape, layout, n_faults in CASES:
        t0 = time.perf_counter()
        model = scenario(layout, paper_faults(n_faults), "qp").model()
        eta = eta_after(model, paper_faults(n_faults), math.inf)
        costs = HoverCosts(model.vehicle, {u: eta[model.unit_slots(u)] for u in model.unit_ids})
        found = best_moves(nominal_cells(model), costs, args.depth, args.max_piece)
        gain = 1.0 - found.best_sum_sq_n2 / found.start_sum_sq_n2
        print(f"{shape} {n_faults} faults: hover sum T^2 {found.start_sum_sq_n2:.5f} N^2 now, "
              f"{found.first_moves} valid first moves, {found.arrangements_seen} arrangements in "
              f"{time.perf_counter() - t0:.1f} s")
        if not found.moves:
            print("  no reachable arrangement is better")
        else:
            print(f"  best {found.best_sum_sq_n2:.5f} N^2 ({100 * gain:.1f} % less) in {len(found.moves)} moves, "
                  f"shape {','.join(layout_of_cells(found.final.values()))}")
            for m in found.moves:
                print(f"    move units {list(m.units)} to cells {list(m.cells)}")
        ground = best_ground_moves(nominal_cells(model), costs)
        if not ground.lifts:
            print("  on the ground: no rebuild is better")
            continue
        gain = 1.0 - ground.best_sum_sq_n2 / ground.start_sum_sq_n2
        print(f"  on the ground: {ground.best_sum_sq_n2:.5f} N^2 ({100 * gain:.1f} % less), shape "
              f"{','.join(layout_of_cells(ground.final.values()))} ({ground.searched} bodies tried)")
        for units, cells in ground.placements:
            print(f"    units {list(units)} lift off and come down at cells {list(cells)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
