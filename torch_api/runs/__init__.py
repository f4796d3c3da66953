"""Beside the layers, a run's durability and execution: the store, its guards, processes.

========================================= ============================================
:mod:`torch_api.runs.store`               :class:`RunStore`: a run in SQLite, one writer
:mod:`torch_api.runs.store_read`          reading a store back, verified (:class:`StoredRun`)
:mod:`torch_api.runs.store_files`         the files around the database, atomic creation
:mod:`torch_api.runs.files`               result files written atomically, never via a link
:mod:`torch_api.runs.store_errors`        one exception per cause
:mod:`torch_api.runs.codec`               TensorDicts as bytes without pickle
:mod:`torch_api.runs.run_guard`           the writer's lock, symlink and signal guards
:mod:`torch_api.runs.lifetime`            worker processes that die with their parent
:mod:`torch_api.runs.dispatch`            chunks of trials in-process, in processes or on Ray
========================================= ============================================

It imports nothing of the library but :mod:`torch_api.streams`; what the loop stores and how a
loop is rebuilt from a store is the loop's (:mod:`torch_api.loop.durable`).
"""
