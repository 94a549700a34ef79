"""How TD3X's update runs: the ways of running the hooks, and the one function that picks one for a model.

What an update computes is written once, as the hooks of :class:`~sb3_td3x.TD3X` (:mod:`sb3_td3x.td3x.hooks`). Every
way here runs those hooks as written; none has code of its own for a step of TD3:

=================  ============================================================================================
``update_path``    what runs
=================  ============================================================================================
``"eager"``        ``model.gradient_step``: the hooks, eagerly, with autograd
``"compiled"``     :class:`~.compiled.CompiledUpdate`: ``update_from_batch`` as one ``torch.compile`` graph (the
                   backward passes and torch's Adam steps in it), on a GPU inside CUDA graphs; it steps aside to
                   ``"eager"``, saying why, where Dynamo cannot make one graph of the user's code
``"cuda_graph"``   :class:`~.cuda_graph.GraphedGradientStep` (``cuda_graph=True``): ``gradient_step`` captured
                   in CUDA graphs of its own and replayed
=================  ============================================================================================

:func:`~.choose.choose_update` picks one from the machine and the run (``compile_update``, ``cuda_graph``, the run's
length, a compiler), never from the user's code, and says why. Collection's pi(s) is in :mod:`.exploration` (many
seeds' at once in :mod:`sb3_td3x.seeds.actions`). Imports go one way: ``hooks``, ``optim`` <- the paths <- ``choose``
<- ``td3x`` <- ``sb3_td3x.seeds``.
"""
