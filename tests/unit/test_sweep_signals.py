"""A sweep worker's signals while a trial runs (sb3_td3x/sweeps/signals.py): a SIGTERM whose interrupt Python drops,
because the handler ran inside a finalizer, is sent again and stops the trial in its own code."""

import gc
import signal
import time

import pytest

from sb3_td3x.sweeps.signals import HeldSignals, SignalInterrupt


class _SignalledWhileFinalized:
    """Sends SIGTERM to this process from ``__del__``; the loop after it lets the handler run there, inside the
    finalizer, where Python drops what it raises ("Exception ignored in ...")."""

    def __del__(self) -> None:
        signal.raise_signal(signal.SIGTERM)
        for _ in range(1000):
            pass


def test_an_interrupt_dropped_in_a_finalizer_is_sent_again(capsys):
    held = HeldSignals()
    with held, pytest.raises(SignalInterrupt) as raised:
        with held.live():
            _SignalledWhileFinalized()  # finalized at once: the interrupt is raised and dropped inside __del__
            gc.collect()
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:  # the trial's own code: where the interrupt must act
                time.sleep(0.01)
    assert raised.value.signal_name == "SIGTERM" and held.received == "SIGTERM"
    assert "Traceback" not in capsys.readouterr().err
