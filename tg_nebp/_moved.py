r"""Aliases of the modules that moved into :mod:`tg_nebp.experiments`, kept
for one release so that existing imports keep working, with a
:class:`DeprecationWarning`."""
import importlib
import sys
import warnings


def alias(old: str, new: str) -> None:
    r"""Makes module :obj:`old` the module :obj:`new` (the same object, so
    that every name, private ones included, resolves as before)."""
    warnings.warn(f"{old} has moved to {new}; the old name will be removed "
                  f"in the next release", DeprecationWarning, stacklevel=3)
    sys.modules[old] = importlib.import_module(new)
