"""``python -m stages.calibrate --selftest [--full]``: the calibration acceptance point."""

from .selftest import _main

raise SystemExit(_main())
