"""The experiments' tests run like the project's (``make test`` runs both): one torch thread per worker."""

import pytest


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread_per_worker():
    import torch

    torch.set_num_threads(1)
    yield
