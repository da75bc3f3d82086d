"""BLAS on one thread while the engine registers, the process's setting back afterwards."""

import threading

import numpy  # noqa: F401 - loads the BLAS the tests set
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from registration.core.blas import one_blas_thread, with_one_blas_thread


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


@pytest.fixture
def two_blas_threads():
    """The process's BLAS set to two threads for the test (whatever the machine's cores), so
    that one thread inside the block and two after it are both observable."""
    if not _blas_threads():
        pytest.skip("no BLAS library that threadpoolctl can set")
    with threadpool_limits(limits=2, user_api="blas"):
        assert set(_blas_threads()) == {2}
        yield


def test_one_thread_inside_and_the_setting_back_after(two_blas_threads):
    with one_blas_thread():
        assert set(_blas_threads()) == {1}
        with one_blas_thread():  # nested: still one, and leaving it keeps one
            assert set(_blas_threads()) == {1}
        assert set(_blas_threads()) == {1}
    assert set(_blas_threads()) == {2}


def test_an_exception_restores_the_setting(two_blas_threads):
    with pytest.raises(RuntimeError), one_blas_thread():
        raise RuntimeError("inside")
    assert set(_blas_threads()) == {2}


def test_concurrent_blocks_share_the_limit_until_the_last_leaves(two_blas_threads):
    """Two registrations in threads: the first to finish must not give the other BLAS threads
    back while it still works."""
    first_in, second_in, first_out, recorded, second_may_leave = (threading.Event() for _ in range(5))
    seen: dict[str, set[int]] = {}

    def first() -> None:
        with one_blas_thread():
            first_in.set()
            second_in.wait(10)
        first_out.set()

    def second() -> None:
        first_in.wait(10)
        with one_blas_thread():
            second_in.set()
            first_out.wait(10)
            seen["after the first left"] = set(_blas_threads())
            recorded.set()
            second_may_leave.wait(10)

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    assert recorded.wait(10)
    seen["while the second works"] = set(_blas_threads())
    second_may_leave.set()
    for t in threads:
        t.join(10)
    assert seen["after the first left"] == {1}
    assert seen["while the second works"] == {1}
    assert set(_blas_threads()) == {2}


def test_the_decorator_keeps_the_function(two_blas_threads):
    @with_one_blas_thread
    def threads_inside(x: int) -> tuple[int, list[int]]:
        """doc"""
        return x + 1, _blas_threads()

    assert threads_inside(1) == (2, [1] * len(_blas_threads()))
    assert threads_inside.__doc__ == "doc" and threads_inside.__name__ == "threads_inside"
    assert set(_blas_threads()) == {2}


def test_register_runs_with_one_blas_thread(two_blas_threads):
    import registration

    ex = registration.load_example("T1")
    seen: list[set[int]] = []

    def callback(progress) -> bool:  # noqa: ANN001
        seen.append(set(_blas_threads()))
        return True  # stop at the first iteration: only the setting during the run matters

    result = registration.register(ex.volume, ex.image, callback=callback)
    assert result.stopped and seen and all(s == {1} for s in seen)
    assert set(_blas_threads()) == {2}
