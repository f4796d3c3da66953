"""Paired experiments: AL and PL runs of Algorithm 1 on the same seeds, as a script runs them.

A script supplies its environment, basis and evaluation as a function of one :class:`Chunk`
(:func:`make_iteration` builds the chunk's run from a :class:`~torch_api.RunSpec`,
:func:`run_iterations` runs it) and :func:`run_experiment` does the rest: trials in chunks on
a backend (here, local processes or Ray), every run stored as it goes (resume, overwrite, the
folder's lock, SIGINT/SIGTERM between commits), one progress bar, the paired t-test (SciPy)
and the results as a long CSV and a JSON.

============================================  ============================================
:mod:`torch_api.experiment.options`           :class:`Execution`: where it runs, where files go
:mod:`torch_api.experiment.runner`            :class:`Experiment`, :class:`Chunk`, the runs
:mod:`torch_api.experiment.folder`            the output folder's lock, stored runs, signals
:mod:`torch_api.experiment.results`           statistics, tables, the CSV and the JSON
:mod:`torch_api.experiment.plots`             the figure: measures per iteration, AL − PL
:mod:`torch_api.experiment.weight_warnings`   collapsed importance weights, summarised once
:mod:`torch_api.experiment.pipeline`          a TorchRL pipeline's rows and seeded test returns
:mod:`torch_api.experiment.seeds`             a user's runs over seeds: stored, summarised, written
============================================  ============================================
"""

from torch_api.experiment.options import BACKENDS, LOGGERS, Execution, checked_device
from torch_api.experiment.plots import plot_paired
from torch_api.experiment.results import (
    COLUMNS,
    METHODS,
    mean_se,
    paired_test,
    print_curves,
    print_t_tests,
    read_results,
    write_results,
)
from torch_api.experiment.runner import (
    Chunk,
    Experiment,
    derived_seed,
    make_iteration,
    run_experiment,
    run_iterations,
)
from torch_api.experiment.weight_warnings import kept_weight_warnings, report_weight_warnings

__all__ = [
    "BACKENDS",
    "COLUMNS",
    "LOGGERS",
    "METHODS",
    "Chunk",
    "Execution",
    "Experiment",
    "checked_device",
    "derived_seed",
    "kept_weight_warnings",
    "make_iteration",
    "mean_se",
    "paired_test",
    "plot_paired",
    "print_curves",
    "print_t_tests",
    "read_results",
    "report_weight_warnings",
    "run_experiment",
    "run_iterations",
    "write_results",
]
