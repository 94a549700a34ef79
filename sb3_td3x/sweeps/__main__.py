"""``python -m sb3_td3x.sweeps --help``."""

import signal

from sb3_td3x.sweeps.cli import main

code = main()
# The worker has said what became of its trial; a signal while the interpreter shuts down changes nothing.
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
raise SystemExit(code)
