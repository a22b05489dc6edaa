"""``python -m stages.devices.lcos_emulator``."""

import sys

from .cli import main

sys.exit(main())
