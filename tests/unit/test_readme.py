"""The README opens with what the project is and how to start, and CI runs its test command."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _bash_blocks(text: str) -> list[list[str]]:
    """The README's ```bash blocks, each as its commands: comments cut, continuations joined."""
    blocks = []
    for body in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        commands, pending = [], ""
        for line in body.splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if line.endswith("\\"):
                pending += line[:-1].strip() + " "
                continue
            if pending + line:
                commands.append(" ".join((pending + line).split()))
            pending = ""
        blocks.append(commands)
    return blocks


def _ci_commands() -> list[str]:
    """The commands .ci/run runs between its ``set -e`` and the pytest exit status."""
    text = (REPO / ".ci" / "run").read_text().replace("\\\n", " ")
    body = text.split("\nset -e\n", 1)[1].split("\nrc=$?", 1)[0]
    return [" ".join(line.split()) for line in body.splitlines() if line.strip() and line.strip() != "set +e"]


def test_readme_starts_with_what_and_how():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines"
    first = next(i for i, line in enumerate(lines, 1) if line.startswith("python -m venv"))
    assert first <= 30, f"the first set-up command is on line {first}"
    assert "## Start" in lines[:first]


def test_ci_runs_the_readmes_test_command():
    train, tests = _bash_blocks((REPO / "README.md").read_text())[:2]
    assert tests == _ci_commands()
    assert tests[-1] == "python -m pytest -n auto --dist worksteal"  # one worker per core; an idle one takes tests from the other
    # the main job is the same set-up without -q and the dev extra, then train.py
    assert [c.replace(" -q", "").replace('".[dev]"', ".") for c in tests[:-1]] == train[:-1]
    assert train[-1] == "python train.py"


def test_experiments_index_lists_every_page_once():
    """docs/experiments/index.md links each page of the folder and of its archive, once."""
    folder = REPO / "docs" / "experiments"
    links = re.findall(r"\]\(([^)]+\.md)\)", (folder / "index.md").read_text())
    pages = sorted(str(p.relative_to(folder)) for p in folder.rglob("*.md") if p.name != "index.md")
    assert sorted(set(links)) == pages
    rows = [line for line in (folder / "index.md").read_text().splitlines() if line.startswith("| ") and ".md)" in line]
    assert sorted(r.rsplit("](", 1)[1].split(")")[0] for r in rows) == pages  # one row per page


def test_hand_written_pages_name_no_machine_path():
    """Commands in the README and the reference and experiment pages are relative to the
    repository (generated pages name their sources where the report found them)."""
    pages = [REPO / "README.md", *(REPO / "docs" / "reference").glob("*.md"), *(REPO / "docs" / "experiments").rglob("*.md")]
    pattern = re.compile(r"(?<![\w.])/(?:work|home|root|tmp/(?!eskin\b|numba_cache\b))[\w.\-]+")
    found = [f"{p.relative_to(REPO)}: {m.group(0)}" for p in pages for m in pattern.finditer(p.read_text())]
    assert found == []
