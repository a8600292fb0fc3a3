"""A Ctrl-C landing inside a finalizer is dropped by Python; the generate loop's latch raises it again."""

from __future__ import annotations

import gc
import signal
import sys
import weakref

import pytest

from services.embedded.ctrl_c import latched_sigint, raise_if_interrupted


class _Collected:
    pass


def _sigint_inside_a_finalizer() -> None:
    """SIGINT delivered while a weakref callback runs, as when the collector frees an ORM object mid-loop."""
    obj = _Collected()
    ref = weakref.ref(obj, lambda _: signal.raise_signal(signal.SIGINT))
    del obj  # the callback runs here: its KeyboardInterrupt is printed ("Exception ignored") and dropped
    gc.collect()
    assert ref() is None


def test_a_ctrl_c_dropped_by_a_finalizer_is_raised_by_the_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    dropped: list[type[BaseException] | None] = []
    # what prints "Exception ignored"
    monkeypatch.setattr(sys, "unraisablehook", lambda u: dropped.append(u.exc_type))
    with latched_sigint():
        _sigint_inside_a_finalizer()  # returns: Python lost the KeyboardInterrupt ...
        assert dropped == [KeyboardInterrupt]
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted()  # ... the latch has not


def test_the_latch_raises_at_once_and_is_cleared_when_its_block_ends() -> None:
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        with latched_sigint():
            signal.raise_signal(signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is before
    raise_if_interrupted()  # nothing pending outside the block
    with latched_sigint():
        raise_if_interrupted()  # nor at the start of the next


def test_the_generate_loop_stops_on_a_dropped_ctrl_c(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    """run_until_final consults the latch each turn: a job far from done stops at once."""
    from services.embedded import ctrl_c
    from tests.embedded.test_tick import _run_fake

    monkeypatch.setattr(ctrl_c, "_interrupted", True)  # as a finalizer's dropped KeyboardInterrupt leaves it
    with pytest.raises(KeyboardInterrupt):
        _run_fake(tmp_path, messages=[], done_at=60.0)


def test_an_inner_latch_keeps_what_the_outer_one_remembered(monkeypatch: pytest.MonkeyPatch) -> None:
    """A block inside a latched one (latched_sigint composes) does not forget a Ctrl-C the outer one
    caught."""
    monkeypatch.setattr(sys, "unraisablehook", lambda u: None)
    with latched_sigint():
        _sigint_inside_a_finalizer()
        with latched_sigint():
            with pytest.raises(KeyboardInterrupt):
                raise_if_interrupted()
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted()
    raise_if_interrupted()
