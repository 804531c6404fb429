"""``embodied-tactile report``: every generated page under docs/generated/ from what it was made from."""

from __future__ import annotations

import json
import shutil

import pytest

from embodied_tactile.eval import pages

from conftest import REPO

GENERATED = REPO / "docs" / "generated"
RECORD = "learned_active_nmse"


@pytest.fixture
def docs(tmp_path):
    """A copy of the generated pages with one active-palpation record."""
    out = tmp_path / "generated"
    (out / "active").mkdir(parents=True)
    for name in ("results.md", "generalisation.md", "generalisation_scores.json"):
        shutil.copy(GENERATED / name, out / name)
    shutil.copy(GENERATED / "active" / f"{RECORD}.json", out / "active" / f"{RECORD}.json")
    return out


def test_regenerate_all_reproduces_the_pages_and_leaves_what_it_cannot(docs, monkeypatch):
    monkeypatch.setattr(pages, "results_page", lambda d: f"{d / 'results.md'}: left as it is: test")
    lines = pages.regenerate_all(docs)
    assert len(lines) == 3 and "left as it is" in lines[0]
    for ext in ("md", "csv", "tex"):  # the tables come back as committed, from the record alone
        assert (docs / "active" / f"{RECORD}.{ext}").read_text() == (GENERATED / "active" / f"{RECORD}.{ext}").read_text()
    assert (docs / "active" / f"{RECORD}.png").stat().st_size > 1000
    body = lambda p: p.read_text().split("\n", 3)[3]  # noqa: E731  (the header names the date and command)
    assert body(docs / "generalisation.md") == body(GENERATED / "generalisation.md")
    assert json.loads((docs / "generalisation_scores.json").read_text()) == json.loads(
        (GENERATED / "generalisation_scores.json").read_text())
    assert (docs / "figures" / "generalisation_curve.png").stat().st_size > 1000


def test_results_page_names_missing_folders_and_reruns_the_header_command(docs, tmp_path, monkeypatch):
    page = docs / "results.md"
    before = page.read_text()
    args, folders = pages.study_sources(page)
    assert folders and all(str(f) in args for f in folders) and "--note" in args
    line = pages.results_page(docs)  # the study's evaluation folders are not on a test machine
    assert "left as it is" in line and str(folders[0]) in line and page.read_text() == before

    for f in (tmp_path / "trial", tmp_path / "object"):
        f.mkdir()
        (f / "results.json").write_text("{}")
    page.write_text(before.replace(str(folders[0]), str(tmp_path / "trial")).replace(str(folders[1]), str(tmp_path / "object")))
    seen = []
    from embodied_tactile.eval import study_report

    monkeypatch.setattr(study_report, "main", lambda argv: seen.append(argv) or 0)
    assert "regenerated" in pages.results_page(docs)
    assert seen[0][:3] == [str(tmp_path / "trial"), "--objects", str(tmp_path / "object")]
    assert seen[0][-2:] == ["--out", str(page)]


def test_report_command_dispatches_and_refuses_a_missing_folder(tmp_path, capsys):
    assert pages.main(["--docs", str(tmp_path / "none")]) == 2
    assert "no such folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        pages.main(["results", "--help"])
    assert "--paper-units" in capsys.readouterr().out
