"""examples/_weight_warnings.py: collapsed-weight warnings kept per run and summarised once."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from torch_api.core.design import CollapsedWeightsWarning, _warn_on_collapsed_weights

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
from _weight_warnings import kept_weight_warnings, report_weight_warnings  # noqa: E402


def collapse(ess_weight: float, n: int) -> None:
    """A fit whose weights are one large weight among n - 1 small ones (ESS below 1 %)."""
    w = torch.full((1, n), 1e-6, dtype=torch.float64)
    w[0, 0] = ess_weight
    _warn_on_collapsed_weights(w, torch.ones(1, n), 0.01)


def test_warnings_are_kept_with_run_and_iteration_and_summarised(tmp_path, capsys):
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
    assert all(w["ess"] < 1.01 and "test_weight_warnings.py" in w["where"] for w in caught)
    runs = [{"weight_warnings": caught}, {"weight_warnings": []}, {}]
    line = report_weight_warnings(runs, tmp_path / "run.log")
    assert "in 2 (run, iteration) fits" in line and "n = 400" in line and "l = 4" in line
    assert capsys.readouterr().out.strip() == line
    assert len((tmp_path / "run.log").read_text().splitlines()) == 2
    assert all("weight_warnings" not in run for run in runs)


def test_the_warning_carries_its_numbers():
    with pytest.warns(CollapsedWeightsWarning) as record:
        collapse(1.0, n=150)
    warning = record[0].message
    assert (warning.n, warning.collapsed, warning.sets) == (150, 1, 1)
    assert warning.ess == pytest.approx(1.0, abs=1e-3)
    assert "effective sample size 1.00 of n = 150" in str(warning)
