"""Layer 5, the algorithms: the loop (Algorithm 1) and the sampling-policy selector (Algorithm 2).

====================================== ====================================================
:mod:`torch_api.loop.iteration`        :class:`ActivePolicyIteration`: ``step`` reads as Algorithm 1
:mod:`torch_api.loop.selector`         :class:`SamplingPolicySelector`: Algorithm 2
:mod:`torch_api.loop.policies`         the loop's policies: pi_l, its candidates, their streams
:mod:`torch_api.loop.buying`           steps 1-2: choose the sampling policy, buy, commit
:mod:`torch_api.loop.durable`          the durable run: the settings a resume checks, restore
:mod:`torch_api.loop.records`          :class:`IterationRecord`, what an iteration leaves
:mod:`torch_api.loop.settings`         the loop's arguments, checked
====================================== ====================================================
"""
