"""The paired experiments' library part (:mod:`torch_api.experiment`): the chunks of a run joined,
the results' CSV (byte for byte what ``csv.writer`` writes) and JSON, the paired t-test,
collapsed-weight warnings kept and summarised, the ``Execution`` checks, and report files never
written through a planted symbolic link (an example run in this process)."""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import io
import os
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.stats
import torch

from torch_api.core.design import CollapsedWeightsWarning, _warn_on_collapsed_weights
from torch_api.experiment import (
    COLUMNS,
    Execution,
    Experiment,
    kept_weight_warnings,
    paired_test,
    read_results,
    report_weight_warnings,
    write_results,
)
from torch_api.experiment.results import csv_lines
from torch_api.experiment.runner import concatenate
from torch_api.runs.store import RunStore

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


# -- the results: chunks joined, the long CSV, the JSON ----------------------------------------


def test_the_long_layout_holds_every_number_once_and_reads_back(tmp_path):
    """Chunks concatenated along the trial axis (times added up), one CSV row per number (a
    number of the iteration repeated per trial, J' per candidate), read back as written; the
    wall times in the JSON only."""

    def part(returns, j, seconds):
        row = {"iteration": 1, "rewarded_transitions": 30, "test_return": returns, "j_mean": j}
        return {"seed": 7, "seconds": seconds, "iterations": [row | {"seconds": seconds}]}

    al = concatenate(
        [part([1.5, 2.0], [[0.1, 0.2], [0.3, 0.4]], 1.0), part([3.0], [[0.5, 0.6]], 2.0)]
    )
    assert al["seconds"] == 3.0 and al["iterations"][0]["seconds"] == 3.0
    assert al["iterations"][0]["test_return"] == [1.5, 2.0, 3.0] and al["seed"] == 7
    pl = part([1.5, 2.0, 3.0], None, 1.0)
    results = {"fixed": {"schedule": [3], "runs": {"AL": al, "PL": pl}, "t_tests": {}}}
    results["fixed"]["t_tests"]["test_return"] = paired_test([1.5, 2.0, 3.0], [1.5, 2.0, 3.0])
    assert results["fixed"]["t_tests"]["test_return"]["t"] is None  # no spread: undefined

    @dataclasses.dataclass
    class Args:  # a script's own arguments, written into the JSON
        trials: int = 3

    experiment = Experiment(
        name="x", schedules={"fixed": [3]}, run_chunk=print, t_tests=(), report=print
    )
    payload = write_results(Execution(out_dir=str(tmp_path)), Args(), experiment, results, 0.5)
    assert payload["args"] == {"trials": 3} and payload["results"] is results
    table = read_results(tmp_path / "x.csv")
    assert table["fixed", "AL", 1, "test_return"] == [1.5, 2.0, 3.0]
    assert table["fixed", "AL", 1, "rewarded_transitions"] == [30, 30, 30]
    assert table["fixed", "AL", 1, "j_mean_k2"] == [0.2, 0.4, 0.6]
    assert ("fixed", "PL", 1, "j_mean_k1") not in table  # PL has no J'
    rows = (tmp_path / "x.csv").read_text().splitlines()
    assert rows[0] == ",".join(COLUMNS) and len(rows) == 1 + 3 * (2 + 2) + 3 * 2
    assert "seconds" not in (tmp_path / "x.csv").read_text()  # wall times: in the JSON only
    summary = (tmp_path / "x.json").read_text()
    assert '"iteration_seconds": [3.0]' in summary and '"wall_seconds": 0.5' in summary


def test_the_csv_lines_are_what_csv_writer_writes():
    """``csv_lines`` formats the rows itself (faster than ``csv.writer``): its bytes equal
    ``csv.writer``'s of the same rows, and ``csv.reader`` reads back every field, texts that
    need quoting, bools and missing entries of a vector included."""
    row = {
        "iteration": 2,
        "seconds": 0.1,
        "test_return": [0.1, 1e-300, -2.5e17],
        "chosen": [1, None, 3],
        "rule": ['eps, "0.1"', "line\nbreak", "plain"],
        "flag": True,
        "j_mean": [[0.25, None], None, [1.0, 2.0]],
    }
    results = {"a,b": {"runs": {"AL": {"seed": -3, "iterations": [row]}}}}
    expected = [list(COLUMNS)]
    for t in range(3):
        head = ["a,b", "AL", "-3", "2", str(t)]
        for key in ("test_return", "chosen", "rule", "flag", "j_mean"):
            value = row[key][t] if isinstance(row[key], list) else row[key]
            if isinstance(value, list):
                for k, x in enumerate(value, 1):
                    expected.append([*head, f"{key}_k{k}", "" if x is None else str(x)])
            elif value is not None:
                expected.append([*head, key, str(value)])
    text = "".join(csv_lines(results))
    assert list(csv.reader(io.StringIO(text, newline=""))) == expected
    handle = io.StringIO(newline="")
    csv.writer(handle).writerows(expected)
    assert text == handle.getvalue()


def test_the_paired_test_is_scipys_ttest_rel():
    rng = np.random.default_rng(0)
    for n in (2, 3, 32, 500):
        a = rng.normal(size=n)
        p = a + rng.normal(size=n) * 0.3 + rng.normal() * 0.1
        ours, theirs = paired_test(a, p), scipy.stats.ttest_rel(a, p)
        assert ours["t"] == pytest.approx(theirs.statistic, rel=1e-12)
        assert ours["p"] == pytest.approx(theirs.pvalue, rel=1e-12, abs=1e-300)
        assert ours["mean_difference"] == pytest.approx(float(np.mean(a - p)))
        assert ours["al_better_share"] + ours["al_worse_share"] == 1.0
    assert paired_test([1.0, 2.0], [0.5, 1.5])["t"] is None  # no spread in the differences
    assert paired_test([1.0], [0.5])["p"] is None  # a single pair


@pytest.mark.parametrize(
    ("settings", "words"),
    [
        ({"resume": True, "overwrite": True}, "resume and overwrite exclude each other"),
        ({"backend": "slurm"}, "backend must be one of"),
        ({"logger": "mlflow"}, "logger must be one of"),
        ({"chunks": 0}, "chunks must be >= 1, got 0"),
        ({"threads": 2000}, "threads must be <= 1024"),
        ({"workers": 2}, "workers applies to backend 'processes', not 'local'"),
        ({"ray_cpus": 2}, "ray_address and ray_cpus apply to backend 'ray'"),
        ({"out_dir": ""}, "out_dir must name a folder"),
    ],
)
def test_execution_refuses_what_it_cannot_honour(settings, words):
    with pytest.raises(ValueError, match=words):
        Execution(**{"backend": "local"} | settings)
    with pytest.raises(ValueError, match="chunks must lie in 1..2"):
        Execution(backend="local", chunks=3).check_chunks(2)


@pytest.mark.skipif(
    importlib.util.find_spec("tensorboard") is not None, reason="tensorboard is installed here"
)
def test_a_logger_whose_package_is_missing_is_refused_when_the_options_are_made():
    """Before, the run bought every reward and then failed writing its curves."""
    with pytest.raises(ValueError, match="needs its package: pip install tensorboard"):
        Execution(backend="local", logger="tensorboard")


# -- collapsed importance weights, kept per run and summarised once ----------------------------


def collapse(ess_weight: float, n: int) -> None:
    """A fit whose weights are one large weight among n - 1 small ones (ESS below 1 %)."""
    w = torch.full((1, n), 1e-6, dtype=torch.float64)
    w[0, 0] = ess_weight
    _warn_on_collapsed_weights(w, torch.ones(1, n), 0.01)


def test_weight_warnings_are_kept_with_run_and_iteration_and_summarised(tmp_path, capsys):
    api = SimpleNamespace(iteration=0)
    chunk = SimpleNamespace(schedule_name="decreasing", method="AL")
    shown = []
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = lambda message, *rest, **kw: shown.append(str(message))
        with kept_weight_warnings(api, chunk) as caught:
            collapse(1.0, n=200)
            api.iteration = 3
            collapse(1.0, n=400)
            warnings.warn("other", UserWarning, stacklevel=1)
    assert shown == ["other"]  # other warnings still reach the user, these do not
    assert [(w["iteration"], w["n"]) for w in caught] == [(1, 200), (4, 400)]
    assert all(w["ess"] < 1.01 and "test_experiment.py" in w["where"] for w in caught)
    runs = [{"weight_warnings": caught}, {"weight_warnings": []}, {}]
    line = report_weight_warnings(runs, tmp_path / "run.log")
    assert "in 2 (run, iteration) fits" in line and "n = 400" in line and "l = 4" in line
    assert capsys.readouterr().out.strip() == line
    assert len((tmp_path / "run.log").read_text().splitlines()) == 2
    assert all("weight_warnings" not in run for run in runs)
    assert report_weight_warnings([{}], tmp_path / "none.log") is None
    assert not (tmp_path / "none.log").exists()


def test_the_warning_carries_its_numbers():
    with pytest.warns(CollapsedWeightsWarning) as record:
        collapse(1.0, n=150)
    warning = record[0].message
    assert (warning.n, warning.collapsed, warning.sets) == (150, 1, 1)
    assert warning.ess == pytest.approx(1.0, abs=1e-3)
    assert "effective sample size 1.00 of n = 150" in str(warning)


# -- report files never written through a planted symbolic link --------------------------------

TINY = ["--trials", "2", "--iterations", "1", "--schedule", "decreasing", "--repeats", "1"]
TINY += ["--test-episodes", "2", "--test-steps", "5", "--backend", "local"]


@pytest.fixture(scope="module")
def chain_walk_api():
    """``examples/chain_walk_api.py`` imported from its file (examples/ is no package)."""
    path = EXAMPLES / "chain_walk_api.py"
    spec = importlib.util.spec_from_file_location("_experiment_chain_walk_api", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # (its dataclasses look their module up)
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)


@pytest.mark.skipif(not hasattr(os, "symlink"), reason="no symbolic links here")
@pytest.mark.parametrize(
    ("name", "flag"),
    [
        ("chain_walk_api.csv", "--overwrite"),
        ("chain_walk_api.json", "--overwrite"),
        ("fig8_performance.png", "--overwrite"),
        ("chain_walk_api.csv", "--resume"),
    ],
)
def test_a_report_is_never_written_through_a_planted_link(
    chain_walk_api, tmp_path, capsys, name, flag
):
    """``ln -s VICTIM OUT/<report>``: the run is refused with one line naming the link (exit
    1) and the victim is left as it was. The refusal comes when the report is written, after
    the runs (``torch_api.runs.files`` refuses the link; the folder's checks before the runs do
    not look for links): the runs are stored, so once the link is gone ``--resume`` writes the
    reports and buys nothing again."""
    victim, out = tmp_path / "victim.txt", tmp_path / "out"
    victim.write_text("someone else's file\n")
    out.mkdir()
    link = out / name
    link.symlink_to(victim)
    argv = [*TINY, "--out-dir", str(out), flag]
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        chain_walk_api.main(argv)
    code = stop.value.code
    err = capsys.readouterr().err + (code if isinstance(code, str) else "")
    code = 1 if isinstance(code, str) else code
    lines = err.strip().splitlines()
    assert code == 1 and "Traceback" not in err, err
    assert lines[-1] == (
        f"error: {link} is a symbolic link; {link} is never written through one (remove the "
        "link, or write elsewhere)"
    ), err
    assert victim.read_text() == "someone else's file\n" and link.is_symlink()
    assert not list(out.glob(f"{name}.*.new"))  # no temporary left behind

    # the refusal comes when the report is written, after the runs: they are stored, whole
    # (a check before the runs would leave none: nothing bought, nothing to keep)
    stores = sorted((out / "checkpoints").glob("*.db"))
    stored = {p.name: RunStore.read(p).num_episodes for p in stores}
    assert stored in ({"decreasing_AL.db": 5, "decreasing_PL.db": 5}, {})
    link.unlink()
    payload = chain_walk_api.main([*TINY, "--out-dir", str(out), "--resume"])
    assert not link.is_symlink() and link.stat().st_size > 0
    assert {p.name: RunStore.read(p).num_episodes for p in stores} == stored  # none bought again
    assert set(payload["summary"]["decreasing"]["runs"]) == {"AL", "PL"}
    assert victim.read_text() == "someone else's file\n"
