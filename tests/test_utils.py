r"""Tests of :mod:`tg_nebp.utils`."""
import torch
from torch import Tensor
from torch_geometric import EdgeIndex, Index

from tg_nebp.utils import plain_tensor


def test_plain_tensor_strips_pyg_subclasses_without_copying():
    edges = torch.tensor([[0, 1, 2], [1, 2, 0]])
    edge_index = EdgeIndex(edges, sparse_size=(3, 3))
    index = Index(edges[1], dim_size=3)
    for wrapped, source in ((edge_index, edges), (index, edges[1]),
                            (edge_index[1], edges[1])):
        plain = plain_tensor(wrapped)
        assert type(plain) is Tensor
        assert plain.data_ptr() == source.data_ptr()  # zero-copy
        assert torch.equal(plain, source)
    assert plain_tensor(edges) is edges  # plain tensors pass through
