"""Training: the recipe (the one definition of a run), the training loop, a whole run from a recipe, its losses,
checkpoints and the file names of its outputs, and the ``refiner-rt train`` command.

``models.run_training(recipe, out=...)`` (:func:`models.train.run.run_training`) is the entry point; the modules
load on use, so ``import models.train.recipe`` needs no torch.
"""
