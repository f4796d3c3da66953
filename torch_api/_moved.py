"""The module paths of the flat layout (before issue #23), kept for one release.

``import torch_api.solve`` (or ``from torch_api.store import RunStore``) still works: it warns
(``DeprecationWarning``, naming the new path) and gives the module at its new home, the very
same module object, so that what is set on one is set on the other. ``torch_api.policies`` and
``torch_api.data`` are packages now and keep their names.

The old names also stay the names a stored run records for the library's classes and
functions (:func:`stable_name`): a run stored before the move resumes after it.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

MOVED = {
    "torch_api.actions": "torch_api.data.actions",
    "torch_api.episodes": "torch_api.data.episodes",
    "torch_api.buffer": "torch_api.data.buffer",
    "torch_api.basis": "torch_api.core.basis",
    "torch_api.weights": "torch_api.core.weights",
    "torch_api.psi": "torch_api.core.psi",
    "torch_api.design": "torch_api.core.design",
    "torch_api.grouped_design": "torch_api.core.grouped_design",
    "torch_api.solve": "torch_api.core.solve",
    "torch_api.criterion": "torch_api.core.criterion",
    "torch_api.lstd": "torch_api.core.lstd",
    "torch_api.iwcv": "torch_api.core.iwcv",
    "torch_api.improvement": "torch_api.core.improvement",
    "torch_api.fit": "torch_api.core.fit",
    "torch_api.policy_base": "torch_api.policies.base",
    "torch_api.candidates": "torch_api.policies.families",
    "torch_api.codec": "torch_api.runs.codec",
    "torch_api.store": "torch_api.runs.store",
    "torch_api.store_errors": "torch_api.runs.store_errors",
    "torch_api.store_files": "torch_api.runs.store_files",
    "torch_api.store_read": "torch_api.runs.store_read",
    "torch_api.run_guard": "torch_api.runs.run_guard",
    "torch_api.lifetime": "torch_api.runs.lifetime",
    "torch_api.dispatch": "torch_api.runs.dispatch",
    "torch_api.collect": "torch_api.collection.collect",
    "torch_api.multiprocess": "torch_api.collection.multiprocess",
    "torch_api.candidate_collection": "torch_api.collection.candidates",
    "torch_api.iteration": "torch_api.loop.iteration",
    "torch_api.buying": "torch_api.loop.buying",
    "torch_api.durable": "torch_api.loop.durable",
    "torch_api.records": "torch_api.loop.records",
    "torch_api.selector": "torch_api.loop.selector",
}
_HOME_OF = {new: old for old, new in MOVED.items()}


def stable_name(module: str | None) -> str | None:
    """The name a stored run records for ``module``: its flat-layout name where it moved.

    Example:
        >>> stable_name("torch_api.core.criterion"), stable_name("envs.chain_walk.env")
        ('torch_api.criterion', 'envs.chain_walk.env')
    """
    return _HOME_OF.get(module, module)


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old module path and loads the module at its new one (after a warning)."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        warnings.warn(
            f"{spec.name} moved to {MOVED[spec.name]}; import it from there (or from "
            "torch_api); the old path goes in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return importlib.import_module(MOVED[spec.name])

    def exec_module(self, module) -> None:
        """Nothing to run: the module at its new home is loaded already."""


def install() -> None:
    """Put the finder after the ordinary ones (once): only paths that are gone reach it."""
    if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
        sys.meta_path.append(_MovedModules())
