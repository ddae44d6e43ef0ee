r"""Tests of :mod:`tg_nebp._moved`: the old paths of the modules that moved
into :mod:`tg_nebp.experiments` import the same module, with a
:class:`DeprecationWarning`."""
import importlib
import sys

import pytest

MOVED = {'tg_nebp.frontier': 'tg_nebp.experiments.frontier',
         'tg_nebp.reproduce': 'tg_nebp.experiments.reproduce',
         'tg_nebp.beyond': 'tg_nebp.experiments.equivariant_nebp',
         'tg_nebp.bench': 'tg_nebp.experiments.bench'}


@pytest.mark.parametrize('old', sorted(MOVED))
def test_old_path_is_the_new_module_with_a_warning(old, monkeypatch):
    new = importlib.import_module(MOVED[old])
    monkeypatch.delitem(sys.modules, old, raising=False)
    with pytest.warns(DeprecationWarning, match=MOVED[old]):
        module = importlib.import_module(old)
    assert module is new
    # private names resolve too, as before the move
    assert all(getattr(module, name) is getattr(new, name)
               for name in dir(new))
