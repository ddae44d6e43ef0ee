import os

import pytest
import torch

#: The intra-op threads of every test: 1 unless the environment's
#: TG_NEBP_TEST_THREADS says otherwise (to run the suite once at another
#: count, as on a machine whose BLAS splits its work differently).
TEST_THREADS = int(os.environ.get('TG_NEBP_TEST_THREADS', '1'))


@pytest.fixture(autouse=True)
def one_thread():
    r"""The tests use tiny tensors: intra-op threads only add overhead, and
    spin-waiting OpenMP threads slow them down by an order of magnitude when
    other processes keep the CPUs busy."""
    threads = torch.get_num_threads()
    torch.set_num_threads(TEST_THREADS)
    yield
    torch.set_num_threads(threads)
