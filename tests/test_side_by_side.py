"""skyfit.fit.side_by_side: independent branches in forked processes, their results back in order."""

import os
import sys

import pytest
import torch

from skyfit.fit import side_by_side as sbs

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="branches fork only on Linux")


@pytest.fixture
def forking(monkeypatch):
    """Fork whatever the test process's threads (pytest's workers run one torch thread and execnet's threads)."""
    monkeypatch.setattr(sbs, "can_fork", lambda device="cpu": True)


def test_each_branch_after_the_first_runs_in_a_child_and_its_result_comes_back_in_order(forking):
    parent = os.getpid()
    calls = [lambda: (os.getpid(), torch.arange(4.0, dtype=torch.float64)),
             lambda: (os.getpid(), torch.full((2, 3), 5.0)),
             lambda: (os.getpid(), {"nested": [torch.tensor([1, 2]), "text"]})]
    out = sbs.side_by_side(calls)
    assert out[0][0] == parent
    assert out[1][0] != parent and out[2][0] != parent and out[1][0] != out[2][0]
    assert torch.equal(out[0][1], torch.arange(4.0, dtype=torch.float64))
    assert torch.equal(out[1][1], torch.full((2, 3), 5.0))
    assert torch.equal(out[2][1]["nested"][0], torch.tensor([1, 2])) and out[2][1]["nested"][1] == "text"


def test_what_a_child_changes_in_memory_stays_there(forking):
    seen = []
    out = sbs.side_by_side([lambda: seen.append("first") or len(seen), lambda: seen.append("second") or len(seen)])
    assert out == [1, 1] and seen == ["first"]


def test_a_childs_exception_is_raised_here(forking):
    def fails():
        raise ValueError("no circle found in photo.jpg")

    with pytest.raises(ValueError, match="no circle found in photo.jpg"):
        sbs.side_by_side([lambda: 1, fails])


def test_a_child_that_dies_or_returns_what_cannot_be_pickled_is_run_again_here(forking):
    parent = os.getpid()

    def dies_in_a_child():
        if os.getpid() != parent:
            os._exit(3)
        return "ran here"

    with pytest.warns(sbs.BranchLostWarning) as lost:
        out = sbs.side_by_side([lambda: 0, dies_in_a_child, lambda: (lambda: os.getpid())])
    assert len(lost) == 2 and "exit code 3" in str(lost[0].message) and "pickle" in str(lost[1].message)
    assert out[0] == 0 and out[1] == "ran here"
    assert out[2]() == parent  # a closure cannot be pickled: the branch ran again in this process


def test_torchs_threads_are_restored_after_the_branches(forking):
    n = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        inside = sbs.side_by_side([torch.get_num_threads, torch.get_num_threads])
        assert inside == [1, 1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(n)


def test_no_fork_where_it_is_not_safe_or_useful(monkeypatch):
    n = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        monkeypatch.setattr(sbs, "BENIGN_THREADS", ("tqdm_monitor",))
        monkeypatch.setattr(sbs.threading, "enumerate", lambda: [sbs.threading.current_thread()])
        assert sbs.can_fork("cpu") == sys.platform.startswith("linux")
        assert not sbs.can_fork("cuda")  # CUDA cannot be forked
        monkeypatch.setattr(sbs, "ENABLED", False)
        assert not sbs.can_fork("cpu")
        monkeypatch.setattr(sbs, "ENABLED", True)
        torch.set_num_threads(1)
        assert not sbs.can_fork("cpu")  # one thread: nothing to share out
        torch.set_num_threads(2)

        class Other:
            name = "dask-worker-io"

        monkeypatch.setattr(sbs.threading, "enumerate", lambda: [sbs.threading.current_thread(), Other()])
        assert not sbs.can_fork("cpu")  # another thread could hold a lock the child would inherit
        parent = os.getpid()
        assert sbs.side_by_side([os.getpid, os.getpid]) == [parent, parent]
    finally:
        torch.set_num_threads(n)
