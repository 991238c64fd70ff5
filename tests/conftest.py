"""Suite-wide settings: one torch thread (much faster for the small models and sets here).

Session-wide, so that module fixtures run with it too: a compiled graph's guards hold the thread count, and a
fixture that prepared a layer's graphs with another count than its tests recompiles them at a control step."""
import pytest
import torch


@pytest.fixture(scope="session", autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
