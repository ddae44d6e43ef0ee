import pytest
import torch


@pytest.fixture(autouse=True)
def one_thread():
    r"""The tests use tiny tensors: intra-op threads only add overhead, and
    spin-waiting OpenMP threads slow them down by an order of magnitude when
    other processes keep the CPUs busy."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
