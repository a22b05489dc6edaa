"""vet's library: pure stages on arrays, file formats, rig physics and device drivers.

Nothing in here imports :mod:`vet_cli`; the command-line layer sits on top.
"""

__version__ = "0.1.0"
