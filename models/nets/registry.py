"""The refiner registry: architectures by name, so training, checkpoints and export build models from a string.

A new architecture is a :class:`models.nets.blocks.Refiner` subclass with a ``DEFAULT_CONFIG`` and a
``build_feature_stage``, decorated with :func:`register_refiner`::

    @register_refiner("tiny")
    class TinyRefiner(Refiner):
        DEFAULT_CONFIG = {"input_size": 32}

        def build_feature_stage(self, config):
            return nn.Sequential(nn.Conv2d(3, 8, 3, stride=4), nn.Flatten()), 8 * 8 * 8

(Same idea as timm's ``register_model``.)
"""

from __future__ import annotations

from collections.abc import Callable

from models.nets.blocks import Refiner

__all__ = ["build_refiner", "get_refiner_class", "list_refiners", "register_refiner"]

_REGISTRY: dict[str, type[Refiner]] = {}


def register_refiner(name: str) -> Callable[[type[Refiner]], type[Refiner]]:
    """Class decorator registering a :class:`Refiner` subclass under ``name`` (sets ``cls.arch = name``).

    Raises:
        ValueError: ``name`` is already registered.
        TypeError: the decorated object is not a ``Refiner`` subclass.
    """

    def decorate(cls: type[Refiner]) -> type[Refiner]:
        if not (isinstance(cls, type) and issubclass(cls, Refiner)):
            raise TypeError(f"register_refiner({name!r}) expects a subclass of models.nets.blocks.Refiner; got {cls!r}")
        if name in _REGISTRY:
            raise ValueError(f"refiner {name!r} is already registered (by {_REGISTRY[name].__qualname__})")
        cls.arch = name
        _REGISTRY[name] = cls
        return cls

    return decorate


def get_refiner_class(arch: str) -> type[Refiner]:
    """The class registered as ``arch``.

    Raises:
        ValueError: unknown ``arch``; the message lists the registered names.
    """
    _register_builtin()
    try:
        return _REGISTRY[arch]
    except (KeyError, TypeError):
        raise ValueError(f"unknown refiner arch {arch!r}; registered: {list_refiners()}") from None


def list_refiners() -> list[str]:
    """Registered architecture names, sorted."""
    _register_builtin()
    return sorted(_REGISTRY)


def _register_builtin() -> None:
    # Importing an architecture's module registers it; done on first lookup so that `models` imports lazily.
    import importlib

    for module in ("models.nets.shallow", "models.nets.vggm", "models.nets.fusion"):
        importlib.import_module(module)


def build_refiner(arch: str, **config) -> Refiner:
    """Build a refiner by name.

    Args:
        arch: registered name, e.g. ``"shallow"`` (paper, 64x64 input) or ``"vggm"`` (224x224 input).
        **config: overrides of the architecture's default config (see its class docstring).

    Returns:
        The model (training mode, freshly initialised). ``model.config`` is the complete config.

    Raises:
        ValueError: unknown ``arch``, unknown config key or invalid config value.
    """
    return get_refiner_class(arch)(**config)
