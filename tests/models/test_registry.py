r"""The registry of model roles (:mod:`tg_nebp.models.registry`): the
names that moved to it from :mod:`tg_nebp.models.base`."""
import pytest


def test_the_names_that_moved_out_of_base_still_import_with_a_warning():
    # MODELS, model_like and wrap_angle were documented in models.base
    # until the split: importable from there for a release, the warning
    # naming their new place; any other name is still an AttributeError
    import tg_nebp.models.base as base
    from tg_nebp.models import layout, registry
    for name, where in (('MODELS', registry), ('model_like', registry),
                        ('model_from_config', registry),
                        ('wrap_angle', layout)):
        with pytest.warns(DeprecationWarning,
                          match=f'moved to {where.__name__}.{name}'):
            assert getattr(base, name) is getattr(where, name)
    with pytest.raises(AttributeError, match='no_such_name'):
        base.no_such_name
