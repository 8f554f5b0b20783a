"""The BLAS thread limit the bake runs its chunks under (core/base/blas.py)."""
import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from prtt_addon.core.base.blas import single_threaded_blas


def _blas_threads():
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_single_threaded_inside_and_restored_after():
    assert _blas_threads(), "numpy's wheel bundles OpenBLAS: threadpoolctl should see it"
    with threadpool_limits(limits=2, user_api="blas"):       # a known starting point
        assert set(_blas_threads()) == {2}
        with single_threaded_blas():
            assert set(_blas_threads()) == {1}
            a = np.ones((64, 64))
            assert float((a @ a)[0, 0]) == 64.0
        assert set(_blas_threads()) == {2}


def test_restored_after_an_exception():
    with threadpool_limits(limits=2, user_api="blas"):
        try:
            with single_threaded_blas():
                raise RuntimeError("chunk failed")
        except RuntimeError:
            pass
        assert set(_blas_threads()) == {2}
