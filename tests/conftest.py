"""Shared test settings."""
from __future__ import annotations

import pytest
import torch


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One intra-op thread per test module (restored after it; module scope so that module-scoped fixtures such
    as precomputed tables get it too): the tests' tensors are small, and `make test` runs two
    pytest workers on two cores; with two threads each, waiting OpenMP threads spin and a fit burned 9-40x the CPU
    on a busy machine (docs/fitting.md, "Threads")."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
