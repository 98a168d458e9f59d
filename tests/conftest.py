"""Shared test fixtures."""

import pytest
import torch


@pytest.fixture
def one_thread():
    """Small solver problems run fastest (and most steadily on a shared machine) on one thread."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
