"""``python -m sb3_td3x.sweeps --help``."""

from sb3_td3x.sweeps.cli import main

raise SystemExit(main())
