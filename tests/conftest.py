"""Test-session settings.

One intra-op thread: the suite's tensors are small, and on a busy 2-core machine two OpenMP
threads made tiny operations 100-300 times slower (measured while writing the suite).
Subprocesses (the examples run end to end) inherit the setting through OMP_NUM_THREADS.
"""

import os

import torch

os.environ.setdefault("OMP_NUM_THREADS", "1")
torch.set_num_threads(1)
