r"""The registry of the models of :mod:`tg_nebp`, what both roles share
(:class:`Model`), and how a model is stored and rebuilt.

Every concrete model names itself at class creation, which registers it
(:obj:`class LaplaceRange(RangeModel, name='laplace-range')`; a complete
example is in the README and :obj:`tests/models/test_user_models.py`).

A model's configuration is :obj:`{"name": ..., "params": {...}}`
(:meth:`Model.config`): scenarios, dataset file names and checkpoints store
it, :func:`model_from_config` rebuilds it, and a user's own class works
everywhere once the module that defines it is imported.

A fast path (closed-form gradient, fused kernel) belongs to the model that
it computes: the model provides it, and :meth:`Model.provides` hands it out
only while the class that defines the likelihood is the class that defines
the fast piece, so a subclass that overrides the likelihood alone can never
reach a fast path that computes another formula; it gets the generic
(autograd) path.
"""
import inspect
from typing import Any, ClassVar, Dict, Optional

__all__ = ['Model', 'MODELS', 'model_from_config', 'model_like']

#: The registered models by role (:obj:`"motion"`, :obj:`"measurement"`)
#: and name. Naming a subclass registers it.
MODELS: Dict[str, Dict[str, type]] = {'motion': {}, 'measurement': {}}



def _definer(cls: type, attribute: str) -> Optional[type]:
    # the class in the MRO that defines the attribute (a few dict lookups;
    # no cache wrapper, which torch.compile would warn about)
    for klass in cls.__mro__:
        if attribute in vars(klass):
            return klass
    return None


class Model:
    r"""What both roles share: a registered name, constructor parameters
    that are JSON values (:meth:`~tg_nebp.models.Model.params`), the
    configuration built from them, equality by configuration, and the
    fast-path gate (:meth:`~tg_nebp.models.Model.provides`)."""
    role: ClassVar[str] = ''
    name: ClassVar[str] = ''
    # the method whose formula the fast pieces compute, per role
    formula: ClassVar[str] = ''

    def __init_subclass__(cls, name: Optional[str] = None, **kwargs):
        super().__init_subclass__(**kwargs)
        if name is None:
            return
        if not isinstance(name, str) or not name:
            raise ValueError(f"a model's 'name' must be a non-empty string, "
                             f"got {name!r}")
        registry = MODELS[cls.role]
        known = registry.get(name)
        # re-running a module (a notebook cell) redefines its class
        if known is not None and known.__qualname__ != cls.__qualname__:
            raise ValueError(f"the {cls.role} model name '{name}' is taken "
                             f"by {known.__module__}.{known.__qualname__}")
        cls.name = name
        registry[name] = cls

    def params(self) -> Dict[str, Any]:
        r"""The constructor arguments as JSON values:
        :obj:`type(self)(**self.params())` rebuilds the model."""
        raise NotImplementedError(f'{type(self).__name__} must implement '
                                  f'params()')

    def config(self) -> Dict[str, Any]:
        r""":obj:`{"name": ..., "params": {...}}`, what scenarios, dataset
        file names and checkpoints store."""
        # a subclass without a name of its own would be stored, and
        # rebuilt, as its parent
        if MODELS[self.role].get(self.name) is not type(self):
            raise ValueError(f"{type(self).__name__} has no registered name "
                             f"of its own (class {type(self).__name__}(..., "
                             f"name='...')): it cannot be stored")
        return {'name': self.name, 'params': self.params()}

    def provides(self, piece: str) -> bool:
        r"""Whether the fast piece :obj:`piece` (a method name) may be used:
        it is defined, and by the class that defines this model's formula,
        so it computes the formula that the model has."""
        owner = _definer(type(self), piece)
        return owner is not None and owner is _definer(type(self),
                                                       self.formula)

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and other.params() == self.params()

    def __hash__(self) -> int:
        return hash((type(self), repr(sorted(self.params().items()))))

    def __repr__(self) -> str:
        args = ', '.join(f'{k}={v!r}' for k, v in self.params().items())
        return f'{type(self).__name__}({args})'


def model_like(name: str, role: str, like: Optional[Model] = None
               ) -> 'Model':
    r"""The registered model :obj:`name` of :obj:`role`, with the
    constructor parameters it shares with :obj:`like` (for example the
    :obj:`sigma` and :obj:`max_range` of a scenario's range model) and its
    own defaults otherwise; :obj:`like` itself if it is that model. Used to
    run a tracker with another likelihood than the one that generated the
    data."""
    registry = MODELS[role]
    if name not in registry:
        raise ValueError(f"unknown {role} model '{name}'; registered: "
                         f"{sorted(registry)}")
    if like is not None and like.name == name:
        return like
    cls = registry[name]
    accepted = inspect.signature(cls.__init__).parameters
    shared = {} if like is None else {
        key: value for key, value in like.params().items()
        if key in accepted}
    return cls(**shared)


def model_from_config(config: Any, role: str) -> 'Model':
    r"""Rebuilds a model of :obj:`role` (:obj:`"motion"` or
    :obj:`"measurement"`) from :meth:`Model.config`; an unknown name or bad
    parameters are a :class:`ValueError` that says which."""
    if role not in MODELS:
        raise ValueError(f"unknown model role '{role}'; the roles are "
                         f"{sorted(MODELS)}")
    registry = MODELS[role]
    if not (isinstance(config, dict) and set(config) == {'name', 'params'}
            and isinstance(config['name'], str)
            and isinstance(config['params'], dict)):
        raise ValueError(f"a {role} model configuration must be "
                         f"{{'name': <str>, 'params': {{...}}}}, got "
                         f"{config!r}")
    cls = registry.get(config['name'])
    if cls is None:
        raise ValueError(f"unknown {role} model '{config['name']}'; "
                         f"registered: {sorted(registry)} (import the module "
                         f"that defines it first)")
    try:
        return cls(**config['params'])
    except TypeError as e:
        raise ValueError(f"{role} model '{config['name']}': {e}") from None
