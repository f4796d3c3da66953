"""Layer 4, collection: policies run in environments, episodes out in the library's format.

============================================ ===========================================
:mod:`torch_api.collection.collect`          rollouts, the user's ``Collector``
:mod:`torch_api.collection.multiprocess`     the rows of a rollout over worker processes
:mod:`torch_api.collection.candidates`       the K candidates' reward-free episodes at once
============================================ ===========================================
"""

from torch_api.collection.collect import (
    EnvPerBatch,
    SpecCheckedPolicy,
    at_most_rows,
    collect_episodes,
    collect_with_collector,
)

__all__ = [
    "EnvPerBatch",
    "SpecCheckedPolicy",
    "at_most_rows",
    "collect_episodes",
    "collect_with_collector",
]
