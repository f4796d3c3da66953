"""Layer 5, the algorithms: the loop (Algorithm 1) and the sampling-policy selector (Algorithm 2).

====================================== ====================================================
:mod:`torch_api.loop.iteration`        :class:`ActivePolicyIteration`: ``step`` reads as Algorithm 1
:mod:`torch_api.loop.selector`         :class:`SamplingPolicySelector`: Algorithm 2
:mod:`torch_api.loop.policies`         the loop's policies: pi_l, its candidates, their streams
:mod:`torch_api.loop.buying`           steps 1-2: choose the sampling policy, buy, commit
:mod:`torch_api.loop.spec`             :class:`RunSpec`: a run's settings, checked; its identity
:mod:`torch_api.loop.durable`          :class:`DurableRun`: the run's store, restore
:mod:`torch_api.loop.records`          :class:`IterationRecord`, what an iteration leaves
====================================== ====================================================
"""
