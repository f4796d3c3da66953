"""Where and how a paired experiment runs: the output folder, stored runs, chunks, backends.

:class:`Execution` is the part of an example's arguments that says where the work goes, not
what it computes: changing it never changes a number, so ``--resume`` may give other values.
It is a plain dataclass whose fields carry one-line docstrings, so a command-line library that
reads dataclasses (``tyro``) shows them in ``--help``; it is checked when it is made.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass

import torch

from torch_api._checks import _check_device
from torch_api.runs.dispatch import BACKENDS

__all__ = ["BACKENDS", "LOGGERS", "Execution", "checked_device"]

LOGGERS = ("none", "csv", "tensorboard", "wandb")
"""TorchRL loggers the learning curves can go to (``--logger``)."""


@dataclass(frozen=True)
class Execution:
    """Where a paired experiment runs and where its files go."""

    out_dir: str = "results"
    """where the JSON, the CSV, the figures and the stored runs go"""
    resume: bool = False
    """continue the runs stored in out_dir (nothing bought twice; a missing run starts fresh)"""
    overwrite: bool = False
    """discard the runs stored in out_dir and start over"""
    backend: str = "local"
    """where chunks of trials run: local (here, one after another), processes or ray"""
    chunks: int = 1
    """C, chunks of trials per schedule and method (each one batched run)"""
    workers: int = 0
    """processes backend: worker processes (0: one per CPU core)"""
    ray_address: str = ""
    """ray backend: the cluster to join (e.g. auto); empty starts a local Ray instance"""
    ray_cpus: int = 0
    """ray backend: CPUs of a local Ray instance (0: all)"""
    threads: int = 1
    """torch intra-op threads of this process (0: torch's default, one per core)"""
    logger: str = "none"
    """also write the learning curves with a TorchRL logger under out_dir/logs"""

    def __post_init__(self) -> None:
        if self.resume and self.overwrite:
            raise ValueError("resume and overwrite exclude each other")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        if self.logger not in LOGGERS:
            raise ValueError(f"logger must be one of {LOGGERS}, got {self.logger!r}")
        package = {"tensorboard": "tensorboard", "wandb": "wandb"}.get(self.logger)
        if package is not None and importlib.util.find_spec(package) is None:
            raise ValueError(f"logger {self.logger!r} needs its package: pip install {package}")
        for name in ("chunks", "workers", "ray_cpus", "threads"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{name} must be an integer, got {value!r}")
            if value < (1 if name == "chunks" else 0):
                raise ValueError(f"{name} must be >= {1 if name == 'chunks' else 0}, got {value}")
        if self.threads > 1024:
            raise ValueError(f"threads must be <= 1024, got {self.threads}")
        if self.workers and self.backend != "processes":
            raise ValueError(
                f"workers applies to backend 'processes', not {self.backend!r} (got "
                f"workers={self.workers})"
            )
        if (self.ray_address or self.ray_cpus) and self.backend != "ray":
            raise ValueError(
                f"ray_address and ray_cpus apply to backend 'ray', not {self.backend!r}"
            )
        if not self.out_dir:
            raise ValueError("out_dir must name a folder")

    def check_chunks(self, trials: int) -> None:
        """C must lie in 1..T."""
        if self.chunks > trials:
            raise ValueError(f"chunks must lie in 1..{trials} (the trials), got {self.chunks}")

    @property
    def num_workers(self) -> int:
        """Worker processes of the processes backend."""
        return self.workers or os.cpu_count() or 1


def checked_device(device: str) -> torch.device:
    """An example's ``--device`` as a ``torch.device`` that is there, or a ``ValueError`` naming
    it (a CUDA device needs a GPU torch sees)."""
    return _check_device(device)
