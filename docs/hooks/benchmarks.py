"""mkdocs hook: the benchmarks page, generated from the results files inside every build so it cannot drift.

`benchmarks/bench_*.py --json` writes one JSON file per run into benchmarks/results/ (benchmarks/record.py).
benchmarks/index.md keeps its hand-written introduction; at the marker `<!-- benchmark results -->` this
hook puts a summary table (each benchmark's headline figure beside the bare-JSBSim rate of the same run)
and a section per benchmark with every figure of its latest result and the headline of the older ones.

`python docs/hooks/benchmarks.py` prints the generated page (to read it without mkdocs).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGE = "benchmarks/index.md"
MARKER = "<!-- benchmark results -->"


def _record():
    """benchmarks/record.py (not a package: the benchmarks are scripts)."""
    if "bench_record" in sys.modules:
        return sys.modules["bench_record"]
    spec = importlib.util.spec_from_file_location("bench_record", ROOT / "benchmarks" / "record.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_record"] = module  # (its dataclasses look their module up there)
    spec.loader.exec_module(module)
    return module


def shown(value) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if abs(value) >= 1000:
            return f"{value:,.0f}"
        return f"{value:.3g}" if value != 0 and abs(value) < 1e-3 else f"{value:.4g}"
    return str(value)


def cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def table(head: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def headline_of(doc: dict) -> dict | None:
    figures = doc.get("figures") or []
    return next((f for f in figures if f.get("headline")), figures[0] if figures else None)


def bare_rate(doc: dict) -> str:
    rate = (doc.get("machine") or {}).get("bare_jsbsim", {}).get("real_time_factor")
    return "—" if rate is None else f"{rate:.0f}x"


def commit_of(doc: dict) -> str:
    commit = doc.get("commit")
    if not commit:
        return "—"
    return f"`{commit[:9]}`" + (" (with changes)" if doc.get("dirty") else "")


def in_bare_steps(figure: dict, doc: dict) -> str:
    """A time per call expressed in bare-JSBSim steps of the same run: steadier across machine states."""
    rate = (doc.get("machine") or {}).get("bare_jsbsim", {}).get("steps_per_s")
    scale = {"us": 1e-6, "ms": 1e-3}.get(figure.get("unit", ""))
    value = figure.get("value")
    if not rate or scale is None or not isinstance(value, (int, float)) or isinstance(value, bool):
        return ""
    return f"{value * scale * rate:.3g}"


def results_section(docs: list[dict]) -> str:
    record = _record()
    latest = record.latest(docs)
    if not latest:
        return "No results yet: run a benchmark with `--json` (see benchmarks/README.md).\n"
    out = ["## Latest results\n",
           "Each benchmark's headline figure from its newest results file, beside the bare-JSBSim rate measured in "
           "the same run (a 3x2 assembly at 500 Hz with every rotor written each step, timed before and after the "
           "benchmark). Compare a figure with the bare-JSBSim rate of its own run, not with another day's figure.\n",
           table(["benchmark", "headline", "value", "date (UTC)", "commit", "bare JSBSim", "mode"],
                 [[f"[{name}](#{name})", (h or {}).get("name", "—"),
                   f"{shown((h or {}).get('value'))} {(h or {}).get('unit', '')}".strip(),
                   doc["date"][:16].replace("T", " "), commit_of(doc), bare_rate(doc),
                   "quick" if doc.get("quick") else "full"]
                  for name, doc in sorted(latest.items()) for h in [headline_of(doc)]])]
    by_bench: dict[str, list[dict]] = {}
    for doc in docs:
        by_bench.setdefault(doc["benchmark"], []).append(doc)
    for name, doc in sorted(latest.items()):
        machine = doc.get("machine") or {}
        bare = machine.get("bare_jsbsim") or {}
        out.append(f"## {name}\n")
        out.append(f"`{doc.get('command', '')}` on {doc['date'].replace('T', ' ')}, commit {commit_of(doc)}, "
                   f"version {doc.get('version') or '—'}; {machine.get('cores', '—')} cores, load "
                   f"{shown(machine.get('load_average_1m'))}, Python {machine.get('python', '—')}; the run took "
                   f"{shown(doc.get('wall_s'))} s. Bare JSBSim in this run: "
                   f"{shown(bare.get('steps_per_s'))} steps/s ({bare_rate(doc)} real time; before "
                   f"{shown(bare.get('steps_per_s_before'))}, after {shown(bare.get('steps_per_s_after'))}).\n")
        rows = [[("**" + f["name"] + "**") if f.get("headline") else f["name"], shown(f.get("value")),
                 f.get("unit", ""), in_bare_steps(f, doc), f.get("note", "")] for f in doc.get("figures") or []]
        out.append(table(["figure", "value", "unit", "in bare-JSBSim steps", "note"], rows))
        older = [d for d in by_bench[name] if d is not doc]
        if older:
            out.append("Earlier runs (headline):\n")
            out.append(table(["date (UTC)", "commit", "headline", "value", "bare JSBSim", "mode"],
                             [[d["date"][:16].replace("T", " "), commit_of(d), (h or {}).get("name", "—"),
                               f"{shown((h or {}).get('value'))} {(h or {}).get('unit', '')}".strip(), bare_rate(d),
                               "quick" if d.get("quick") else "full"]
                              for d in reversed(older) for h in [headline_of(d)]]))
    return "\n".join(out)


def render(source: str, docs: list[dict] | None = None) -> str:
    docs = _record().load_results(ROOT / "benchmarks" / "results") if docs is None else docs
    generated = results_section(docs)
    if MARKER in source:
        return source.replace(MARKER, generated)
    return source.rstrip("\n") + "\n\n" + generated


# ----------------------------------------------------------------------------- mkdocs
def on_page_markdown(markdown, page, config, files):  # noqa: ARG001 (mkdocs' hook signature)
    if page.file.src_uri == PAGE:
        return render(markdown)
    return markdown


if __name__ == "__main__":
    print(render((ROOT / "docs" / PAGE).read_text(encoding="utf-8")))
    sys.exit(0)
