"""Rebuild docs/RESULTS.md: every results file in tests/benchmarks/results/ with its title, commit
and command, and which the README quotes.

    python tests/benchmarks/results_index.py
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "tests" / "benchmarks" / "results"
INDEX = ROOT / "docs" / "RESULTS.md"

_COMMIT = re.compile(r"[Cc]ommit[^`\n]*`([0-9a-f]{7,40}[^`]*)`|\b[Cc]ommit ([0-9a-f]{7,40})\b|at ([0-9a-f]{7,12}) |code of `([0-9a-f]{7,40})`")
_COMMAND = re.compile(r"(?:Command|Made by|made by)[^`\n]*`([^`]+)`")


def describe(path: Path) -> dict:
    text = path.read_text(encoding="utf-8")
    title = next((line.lstrip("# ").strip() for line in text.splitlines() if line.startswith("#")), path.stem)
    commit = _COMMIT.search(text)
    command = _COMMAND.search(text)
    return {"file": path.relative_to(RESULTS).as_posix(), "title": title,
            "commit": next((g for g in commit.groups() if g), None) if commit else None,
            "command": command.group(1) if command else None}


def main() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    research = (ROOT / "docs" / "RESEARCH.md").read_text(encoding="utf-8")
    rows = [describe(p) for p in sorted(RESULTS.rglob("*.md"))]
    lines = ["# Results index", "",
             "Every results file in `tests/benchmarks/results/` (JSON beside most of them), with the commit it",
             "names and the command that made it. A file measured at an earlier default is history: read its",
             "settings before comparing it with today's. Quoted: cited by the README (R) or docs/RESEARCH.md (D).",
             "Rebuilt by `python tests/benchmarks/results_index.py`.", "",
             "| file | what | commit | quoted | command |", "|---|---|---|---|---|"]
    for row in rows:
        name = row["file"]
        quoted = "".join(tag for tag, text in (("R", readme), ("D", research))
                         if Path(name).name in text or name in text)
        command = f"`{row['command'][:120]}`" if row["command"] else "see the file"
        lines.append(f"| [{name}](../tests/benchmarks/results/{name}) | {row['title']} | `{row['commit'] or 'none'}` | "
                     f"{quoted} | {command} |")
    INDEX.write_text("\n".join(lines) + "\n", encoding="utf-8")
    missing = [r["file"] for r in rows if not r["commit"]]
    print(f"{len(rows)} files; without a commit: {missing or 'none'}")


if __name__ == "__main__":
    main()
