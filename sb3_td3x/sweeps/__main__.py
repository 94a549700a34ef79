"""``python -m sb3_td3x.sweeps --help``."""

from sb3_td3x.experiment import stops
from sb3_td3x.sweeps.cli import main

code = main()
stops.ignore()  # the worker has said what became of its trial; a signal while the interpreter shuts down changes nothing
raise SystemExit(code)
