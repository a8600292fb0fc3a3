"""stop_within: the stop a wrapped exception carries along its causes, and nothing else."""

from __future__ import annotations

import pytest

from services.worker.run.stop_signal import reraise_stop, stop_within


def _wrapped(stop: BaseException) -> SystemError:
    try:
        raise stop
    except BaseException as e:  # noqa: BLE001 (what the interpreter does around a kernel's call)
        try:
            raise SystemError("returned a result with an exception set") from e
        except SystemError as wrapped:
            return wrapped


def test_the_stop_behind_a_wrapped_error_is_found_and_raised_again() -> None:
    wrapped = _wrapped(SystemExit(143))
    assert isinstance(stop_within(wrapped), SystemExit) and stop_within(wrapped).code == 143  # type: ignore[union-attr]
    assert isinstance(stop_within(_wrapped(KeyboardInterrupt())), KeyboardInterrupt)
    with pytest.raises(SystemExit):
        reraise_stop(wrapped)


def test_an_ordinary_failure_is_no_stop_even_with_a_cycle_of_causes() -> None:
    plain = _wrapped(ValueError("bad depth"))
    assert stop_within(plain) is None
    reraise_stop(plain)  # nothing raised
    a, b = RuntimeError("a"), RuntimeError("b")
    a.__cause__, b.__cause__ = b, a
    assert stop_within(a) is None
