"""Suite-wide settings: one torch thread (tests are small; extra threads only contend on 2 cores)."""

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _single_thread():
    torch.set_num_threads(1)
    yield
