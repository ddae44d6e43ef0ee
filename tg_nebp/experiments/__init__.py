r"""The experiment drivers: each runs methods on datasets through the
evaluation layer and writes resumable results, tables and figures. The
layers below (evaluation, plot, metrics, io) import none of them."""
from . import bench, compare, equivariant_nebp, frontier, reproduce

__all__ = ['compare', 'frontier', 'reproduce', 'equivariant_nebp', 'bench']
