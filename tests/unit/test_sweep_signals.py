"""A sweep worker's signals while a trial runs (sb3_td3x/sweeps/signals.py): a SIGTERM whose interrupt Python drops,
because the handler ran inside a finalizer, is sent again and stops the trial in its own code.

Run in a child process: signal handlers belong to the main thread, which a test runner (pytest-xdist) may not give
a test."""

import subprocess
import sys

SCRIPT = r'''
import gc, signal, sys, time
from sb3_td3x.sweeps.signals import HeldSignals, SignalInterrupt

class SignalledWhileFinalized:
    """Sends SIGTERM to this process from __del__; the loop after it lets the handler run there, inside the
    finalizer, where Python drops what it raises ("Exception ignored in ...")."""

    def __del__(self):
        signal.raise_signal(signal.SIGTERM)
        for _ in range(1000):
            pass

held = HeldSignals()
with held:
    try:
        with held.live():
            SignalledWhileFinalized()  # finalized at once: the interrupt is raised and dropped inside __del__
            gc.collect()
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:  # the trial's own code: where the interrupt must act
                time.sleep(0.01)
        print("not interrupted")
    except SignalInterrupt as interrupt:
        print(f"interrupted by {interrupt.signal_name}; received {held.received}")
'''


def test_an_interrupt_dropped_in_a_finalizer_is_sent_again():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "interrupted by SIGTERM; received SIGTERM", result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
