"""The shipped artefacts, built on the product's own path: each model trained through the training API
(:func:`models.run_training` with a named :class:`models.train.recipe.TrainRecipe` and a list of rendered sets),
exported and quantised through :mod:`export`, scored through the runtime, with its card.

One module per artefact, each a command (``export/release/README.md`` has one per shipped version):
:mod:`export.release.coarse` (the coarse refiners and the card), :mod:`export.release.fine` (the fine refiners of the
cascade), :mod:`export.release.samples` (the demo's frames); :mod:`export.release.card` writes the card.
"""
