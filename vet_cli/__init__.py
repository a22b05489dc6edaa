"""vet's command-line layer: thin click commands over :mod:`stages`."""
