"""Collapsed importance weights of a run: kept with their run and iteration, summarised once.

Fits on rewarded data warn when the importance weights' effective sample size falls below 1 %
of n (:class:`~torch_api.core.design.CollapsedWeightsWarning`). A run of many trials and iterations
gives one such warning per fit; :func:`kept_weight_warnings` keeps them (with the run, the
iteration and the source line) instead of printing them, and :func:`report_weight_warnings`
prints one line and writes every warning to a log file.
"""

from __future__ import annotations

import warnings
from contextlib import contextmanager
from pathlib import Path

from torch_api.core.design import CollapsedWeightsWarning
from torch_api.runs.files import write_text_atomic

__all__ = ["kept_weight_warnings", "report_weight_warnings"]


@contextmanager
def kept_weight_warnings(api, chunk):
    """Within the block, collapsed-weight warnings of ``api`` (the chunk's run) go to the list
    it yields, as plain dicts; any other warning is shown as before."""
    caught: list[dict] = []
    with warnings.catch_warnings():
        warnings.simplefilter("always", CollapsedWeightsWarning)
        shown = warnings.showwarning

        def keep(message, category, filename, lineno, file=None, line=None):
            if not isinstance(message, CollapsedWeightsWarning):
                return shown(message, category, filename, lineno, file, line)
            caught.append(
                {
                    "schedule": chunk.schedule_name,
                    "method": chunk.method,
                    "iteration": api.iteration + 1,  # the iteration in progress
                    "ess": message.ess,
                    "n": message.n,
                    "collapsed": message.collapsed,
                    "sets": message.sets,
                    "where": f"{filename}:{lineno}",
                    "message": str(message),
                }
            )

        warnings.showwarning = keep
        yield caught


def report_weight_warnings(runs: list[dict], log: Path) -> str | None:
    """One line on the collapsed importance weights of all ``runs`` (each run's
    ``"weight_warnings"`` is taken out of it); every warning written to ``log``."""
    caught = [w for run in runs for w in run.pop("weight_warnings", [])]
    if not caught:
        return None
    lines = [
        f"{w['schedule']} {w['method']} l={w['iteration']} {w['where']}: {w['message']}"
        for w in caught
    ]
    write_text_atomic(log, "\n".join(lines) + "\n")
    fits = {(w["schedule"], w["method"], w["iteration"]) for w in caught}
    worst = min(caught, key=lambda w: w["ess"] / max(w["n"], 1))
    line = (
        f"importance weights collapsed (ESS below 1 % of n) in {len(fits)} (run, iteration) fits; "
        f"lowest ESS {worst['ess']:.2f} of n = {worst['n']} ({worst['schedule']} "
        f"{worst['method']}, l = {worst['iteration']}); every warning in {log}"
    )
    print(line)
    return line
