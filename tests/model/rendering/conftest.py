"""Fixtures shared by the rendering tests."""

import pytest
import torch


@pytest.fixture()
def two_threads():
    """Two torch threads for the test (the suite runs on one), as the threaded chunk renderer uses."""
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)
