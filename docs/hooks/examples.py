"""mkdocs hook: guides/examples.md, made inside every build from examples/README.md and the scripts
themselves, so the page shows what the test suite runs (a docs page cannot link outside docs/).

`python docs/hooks/examples.py DIR` writes the page into DIR (to read it without mkdocs).
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
PAGE = "guides/examples.md"
LANGUAGES = {".py": "python", ".txt": "text"}


def examples_page() -> str:
    readme = (EXAMPLES / "README.md").read_text(encoding="utf-8")
    out = [readme.rstrip(), "", "## The scripts", "",
           "As they are in the repository's `examples/` folder:", ""]
    for path in sorted(EXAMPLES.iterdir()):
        if path.suffix in LANGUAGES:
            out += [f"### {path.name}", "", f"```{LANGUAGES[path.suffix]}",
                    path.read_text(encoding="utf-8").rstrip(), "```", ""]
    return "\n".join(out)


def on_files(files, config):
    from mkdocs.structure.files import File

    existing = files.get_file_from_path(PAGE)
    if existing is not None:
        files.remove(existing)
    files.append(File.generated(config, PAGE, content=examples_page()))
    return files


if __name__ == "__main__":
    target = Path(sys.argv[1] if len(sys.argv) > 1 else "site-examples") / PAGE
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(examples_page(), encoding="utf-8")
    print(target)
