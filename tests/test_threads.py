"""inference.threads: host work on a thread per core, matching's products on one BLAS thread."""

import contextlib
import threading
import time

import cv2
import numpy as np
import threadpoolctl

from usp_jax import sfm
from usp_jax.inference import threads
from usp_jax.inference.features import Features
from usp_jax.inference.matching import nearest_neighbours
from usp_jax.inference.threads import one_blas_thread


def blas_threads() -> set[int]:
    return {
        lib["num_threads"] for lib in threadpoolctl.threadpool_info() if lib["user_api"] == "blas"
    }


def test_one_blas_thread_inside_and_the_callers_count_after():
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        with one_blas_thread:
            assert blas_threads() == {1}
            with one_blas_thread:  # re-entrant
                assert blas_threads() == {1}
            assert blas_threads() == {1}
        assert blas_threads() == {2}


def test_other_threads_share_the_main_threads_limit_and_change_nothing_themselves():
    seen = []

    def worker():
        with one_blas_thread:
            seen.append(blas_threads())
        seen.append(blas_threads())

    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        for outer in (one_blas_thread, contextlib.nullcontext()):
            with outer:
                thread = threading.Thread(target=worker)
                thread.start()
                thread.join(5)
        assert seen == [{1}, {1}, {2}, {2}]
        assert blas_threads() == {2}


def test_matching_leaves_the_blas_threads_as_it_found_them():
    rng = np.random.default_rng(0)
    descriptors = [rng.standard_normal((300, 64)).astype(np.float32) for _ in range(3)]
    features = [Features(rng.uniform(0, 50, (300, 2)), np.ones(300), d) for d in descriptors]
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        assert len(nearest_neighbours(*descriptors[:2], cv2.NORM_L2, True)) > 0
        assert blas_threads() == {2}
        matches = sfm.match_pairs(features, sfm.image_pairs(3))
        assert blas_threads() == {2}
    # Threaded, in the pairs' order: each pair as matched alone.
    for (i, j), found in zip(sfm.image_pairs(3), matches, strict=True):
        np.testing.assert_array_equal(
            found, sfm.match_pairs([features[i], features[j]], np.array([[0, 1]]))[0]
        )


def test_threaded_returns_results_in_the_items_order_whichever_finishes_first(monkeypatch):
    monkeypatch.setattr(threads, "THREADS", 3)
    waited = []

    def slow_first(item):
        time.sleep(0.05 if item == 0 else 0.0)
        return item * item

    def progress(futures):
        waited.append(len(futures))
        return futures

    assert threads.threaded(slow_first, range(5), progress) == [0, 1, 4, 9, 16]
    assert waited == [5]
