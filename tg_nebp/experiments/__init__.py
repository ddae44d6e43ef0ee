r"""The experiment drivers: each runs methods on datasets through the
evaluation layer and writes resumable results, tables and figures."""
from . import compare

__all__ = ['compare']
