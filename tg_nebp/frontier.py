r"""Deprecated alias of :mod:`tg_nebp.experiments.frontier` (removed in the
next release)."""
from tg_nebp._moved import alias

alias(__name__, 'tg_nebp.experiments.frontier')
