"""Layer 5, the algorithms: the loop (Algorithm 1) and the sampling-policy selector (Algorithm 2).

====================================== ====================================================
:mod:`torch_api.loop.iteration`        :class:`ActivePolicyIteration`: the loop, Algorithm 1
:mod:`torch_api.loop.selector`         :class:`SamplingPolicySelector`: Algorithm 2
:mod:`torch_api.loop.buying`           steps 1-2: choose the sampling policy, buy, commit
:mod:`torch_api.loop.durable`          the durable state: the settings a resume checks, restore
:mod:`torch_api.loop.records`          :class:`IterationRecord`, what an iteration leaves
====================================== ====================================================
"""
