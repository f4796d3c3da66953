"""The results pages are generated from docs/results/data/, not copied: the committed pages equal
what ``benchmarks/report.py`` makes of the data files, and a changed number changes them."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "docs" / "results" / "data"


def _load(name: str):
    """benchmarks/<name>.py by its path (torchrl installs a namespace package ``benchmarks``)."""
    spec = importlib.util.spec_from_file_location(
        f"_results_{name}", ROOT / "benchmarks" / f"{name}.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


report = _load("report")
summarize = _load("summarize")


def test_the_committed_pages_are_what_the_report_generates(capsys):
    assert sorted(DATA.glob("*.json")), "no data files in docs/results/data"
    assert report.main(["--check"]) == 0, capsys.readouterr().out


def test_a_changed_number_changes_the_page(tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(DATA, data)
    index = tmp_path / "index.md"
    index.write_text(report.INDEX.read_text())
    args = ["--check", "--data-dir", str(data), "--index", str(index), "--readme", ""]
    assert report.main(args) == 0, capsys.readouterr().out

    path = sorted(data.glob("*.json"))[0]
    payload = json.loads(path.read_text())
    payload["rows"][0]["al"]["mean"] += 1.0
    path.write_text(json.dumps(payload))
    assert report.main(args) == 1
    assert str(index) in capsys.readouterr().out

    assert report.main(args[1:]) == 0  # writing it makes the check pass again
    assert report.main(args) == 0


def test_the_readme_block_is_replaced_between_the_markers_only(tmp_path):
    experiments = report.load(DATA)
    text = f"intro\n{report.START}\nold table\n{report.END}\noutro\n"
    new = report.with_readme_block(text, report.readme_block(experiments))
    assert new.startswith(f"intro\n{report.START}\n| task |") and new.endswith(
        f"\n{report.END}\noutro\n"
    )
    assert "old table" not in new
    assert report.with_readme_block("no markers\n", "table") is None
    assert len(report.readme_block(experiments).splitlines()) <= report.README_ROWS + 4


@pytest.mark.parametrize(
    ("difference", "p", "better", "expected"),
    [
        (0.5, 0.01, "higher", "AL better"),
        (-0.5, 0.01, "higher", "PL better"),
        (-0.5, 0.01, "lower", "AL better"),
        (0.5, 0.05, "higher", "no difference found"),
        (0.0, None, "higher", "no difference found"),
    ],
)
def test_the_verdict_rule(difference, p, better, expected):
    assert summarize.verdict(difference, p, better) == expected
    assert summarize.VERDICTS == report.VERDICTS


def test_every_data_file_holds_its_verdicts_by_the_rule():
    for path in sorted(DATA.glob("*.json")):
        e = json.loads(path.read_text())
        for key in ("experiment", "title", "command", "commit", "date", "machine", "rows"):
            assert key in e, (path.name, key)
        assert path.stem == e["experiment"]
        for row in e["rows"]:
            d = row["difference"]
            assert row["verdict"] == summarize.verdict(d["mean"], d["p"], e["better"])
            assert d["trials"] == row["al"]["trials"] == row["pl"]["trials"]


def test_summarize_reads_an_output_folder(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    lines = ["schedule,method,seed,iteration,trial,measure,value"]
    al, pl = [3.0, 4.0, 5.0, 6.0], [1.0, 2.5, 2.0, 4.0]
    for method, values in (("AL", al), ("PL", pl)):
        for t, v in enumerate(values):
            lines += [f"fixed,{method},0,0,{t},score,0.0", f"fixed,{method},0,1,{t},score,{v}"]
            lines.append(f"fixed,{method},0,1,{t},rewarded_transitions,30")
    (folder / "toy.csv").write_text("\r\n".join(lines) + "\r\n")
    runs = {"AL": {"seed": 0, "seconds": 2.0}, "PL": {"seed": 0, "seconds": 1.0}}
    (folder / "toy.json").write_text(
        json.dumps(
            {"args": {"trials": 4}, "wall_seconds": 3.0, "summary": {"fixed": {"runs": runs}}}
        )
    )
    argv = [str(folder), "--id", "toy", "--title", "Toy", "--measure", "score", "--command", "x"]
    assert summarize.main([*argv, "--data-dir", str(tmp_path / "data")]) == 0
    e = json.loads((tmp_path / "data" / "toy.json").read_text())
    (row,) = e["rows"]
    assert row["al"]["mean"] == 4.5 and row["pl"]["mean"] == 2.375
    diff = row["difference"]
    assert diff["mean"] == pytest.approx(2.125) and diff["ci95_low"] < 2.125 < diff["ci95_high"]
    assert row["per_iteration"] == {"iterations": [0, 1], "AL": [0.0, 4.5], "PL": [0.0, 2.375]}
    assert row["rewarded_transitions"] == {"AL": 30.0, "PL": 30.0}
    assert row["seconds"] == {"AL": 2.0, "PL": 1.0}
    assert row["verdict"] == summarize.verdict(diff["mean"], diff["p"])
    assert e["commit"].split("+")[0] and e["machine"]["cores"]
