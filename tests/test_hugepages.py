import numpy as np
import pytest

from twoscale._hugepages import ENV_VAR, _setter, avoid_hugepage_stalls


def _get():
    ma = getattr(np, "_core", np).multiarray
    return ma._get_madvise_hugepage()


@pytest.fixture
def restore_advice():
    before = _get()
    yield
    _setter()(before)


def test_advice_off_unless_the_user_chose(restore_advice):
    setter = _setter()
    assert setter is not None  # NumPy ≥ 1.19 on every platform
    setter(True)
    assert avoid_hugepage_stalls({ENV_VAR: "1"}) is False  # the user's choice stands
    assert _get() is True
    assert avoid_hugepage_stalls({}) is True
    assert _get() is False
