"""How TD3X's update runs: the ways of running the hooks' math, and the one function that picks one for a model.

What an update computes is written once, as the hooks of :class:`~sb3_td3x.TD3X` (:mod:`sb3_td3x.td3x.hooks`). This
package holds the ways of running it. Each says which hooks it replaces with code of its own and what else it
assumes (``requirements(model)``, checked conservatively: when in doubt, the user's code runs):

========================  ==========================================================  ==============================
``update_path``           what runs                                                   replaces
========================  ==========================================================  ==============================
``"autograd"``            ``model.gradient_step``: the hooks as written, autograd     nothing
``"mlp"``                 :class:`~.mlp.MlpUpdate`: gradients written out by hand     13 hooks, the networks'
                                                                                      ``forward``, autograd
``"compiled_mlp"``        ``MlpUpdate``'s gradient functions, ``torch.compile``-d     as ``"mlp"``
                          (``compile_update=True``, or by default on a CPU for a
                          long run: :func:`~.compiled.why_not_compile`)
``"compiled"``            :class:`~.compiled.FunctionalCompiledUpdate`: the hooks     the optimizer steps,
                          compiled with ``torch.func`` gradients                      ``update_from_batch``
``"compiled_eager_backward"``  ``update_from_batch`` compiled as it is               ``gradient_step``
``"cuda_graph"``          :class:`~.cuda_graph.GraphedGradientStep`: the hooks as     nothing
                          written, captured in CUDA graphs (``cuda_graph=True``, or
                          by default where :func:`~.cuda_graph.why_not_cuda_graph`
                          proves the update stock and capturable)
========================  ==========================================================  ==============================

Collection has its own shortcut, :class:`~.exploration.DirectMlpActor`, chosen by
:func:`~.exploration.choose_exploration_actor`.

Many seeds in one process (:class:`~sb3_td3x.SeedBatch`) run the same ``MlpUpdate``, over their N models at once:
a lone model is a batch of one.

:func:`~.choose.choose_update` picks the fastest way that computes what the model's code computes, and says why.
Imports go one way: ``hooks`` <- ``requirements`` <- the paths <- ``choose`` <- ``td3x``; none imports ``TD3X``.
"""
